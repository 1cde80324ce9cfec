"""The scene plan in ns-train: kc-train's rules on the training split nerfstudio's dataparser gives, so one scene gets
one plan in both (the cameras converted from nerfstudio's axes, its points moved by its own transform: view coverage
does not change under a similarity); the fixed settings one switch away."""

from __future__ import annotations

import copy

import pytest

pytest.importorskip("nerfstudio", reason="nerfstudio is not installed here: run `make test-nerfstudio`")

import torch  # noqa: E402

from kc_splatfacto.data.spars3r import Spars3rDataParserConfig  # noqa: E402
from kc_splatfacto.engine.scene_planning import plan_only  # noqa: E402
from kc_splatfacto.nerfstudio_plugin.configs import method_specifications  # noqa: E402
from kc_splatfacto.nerfstudio_plugin.dataparser import Spars3rNerfstudioDataParserConfig  # noqa: E402
from kc_splatfacto.nerfstudio_plugin.plan import plan_nerfstudio_run, project_cameras  # noqa: E402
from kc_splatfacto.plan.measure import project  # noqa: E402
from kc_splatfacto.registry import discover_methods  # noqa: E402
from tests.conftest import shared_scene  # noqa: E402


def _nerfstudio_config(method: str, scene, downscale: int):
    config = copy.deepcopy(method_specifications()[method].config)
    config.pipeline.datamanager.data = scene
    config.pipeline.datamanager.dataparser = Spars3rNerfstudioDataParserConfig(downscale_factor=downscale)
    return config


def _kc_train_config(method: str, scene, downscale: int):
    config = copy.deepcopy(discover_methods()[method].config)
    config.pipeline.datamanager.dataparser = Spars3rDataParserConfig(data=scene, downscale_factor=downscale)
    return config


def test_the_cameras_project_as_nerfstudios_own_projection_does():
    from nerfstudio.cameras.cameras import Cameras as NerfstudioCameras

    c2w = torch.tensor([[[1.0, 0, 0, 0.2], [0, 0.8, -0.6, -0.1], [0, 0.6, 0.8, 1.5]]])
    cameras = NerfstudioCameras(camera_to_worlds=c2w, fx=100.0, fy=110.0, cx=40.0, cy=30.0, width=80, height=60)
    # nerfstudio's OpenGL camera looks down -z: a camera-space point (x, y, -d) lands at (cx + fx x/d, cy - fy y/d)
    local = torch.tensor([0.1, -0.05, -2.0])
    point = (c2w[0, :3, :3] @ local + c2w[0, :3, 3])[None]
    expected_u = 40.0 + 100.0 * 0.1 / 2.0
    expected_v = 30.0 - 110.0 * -0.05 / 2.0
    u, v, seen = project(point, project_cameras(cameras))
    assert bool(seen[0, 0]) and abs(float(u[0, 0]) - float(expected_u)) < 1e-4
    assert abs(float(v[0, 0]) - float(expected_v)) < 1e-4


@pytest.mark.parametrize("method", ["kc-splatfacto", "splatfacto-cpu"])
def test_ns_train_and_kc_train_make_one_plan_of_a_scene(method, monkeypatch, tmp_path):
    monkeypatch.setenv("KC_SPLATFACTO_CACHE", str(tmp_path / "cache"))
    scene = shared_scene("castle-P30")
    ns_config = _nerfstudio_config(method, scene, 4)
    plan = plan_nerfstudio_run(ns_config, method_specifications()[method].config)
    ours = plan_only(_kc_train_config("kc-splatfacto" if method == "kc-splatfacto" else "splatfacto", scene, 4))
    assert [(d.name, d.field, d.asked, d.chosen, d.source) for d in plan.decisions] == \
        [(d.name, d.field, d.asked, d.chosen, d.source) for d in ours.decisions]
    schedule = next(d for d in plan.decisions if d.name == "schedule")
    assert schedule.measured == next(d for d in ours.decisions if d.name == "schedule").measured  # the coverage
    for dotted, value in plan.choices().items():  # applied to nerfstudio's config
        target = ns_config
        for part in dotted.split("."):
            target = getattr(target, part)
        assert target == value, dotted


def test_with_the_plan_off_ns_train_keeps_the_config():
    config = _nerfstudio_config("kc-splatfacto", shared_scene("castle-P30"), 4)
    config.pipeline.model.plan = "off"
    before = copy.deepcopy(config)
    assert plan_nerfstudio_run(config, method_specifications()["kc-splatfacto"].config) is None
    assert config.max_num_iterations == before.max_num_iterations
    assert config.pipeline.model.frequency == before.pipeline.model.frequency
