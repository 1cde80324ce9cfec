"""The GPU campaign (benchmarks/gpu_campaign.py, issue 36) without a GPU: its plan against the device tool's limits,
the wheels against the device image's packages, what travels, and the dry run of every phase on the CPU."""

import importlib.util
import json
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path
from types import SimpleNamespace

import pytest

from tests.conftest import PROJECT_ROOT, shared_scene

SPEC = importlib.util.spec_from_file_location("gpu_campaign", PROJECT_ROOT / "benchmarks" / "gpu_campaign.py")
campaign = importlib.util.module_from_spec(SPEC)
sys.modules["gpu_campaign"] = campaign  # dataclasses look their module up while the class is built
SPEC.loader.exec_module(campaign)

#: what lists the files a call sends needs a git checkout: a device call gets the working tree without .git
needs_git_checkout = pytest.mark.skipif(
    not (PROJECT_ROOT / ".git").exists() or shutil.which("git") is None,
    reason="not a git checkout with git installed (the device image's copy of the tree has no .git)")


def test_every_lease_fits_the_device_tools_limits():
    for name, calls in campaign.LEASES.items():
        assert campaign.check_plan(calls) == [], name
        # the tool's own numbers, written out here: 10 minutes a command, 15 minutes of device time a session, the
        # machine's start, 15 s between calls and 30 s for the close counted in
        assert all(c.timeout_s <= 600 and len(c.command()) <= 2000 for c in calls)
        assert 120 + sum(c.timeout_s for c in calls) + 15 * (len(calls) - 1) <= 15 * 60 - 30
    # what issue 36 asks of the first lease, in its order, and the study in a lease of its own
    assert [p for c in campaign.LEASES["full"] for p, _ in c.phases] == ["setup", "tests", "train", "bench", "suite",
                                                                         "pack"]
    assert "study" in [p for c in campaign.LEASES["study"] for p, _ in c.phases]
    # each lease carries what its phases read: the full lease the scenes of the GPU tests and the bench and the
    # nerfstudio plugin's wheels, the study its three scenes and the runs earlier leases finished
    full, = campaign.LEASES["full"]
    assert {".whl", ".whl-ns", ".gpu/site", ".gpu/data/castle-P30", ".gpu/data/fern-12",
            ".gpu/data/gsplat-test-garden"} <= set(full.carry)
    assert all({".whl", ".gpu/site", ".gpu/study", ".gpu/data/castle-P30", ".gpu/data/fern-12", ".gpu/data/flower-12"}
               <= set(c.carry) for c in campaign.LEASES["study"])


def test_the_study_queue_runs_each_seeds_pairs_before_the_low_pass_arm(tmp_path):
    """Issue 56's low-pass arm rides in the GPU study on fern-12 and flower-12 only, after each seed's pairs of the
    GPU issue's study: a lease cut short loses low-pass runs, never half a pair."""
    from kc_splatfacto.registry import discover_methods

    full = campaign.FULL
    assert set(full.methods) <= set(discover_methods())
    assert full.methods == ("splatfacto", "kc-splatfacto", "splatfacto-lowpass")
    queue = campaign.study_queue(tmp_path / "runs", full, done_before=set())
    assert len(queue) == len(full.seeds) * (2 * 3 + 2)
    assert queue[:8] == [("fern-12", "splatfacto", 0), ("fern-12", "kc-splatfacto", 0),
                         ("flower-12", "splatfacto", 0), ("flower-12", "kc-splatfacto", 0),
                         ("castle-P30", "splatfacto", 0), ("castle-P30", "kc-splatfacto", 0),
                         ("fern-12", "splatfacto-lowpass", 0), ("flower-12", "splatfacto-lowpass", 0)]
    assert queue[8] == ("fern-12", "splatfacto", 1)
    assert not any(scene == "castle-P30" and method == "splatfacto-lowpass" for scene, method, _ in queue)
    # what an earlier lease finished is left out, and nothing else
    later = campaign.study_queue(tmp_path / "runs", full, done_before={"fern-12/splatfacto-lowpass/seed0",
                                                                       "castle-P30/splatfacto/seed1"})
    assert sorted(set(queue) - set(later)) == [("castle-P30", "splatfacto", 1), ("fern-12", "splatfacto-lowpass", 0)]


def test_a_plan_over_the_limits_is_named():
    long_call = campaign.Call((("setup", 590), ("bench", 100)), "long")
    problems = campaign.check_plan((long_call, long_call, long_call))
    assert "long: 720 s is over the 600 s a command may run" in problems
    assert any(p.startswith("the plan needs 2310 s") and "over the 870 s it may use" in p for p in problems)
    # a session with less device time left than a lease: the plan is checked against what status says is left
    full = campaign.LEASES["full"]
    assert campaign.check_plan(full, device_s=900) == []
    assert campaign.check_plan(full, device_s=600) == [
        "the plan needs 720 s with the machine's start and the turnarounds, over the 570 s it may use (600 s of device"
        " time less 30 s for the close)"]
    assert campaign.check_plan((campaign.Call((("typo", 10),), "c"),)) == ["c: unknown phases ['typo']"]


def test_the_wheels_and_the_image_hold_what_the_project_imports():
    image = json.loads(campaign.IMAGE_FILE.read_text())
    lock = json.loads(campaign.LOCK_FILE.read_text())
    assert campaign.check_wheels(PROJECT_ROOT, lock, image) == []
    # the image lacks kornia (KINDS.md's list): a lock without its wheel is a problem that names it
    assert "kornia" not in {campaign.normalize(p) for p in image["packages"]}
    without = [e for e in lock if e["name"] != "kornia"]
    problems = campaign.check_wheels(PROJECT_ROOT, without, image)
    assert any(p.startswith("kornia: required by the project") for p in problems)
    assert any("WHEELS pins ['kornia']" in p for p in problems)
    # a wheel's requirement that nothing provides (tyro needs docstring-parser, which the image lacks)
    without = [e for e in lock if e["name"] != "docstring-parser"]
    assert any("requires docstring-parser" in p for p in campaign.check_wheels(PROJECT_ROOT, without, image))
    # the nerfstudio plugin's wheels: nerfstudio's import closure, whatever it needs besides is in the image
    ns_lock = json.loads(campaign.NS_LOCK_FILE.read_text())
    assert campaign.check_ns_wheels(lock, ns_lock, image) == []
    without = [e for e in ns_lock if e["name"] != "viser"]  # ns-train imports the viewer at module level
    problems = campaign.check_ns_wheels(lock, without, image)
    assert any(p.startswith("nerfstudio-1.1.5") and p.endswith("requires viser, neither in the device image nor "
                                                                "among the wheels") for p in problems)


def test_wheel_requirements_read_for_cpython_312_on_linux(tmp_path):
    wheel = tmp_path / "demo-1.0-py3-none-any.whl"
    metadata = "\n".join([
        "Metadata-Version: 2.1", "Name: demo", "Version: 1.0",
        "Requires-Dist: numpy>=1.21",
        "Requires-Dist: eval-type-backport>=0.1; python_version < '3.10'",  # another Python: left out
        "Requires-Dist: pywin32; sys_platform == 'win32'",  # another platform: left out
        "Requires-Dist: pytest; extra == 'test'",  # an extra: left out
        "Requires-Dist: Typing_Extensions>=4.0; python_version >= '3.8'",
    ])
    with zipfile.ZipFile(wheel, "w") as z:
        z.writestr("demo-1.0.dist-info/METADATA", metadata)
    assert campaign.wheel_requirements(wheel) == ["numpy", "typing-extensions"]


def _git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", *args], cwd=repo, check=True, capture_output=True, text=True).stdout


@pytest.mark.skipif(shutil.which("git") is None, reason="git is not installed")
def test_set_aside_keeps_the_files_and_restore_puts_them_back_in_the_index(tmp_path):
    repo = tmp_path / "repo"
    files = [".gitignore", "code.py", "docs/results/study-7k/runs/a/metrics.jsonl", "docs/results/study-7k/README.md",
             "docs/results/gpu/README.md", "docs/results/castle-P30/figure.png"]
    for f in files:
        (repo / f).parent.mkdir(parents=True, exist_ok=True)
        (repo / f).write_text(f)
    (repo / ".gitignore").write_text(".gpu/\n")  # as the project's
    _git(repo, "init", "-q")
    _git(repo, "add", ".")
    _git(repo, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "c")
    (repo / "docs/results/study-7k/runs/b").mkdir()
    (repo / "docs/results/study-7k/runs/b/metrics.jsonl").write_text("running")  # a study's untracked run

    folders = campaign.set_aside(repo)
    assert folders == ["docs/results/castle-P30", "docs/results/study-7k"]
    assert sorted(campaign.tracked_and_untracked(repo)) == [".gitignore", "code.py", "docs/results/gpu/README.md"]
    assert all((repo / f).is_file() for f in files)  # nothing deleted on disk
    assert _git(repo, "log", "--oneline", "--", "docs/results/study-7k")  # nor in the commits

    assert campaign.restore(repo) == folders
    assert _git(repo, "status", "--porcelain").split("\n")[0] == "?? docs/results/study-7k/runs/b/"
    assert set(files) <= set(campaign.tracked_and_untracked(repo))
    assert "gpu_campaign" not in (repo / ".git/info/exclude").read_text()
    assert (repo / ".git/info/exclude").read_text().startswith("# git ls-files")  # git's own lines kept
    assert campaign.restore(repo) == []  # twice: nothing to do


@needs_git_checkout
def test_the_dry_run_runs_every_phase_and_a_second_lease_reuses_the_first_ones_runs(tmp_path):
    """The whole campaign on the CPU with tiny budgets: setup, tests, training (one method of each model, strategy
    and set of loss terms: DRY_TRAIN_METHODS), bench,
    the study (two runs at once), packing under the device tool's limits, collecting with the study's report, and
    a second lease that trains nothing the first one finished."""
    for scene in campaign.SCENES:
        shared_scene(scene)
    work = tmp_path / "dry"
    proc = subprocess.run([sys.executable, str(PROJECT_ROOT / "benchmarks" / "gpu_campaign.py"), "dry-run",
                           "--workdir", str(work)], cwd=PROJECT_ROOT, capture_output=True, text=True, timeout=1500)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "dry-run: OK" in proc.stdout
    # the phases ran as on the device, without the distributions that do not travel (pycolmap: the scenes are text)
    hidden = {"PYTHONPATH": str(work / "absent-on-device")}
    probe = subprocess.run([sys.executable, "-c", "import pycolmap"], env=hidden, capture_output=True, text=True)
    assert probe.returncode != 0 and "import of pycolmap halted" in probe.stderr
    train_log = next((work / "first" / "logs").glob("call1-train.log")).read_text()
    from kc_splatfacto.registry import discover_methods

    assert set(campaign.DRY_TRAIN_METHODS) <= set(discover_methods())  # each one a registered method
    for method in campaign.DRY_TRAIN_METHODS:
        assert f"TRAIN {method} exit 0" in train_log
    bench_log = (work / "first" / "logs" / "call1-bench.log").read_text()
    assert bench_log.count("| kc-splatfacto |") == 1 and "syncs | launches" in bench_log
    results = (work / "collected" / "study" / "results.md").read_text()
    assert "fern-12" in results and "flower-12" in results
    # the low-pass arm against both arms of the pair: per-seed tables to splatfacto and to kc-splatfacto
    assert "differences to `splatfacto`" in results and "differences to `kc-splatfacto`" in results
    lowpass_rows = [line for line in results.splitlines() if line.startswith(f"| fern-12 | {campaign.LOWPASS_ARM} |")]
    assert len(lowpass_rows) >= 3, results  # its final metrics, and one row in each paired table
    # the suite's outcome by name, from its junit XML: counts, then each failure; skips by reason
    summary = (work / "first" / "logs" / "call1-suite-summary.txt").read_text()
    assert summary.splitlines()[0].endswith("0 failed, 0 error, 1 skipped")
    assert "SKIPPED x1: needs a CUDA device" in summary
    back = [f for call in ("call1", "study1") for f in (work / "first" / "out" / call).iterdir()]
    assert 0 < len(back) and all(f.stat().st_size < campaign.OUT_FILE_BYTES for f in back)


def test_the_dist_info_registers_the_methods_without_a_build(tmp_path):
    """The device's fallback when pip cannot build the project: entry points from pyproject.toml, found by
    importlib.metadata ahead of this environment's own installation."""
    info = campaign.write_dist_info(tmp_path)
    code = ("import importlib.metadata as m; eps = m.entry_points(group='kc_splatfacto.method_configs'); "
            "print(sorted(e.name for e in eps)); import pathlib; print(pathlib.Path(str(next(iter(eps)).dist._path)).resolve())")
    out = subprocess.run([sys.executable, "-c", code], env={"PYTHONPATH": str(tmp_path)}, cwd=tmp_path, capture_output=True,
                         text=True, check=True).stdout.splitlines()
    assert "kc-splatfacto" in out[0] and "splatfacto" in out[0]
    assert out[1] == str(info)
    import tomllib

    scripts = tomllib.loads((PROJECT_ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    assert f"kc-train = {scripts['kc-train']}" in (info / "entry_points.txt").read_text()


def test_a_phase_that_overruns_takes_its_time_from_the_later_phases_not_from_the_packing(tmp_path, monkeypatch):
    """A device call's timeout is the sum of its phases' budgets: when one runs over (setup's steps each have their
    own budget), the later phases get what is left and the packing its whole budget, so the logs still come back.
    A fake clock that only the phases move keeps it deterministic."""
    now = [0.0]
    monkeypatch.setattr(campaign, "time", SimpleNamespace(monotonic=lambda: now[0], strftime=lambda *a: "t"))
    monkeypatch.setattr(campaign.os, "environ", dict(campaign.os.environ))
    monkeypatch.setattr(campaign.sys, "path", list(campaign.sys.path))
    given: dict[str, float] = {}

    def phase(name: str, takes: float):
        def run(ctx, budget: float) -> int:
            given[name] = budget
            now[0] += takes
            return 0
        return run

    phases = {"setup": phase("setup", 170.0), "tests": phase("tests", 60.0), "bench": phase("bench", 10.0),
              "suite": phase("suite", 0.0), "pack": phase("pack", 5.0)}
    monkeypatch.setattr(campaign, "PHASES", phases)
    argv = ["device", "setup:110", "tests:60", "bench:100", "suite:20", "pack:15", "--call", "c", "--dry",
            "--work", str(tmp_path / "work"), "--out", str(tmp_path / "out")]
    # 305 s in all; setup overran by 60 s: tests keeps its 60 (305 - 170 - 15 left), bench gets 60 of its 100
    # (305 - 230 - 15), the suite its 20 (50 left after bench's 10 s), the packing its whole 15
    assert campaign.main(argv) == 0
    assert given == {"setup": 110, "tests": 60, "bench": 60, "suite": 20, "pack": 15}

    given.clear()
    now[0] = 0.0
    phases["setup"] = phase("setup", 290.0)  # over by 180 s: nothing left for the suite; the packing still runs
    assert campaign.main([*argv[:-4], "--work", str(tmp_path / "work2"), "--out", str(tmp_path / "out2")]) == 124
    assert given == {"setup": 110, "pack": 15}


def test_a_phase_past_its_budget_is_interrupted_so_pytest_can_name_its_failures(tmp_path):
    """The first campaign's suite was killed at its budget and its log named none of its failures: a command past its
    budget now gets SIGINT first (pytest then prints its summary and writes its XML) and SIGKILL only after a grace."""
    ctx = campaign.Context(work=tmp_path, out=tmp_path / "out", call="c", dry=True)
    waits = ("import signal, sys, time\n"
             "def stop(*_):\n    print('summary: 2 failed', flush=True)\n    sys.exit(2)\n"
             "signal.signal(signal.SIGINT, stop)\nprint('started', flush=True)\ntime.sleep(60)\n")
    assert ctx.run("suite", [sys.executable, "-c", waits], campaign.INTERRUPT_GRACE_S + 3) == 124
    log = ctx.log("suite").read_text()
    assert "summary: 2 failed" in log and "[exit 124]" in log
    deaf = "import signal, time\nsignal.signal(signal.SIGINT, signal.SIG_IGN)\ntime.sleep(60)\n"  # ignores SIGINT
    assert ctx.run("deaf", [sys.executable, "-c", deaf], campaign.INTERRUPT_GRACE_S + 1) == 124


def test_the_bench_counts_ordinary_training_steps_only(tmp_path, monkeypatch):
    """bench_gpu's synchronisation/launch count covers training steps alone: the first campaign counted train()
    through a run's last step, whose evaluation of every test image and checkpoint swelled the counts per step."""
    from tests.training_utils import tiny_demo_config

    spec = importlib.util.spec_from_file_location("bench_gpu", PROJECT_ROOT / "benchmarks" / "bench_gpu.py")
    bench = importlib.util.module_from_spec(spec)
    monkeypatch.setattr(sys, "path", list(sys.path))
    spec.loader.exec_module(bench)
    from kc_splatfacto.engine.trainer import Trainer
    from kc_splatfacto.engine.training_state import PARAMETER_SCAN_EVERY

    trainer = Trainer(tiny_demo_config("splatfacto", tmp_path, iterations=PARAMETER_SCAN_EVERY - 2))
    trainer.train()
    counted: list[int] = []
    original = trainer.train_iteration
    monkeypatch.setattr(trainer, "train_iteration", lambda step: counted.append(step) or original(step))
    for name in ("evaluate", "save_checkpoint", "_log_train"):
        monkeypatch.setattr(trainer, name, lambda *a, name=name: pytest.fail(f"{name} inside the counted steps"))
    monkeypatch.setattr(bench, "count_syncs_and_launches", lambda run_steps, steps: (run_steps(), {"steps": steps})[1])
    assert bench.trainer_syncs(trainer, SimpleNamespace(device="cuda"), steps=5) == {"steps": 5}
    assert counted == [98, 99, 101, 102, 103]  # 100 is a parameter-scan step


def test_the_summary_names_each_failure_and_counts_skips_by_reason(tmp_path):
    """What the suite phase brings back: every failed and errored test by name with its message's first line (the
    first campaign's suite printed about 11 F and no names), skips counted per reason; from the log's summary lines
    when the run was cut before its XML was written."""
    xml = tmp_path / "suite.xml"
    xml.write_text(
        '<?xml version="1.0"?><testsuites><testsuite name="pytest">'
        '<testcase classname="tests.a" name="test_ok"/>'
        '<testcase classname="tests.a" name="test_bad"><failure message="assert 1 == 2&#10;more">tb</failure></testcase>'
        '<testcase classname="tests.b" name="test_fixture"><error message="fixture \'x\' not found">tb</error></testcase>'
        '<testcase classname="tests.c" name="test_gpu"><skipped message="needs a CUDA device"/></testcase>'
        '<testcase classname="tests.c" name="test_gpu2"><skipped message="needs a CUDA device"/></testcase>'
        '</testsuite></testsuites>')
    summary = campaign.summarise_junit(xml, tmp_path / "unused.log").splitlines()
    assert summary == ["1 passed, 1 failed, 1 error, 2 skipped", "FAILURE tests.a::test_bad: assert 1 == 2",
                       "ERROR tests.b::test_fixture: fixture 'x' not found", "SKIPPED x2: needs a CUDA device"]
    log = tmp_path / "suite.log"
    log.write_text("..F.\nFAILED tests/a.py::test_bad - assert 1 == 2\n!!! KeyboardInterrupt !!!\n")
    cut = campaign.summarise_junit(tmp_path / "missing.xml", log).splitlines()
    assert cut[0].startswith("no junit XML") and cut[1:] == ["FAILED tests/a.py::test_bad - assert 1 == 2"]


def test_the_profile_script_runs_its_plumbing_on_the_cpu():
    """benchmarks/profile_gpu_step.py on the CPU with tiny settings, through the same configuration path as on CUDA
    (it once raised AttributeError before its first step: ``args.device``, which bench_gpu's config reads, was never
    set); it profiles ordinary steps of both methods and states the device's share (none on the CPU)."""
    scene = shared_scene("castle-P30")
    proc = subprocess.run([sys.executable, str(PROJECT_ROOT / "benchmarks" / "profile_gpu_step.py"), "--device", "cpu",
                           "--scene", str(scene), "--downscale", "8", "--warmup-steps", "3", "--steps", "2",
                           "--rows", "5"], cwd=PROJECT_ROOT, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    for method in ("splatfacto", "kc-splatfacto"):
        assert f"==== {method}: 2 ordinary steps" in proc.stdout
        assert f"==== {method}: by device time" not in proc.stdout  # no device on the CPU
        assert "0 % of the wall time" in proc.stdout
