"""The nerfstudio commands on the plugin's runs, on this machine's CPU, as a nerfstudio user types them: a short
``ns-train kc-splatfacto --machine.device-type cpu`` on castle-P30 through ``spars3r`` and on fern-12 through
nerfstudio's own ``colmap`` parser trains with the three KC-3DGS terms in its loss dictionary and writes a checkpoint;
``ns-train splatfacto-cpu`` trains without them; ``--load-dir`` continues a run; ``ns-eval`` writes its JSON (PSNR,
SSIM, LPIPS); ``ns-export gaussian-splat`` writes a PLY the project's reader reads, one vertex per Gaussian;
``ns-render dataset`` renders every test view; ``ns-viewer`` serves its page."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

pytest.importorskip("nerfstudio", reason="nerfstudio is not installed here: run `make test-nerfstudio`")

import torch  # noqa: E402

from kc_splatfacto.data.ply import read_ply_vertices  # noqa: E402
from tests.conftest import shared_scene  # noqa: E402

pytestmark = pytest.mark.slow
TERMS = ("wavelet_loss", "kc_loss", "cbc_loss")
STEPS = 40
ENV = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
CPU_RUN = ["--machine.device-type", "cpu", "--vis", "tensorboard", "--timestamp", "run",
           "--steps-per-save", "20", "--logging.steps-per-log", "5"]


def ns(command: str, *args: str, cwd: Path, timeout: float = 600) -> subprocess.CompletedProcess:
    """An ``ns-*`` command of this environment (its console script beside this Python)."""
    script = Path(sys.executable).parent / command
    done = subprocess.run([str(script), *args], capture_output=True, text=True, env=ENV, cwd=cwd, timeout=timeout)
    assert done.returncode == 0, f"{command} {' '.join(args)} failed:\n{done.stdout[-2000:]}\n{done.stderr[-3000:]}"
    return done


def loss_terms(run: Path) -> dict[str, list[float]]:
    """The ``Train Loss Dict/*`` scalars of the run's tensorboard events."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    [events] = run.glob("events.out.tfevents.*")
    accumulator = EventAccumulator(str(events))
    accumulator.Reload()
    prefix = "Train Loss Dict/"
    return {tag[len(prefix):]: [e.value for e in accumulator.Scalars(tag)]
            for tag in accumulator.Tags()["scalars"] if tag.startswith(prefix)}


@pytest.fixture(scope="module")
def castle_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ns")
    ns("ns-train", "kc-splatfacto", *CPU_RUN, "--output-dir", str(out), "--max-num-iterations", str(STEPS),
       "--data", str(shared_scene("castle-P30")), "spars3r", "--downscale-factor", "4", cwd=out)
    return out / "castle-P30" / "kc-splatfacto" / "run"


def planned_downscales(run: Path) -> int:
    plan = json.loads((run / "plan.json").read_text())
    return next(d["chosen"] for d in plan["decisions"] if d["name"] == "downscales")


def test_ns_train_kc_splatfacto_on_a_spars3r_split_trains_its_plan_with_the_three_terms(castle_run):
    assert (castle_run / "config.yml").is_file() and (castle_run / "dataparser_transforms.json").is_file()
    assert sorted(p.name for p in (castle_run / "nerfstudio_models").iterdir())[-1] == f"step-{STEPS - 1:09d}.ckpt"
    assert planned_downscales(castle_run) == 1  # 192x128 halved twice, 48x32, holds 2 of 3 db3 levels
    assert "num_downscales: 1" in (castle_run / "config.yml").read_text()  # written again with the planned values
    terms = loss_terms(castle_run)
    for term in TERMS:
        assert len(terms[term]) >= STEPS // 5 - 1 and all(v >= 0 for v in terms[term]) and max(terms[term]) > 0, term
    checkpoint = torch.load(castle_run / "nerfstudio_models" / f"step-{STEPS - 1:09d}.ckpt", map_location="cpu")
    assert checkpoint["step"] == STEPS - 1  # torch.load's weights-only default reads it (no numpy scalars inside)


def test_ns_eval_writes_psnr_ssim_and_lpips(castle_run, tmp_path):
    ns("ns-eval", "--load-config", str(castle_run / "config.yml"), "--output-path", str(tmp_path / "eval.json"),
       cwd=tmp_path)
    results = json.loads((tmp_path / "eval.json").read_text())["results"]
    assert 5 < results["psnr"] < 40 and 0 < results["ssim"] < 1 and 0 < results["lpips"] < 1


def test_ns_export_writes_a_ply_the_project_reads(castle_run, tmp_path):
    ns("ns-export", "gaussian-splat", "--load-config", str(castle_run / "config.yml"), "--output-dir",
       str(tmp_path), cwd=tmp_path)
    vertices = read_ply_vertices(tmp_path / "splat.ply")
    state = torch.load(castle_run / "nerfstudio_models" / f"step-{STEPS - 1:09d}.ckpt", map_location="cpu")
    means = state["pipeline"]["_model.gauss_params.means"]
    assert len(vertices) == len(means)  # one vertex per Gaussian (ns-export would drop non-finite ones: none here)
    for axis, name in enumerate("xyz"):
        assert torch.equal(torch.from_numpy(vertices[name].astype("float32")), means[:, axis])


def test_ns_render_renders_the_test_views(castle_run, tmp_path):
    ns("ns-render", "dataset", "--load-config", str(castle_run / "config.yml"), "--output-path", str(tmp_path),
       "--split", "test", cwd=tmp_path)
    test_list = (shared_scene("castle-P30") / "test_list.txt").read_text().split()
    for kind in ("rgb", "gt-rgb", "depth"):
        assert len(list((tmp_path / "test" / kind).iterdir())) == len(test_list), kind


def test_load_dir_continues_the_run(castle_run, tmp_path):
    # nerfstudio's --max-num-iterations counts the steps of this invocation (kc-train's: the run's total)
    ns("ns-train", "kc-splatfacto", *CPU_RUN, "--output-dir", str(tmp_path), "--max-num-iterations", "10",
       "--load-dir", str(castle_run / "nerfstudio_models"),
       "--data", str(shared_scene("castle-P30")), "spars3r", "--downscale-factor", "4", cwd=tmp_path)
    continued = tmp_path / "castle-P30" / "kc-splatfacto" / "run"
    assert f"step-{STEPS + 9:09d}.ckpt" in {p.name for p in (continued / "nerfstudio_models").iterdir()}
    # the continued run trains the plan the first one made (read again, not measured anew), and records it
    assert (continued / "plan.json").read_text() == (castle_run / "plan.json").read_text()
    assert "num_downscales: 1" in (continued / "config.yml").read_text()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_ns_viewer_serves_its_page(castle_run, tmp_path):
    port = _free_port()
    viewer = subprocess.Popen([str(Path(sys.executable).parent / "ns-viewer"), "--load-config",
                               str(castle_run / "config.yml"), "--viewer.websocket-port", str(port)],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=ENV, cwd=tmp_path)
    try:
        deadline = time.monotonic() + 180
        while True:
            assert viewer.poll() is None, viewer.communicate()[0].decode(errors="replace")[-3000:]
            try:
                page = urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=5).read().decode()
                break
            except OSError:
                assert time.monotonic() < deadline, "ns-viewer did not serve its page within 180 s"
                time.sleep(1)
        assert "<html" in page.lower()
    finally:
        viewer.terminate()
        try:
            viewer.wait(timeout=30)
        except subprocess.TimeoutExpired:
            viewer.kill()


@pytest.mark.parametrize("method", ["kc-splatfacto", "splatfacto-cpu"])
def test_fern_through_nerfstudios_colmap_parser(method, tmp_path):
    # fern-12 as a plain COLMAP scene (its images and model linked, without the split lists): nerfstudio 1.1.5's colmap
    # parser, given train_list.txt and test_list.txt, asks for a validation_list.txt during training and stops, which
    # is what the spars3r parser is for; here it splits by its own interval rule
    fern, scene = shared_scene("fern-12"), tmp_path / "fern-plain"
    scene.mkdir()
    for name in ("images", "sparse"):
        (scene / name).symlink_to(fern / name)
    # with the scene plan off (the fixed settings: the paper's three terms, nerfstudio's own trainer's steps)
    ns("ns-train", method, *CPU_RUN, "--output-dir", str(tmp_path), "--max-num-iterations", "20",
       "--pipeline.model.plan", "off",
       "--data", str(scene), "colmap", "--colmap-path", "sparse/0", "--downscale-factor", "1", cwd=tmp_path)
    run = tmp_path / "fern-plain" / method / "run"
    assert (run / "nerfstudio_models" / "step-000000019.ckpt").is_file() and not (run / "plan.json").exists()
    terms = loss_terms(run)
    if method == "kc-splatfacto":
        assert all(max(terms[t]) > 0 for t in TERMS)
    else:
        assert not set(TERMS) & set(terms) and "main_loss" in terms


def test_ns_train_splatfacto_mcmc_holds_its_cap_with_the_two_terms(tmp_path):
    # castle-P30's 1,787 seed points; refinements at steps 20 and 30: +5% (1,876), then the cap of 1,900
    ns("ns-train", "splatfacto-mcmc", *CPU_RUN, "--output-dir", str(tmp_path), "--max-num-iterations", str(STEPS),
       "--pipeline.model.warmup-length", "10", "--pipeline.model.refine-every", "10",
       "--pipeline.model.max-gs-num", "1900", "--data", str(shared_scene("castle-P30")), "spars3r",
       "--downscale-factor", "4", cwd=tmp_path)
    run = tmp_path / "castle-P30" / "splatfacto-mcmc" / "run"
    [checkpoint] = (run / "nerfstudio_models").glob("*.ckpt")
    state = torch.load(checkpoint, map_location="cpu", weights_only=True)["pipeline"]
    assert state["_model.gauss_params.means"].shape == (1900, 3)
    terms = loss_terms(run)
    assert terms["mcmc_opacity_reg"] and terms["mcmc_scale_reg"] and not set(TERMS) & set(terms)
