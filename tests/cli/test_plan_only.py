"""``kc-train METHOD --data SCENE --plan-only``: the scene plan's table in seconds, nothing trained or written."""

from __future__ import annotations

import pytest

from kc_splatfacto.cli.train import main
from tests.conftest import shared_scene


def _plan_only(tmp_path, capsys, *args):
    code = main(["kc-splatfacto", "--data", "demo", "--plan-only", "--output-dir", str(tmp_path / "outputs"), *args,
                 "demo", "--width", "64", "--height", "48", "--demo-cache-dir", str(tmp_path / "cache")])
    return code, capsys.readouterr().out


def test_plan_only_prints_the_table_and_trains_nothing(tmp_path, capsys):
    code, out = _plan_only(tmp_path, capsys)
    assert code == 0
    assert out.startswith("scene plan for kc-splatfacto on demo (12 training views, 64x48):")
    for name in ("schedule", "downscales", "cbc", "background"):
        assert f"  {name} " in out
    assert "plan is off" not in out  # the registered methods train with their plan
    assert not (tmp_path / "outputs").exists()


def test_plan_only_shows_a_set_value_as_yours_and_says_when_the_plan_is_off(tmp_path, capsys):
    code, out = _plan_only(tmp_path, capsys, "--pipeline.model.num-downscales", "1")
    assert code == 0 and "1 (set by you)" in out and "plan is off" not in out
    code, out = _plan_only(tmp_path, capsys, "--pipeline.model.plan", "off")
    assert code == 0 and "the plan is off for this run" in out and "--pipeline.model.plan on applies them" in out


@pytest.mark.parametrize("scene, parser", [("castle-P30", "spars3r"), ("fern-12", "auto"), ("beer-12", "auto"),
                                           ("fountain-P11", "auto")])
def test_plan_only_works_on_the_shared_scenes(tmp_path, capsys, scene, parser, monkeypatch):
    monkeypatch.setenv("KC_SPLATFACTO_CACHE", str(tmp_path / "cache"))
    code = main(["kc-splatfacto", "--data", str(shared_scene(scene)), "--plan-only", parser, "--downscale-factor", "4"])
    out = capsys.readouterr().out
    assert code == 0 and out.startswith(f"scene plan for kc-splatfacto on {shared_scene(scene)}")
