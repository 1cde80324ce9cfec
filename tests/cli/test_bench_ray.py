"""``kc-bench`` on Ray: a 2-worker local study stopped by SIGTERM (Ctrl-C takes the same path) keeps its finished
runs and, resumed, gives the serial study's numbers exactly (every evaluation and every logged value but the clocks);
so does a study submitted to a running cluster (``ray start``); a failed task is reported with its folder and error
while the others finish; without Ray, ``--workers 2`` is a one-line error.

Each Ray study here starts a cluster and worker processes (the slow part of the suite), so the stopped-and-resumed
study is also the check that 2 local workers give the serial numbers."""

from __future__ import annotations

import csv
import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from kc_splatfacto.cli import bench
from kc_splatfacto.engine.metrics_log import read_metrics
from kc_splatfacto.study.runs import numbers_only

REPO = Path(__file__).resolve().parents[2]
ARGS = ["--data", "demo", "--methods", "splatfacto", "kc-splatfacto", "--seeds", "0", "1", "--max-num-iterations",
        "12", "--num-evals", "3", "--steps-per-save", "4",
        "--set", "pipeline.model.steps_scale=0.02", "pipeline.model.num_downscales=0", "logging.steps_per_log=3"]
RUNS = [("demo", m, s) for s in (0, 1) for m in ("splatfacto", "kc-splatfacto")]
CLOCKS = ("elapsed_s", "train_s", "train_cpu_s", "run_dir")


def _ray():
    return pytest.importorskip("ray", reason="Ray is not installed (pip install 'kc-splatfacto[cluster]')")


def _bench(out: Path, *extra: str) -> int:
    return bench.entrypoint([*ARGS, "--output-dir", str(out), *extra])


def _evals(out: Path) -> list[dict]:
    with (out / "evals.csv").open() as handle:
        return [{k: v for k, v in row.items() if k not in CLOCKS} for row in csv.DictReader(handle)]


def _records(out: Path, run: tuple) -> list[dict]:
    return numbers_only(read_metrics(out / "runs" / run[0] / run[1] / f"seed{run[2]}" / "metrics.jsonl"))


def _logs(out: Path) -> dict[tuple, list[dict]]:
    """Every run's records but its checkpoints (see :func:`_checkpoint_steps`), without the clocks."""
    return {run: [r for r in _records(out, run) if r["kind"] != "checkpoint"] for run in RUNS}


def _checkpoint_steps(out: Path) -> dict[tuple, set[int]]:
    return {run: {r["step"] for r in _records(out, run) if r["kind"] == "checkpoint"} for run in RUNS}


def assert_same_study(out: Path, reference: Path) -> None:
    assert _evals(out) == _evals(reference)  # the report, row for row in the planned order
    assert _logs(out) == _logs(reference)  # every logged loss, metric, kurtosis, densification count
    # a task cancelled by the stop saves a checkpoint where it was (a step that depends on timing) on top of the
    # periodic ones, which every run has
    checkpoints, periodic = _checkpoint_steps(out), _checkpoint_steps(reference)
    assert all(checkpoints[run] >= periodic[run] for run in RUNS), (checkpoints, periodic)
    assert (out / "per_view.csv").read_text() == (reference / "per_view.csv").read_text()
    runs = json.loads((out / "runs.json").read_text())
    assert [(r["scene"], r["method"], r["seed"]) for r in runs] == RUNS


@pytest.fixture(scope="module")
def serial_study(tmp_path_factory) -> Path:
    """The serial path with one thread, as each worker below runs: the thread count changes float32 reduction order
    (the evaluations' sums), so equal numbers are only promised for equal threads. A subprocess, because torch's and
    numba's thread pools are fixed once they start."""
    out = tmp_path_factory.mktemp("serial") / "study"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-m", "kc_splatfacto.cli.bench", *ARGS, "--output-dir", str(out)],
                          env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    return out


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_study_submitted_to_a_running_cluster_gives_the_serial_numbers(serial_study, tmp_path):
    _ray()
    port = _free_port()
    ray_cli = Path(sys.executable).parent / "ray"
    head = subprocess.Popen(
        [str(ray_cli), "start", "--head", "--block", f"--port={port}", "--num-cpus=2", "--num-gpus=0",
         "--include-dashboard=false", "--disable-usage-stats"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env={**os.environ, "RAY_USAGE_STATS_ENABLED": "0"},
    )
    try:
        deadline = time.monotonic() + 120
        while True:  # the head's GCS port answers once the cluster is up
            assert head.poll() is None, head.stdout.read().decode(errors="replace")[-2000:]
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                assert time.monotonic() < deadline, "ray start --head did not come up in 120 s"
                time.sleep(1)
        out = tmp_path / "study"
        assert _bench(out, "--ray-address", f"127.0.0.1:{port}", "--threads", "1") == 0
        assert_same_study(out, serial_study)
    finally:
        head.terminate()  # `ray start --block` stops its own processes (never `ray stop`: it would stop every cluster)
        try:
            head.wait(timeout=60)
        except subprocess.TimeoutExpired:
            head.kill()


def _broken_scene(folder: Path) -> Path:
    """A transforms.json scene whose images are not images: the run fails when it loads them, inside its task."""
    folder.mkdir()
    frames = []
    for i in range(4):
        (folder / f"{i}.png").write_bytes(b"not a png")
        frames.append({"file_path": f"{i}.png", "transform_matrix": [[1, 0, 0, i * 0.1], [0, 1, 0, 0], [0, 0, 1, 2],
                                                                    [0, 0, 0, 1]]})
    (folder / "transforms.json").write_text(json.dumps(
        {"fl_x": 20.0, "fl_y": 20.0, "cx": 8.0, "cy": 8.0, "w": 16, "h": 16, "frames": frames}))
    return folder


def test_a_failed_task_is_reported_and_the_other_runs_finish(tmp_path, capsys):
    _ray()
    broken = _broken_scene(tmp_path / "broken")
    out = tmp_path / "study"
    args = [*ARGS]
    args[args.index("--data") + 1] = "demo"
    args.insert(args.index("--data") + 2, str(broken))
    args[args.index("--methods") + 1: args.index("--seeds")] = ["splatfacto"]
    args[args.index("--seeds") + 1: args.index("--max-num-iterations")] = ["0"]
    assert bench.entrypoint([*args, "--output-dir", str(out), "--workers", "2", "--threads", "1"]) == 1
    runs = {r["scene"]: r for r in json.loads((out / "runs.json").read_text())}
    assert runs["demo"]["status"] == "trained" and runs["broken"]["status"] == "failed"
    err = capsys.readouterr().err
    assert "1 of 2 runs failed" in err and str(Path("runs") / "broken" / "splatfacto" / "seed0") in err
    assert re.search(r"broken/\d\.png is corrupt", runs["broken"]["error"])  # the error names what was wrong
    assert {r["scene"] for r in csv.DictReader((out / "evals.csv").open())} == {"demo"}


def test_sigterm_cancels_the_tasks_keeps_finished_runs_and_resume_completes(serial_study, tmp_path, monkeypatch):
    """A real SIGTERM to this process (the driver) after the first result, while the other tasks run or wait: Ray's
    own handler would exit the driver at once; the study stops as on Ctrl-C instead."""
    _ray()
    out = tmp_path / "study"
    original = bench.Study.add
    handler_before = signal.getsignal(signal.SIGTERM)

    def terminate_after_the_first_result(self, result):
        original(self, result)
        os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(bench.Study, "add", terminate_after_the_first_result)
    assert _bench(out, "--workers", "2", "--threads", "1") == 130
    assert signal.getsignal(signal.SIGTERM) == handler_before  # neither ours nor Ray's handler is left behind
    monkeypatch.setattr(bench.Study, "add", original)
    finished = json.loads((out / "runs.json").read_text())
    assert len(finished) == 1 and finished[0]["status"] == "trained"
    kept = out / finished[0]["run_dir"] if not Path(finished[0]["run_dir"]).is_absolute() else Path(finished[0]["run_dir"])
    kept_log = (kept / "metrics.jsonl").read_text()
    assert any(r["kind"] == "eval" and r["step"] == 12 for r in read_metrics(kept / "metrics.jsonl"))

    assert _bench(out, "--workers", "2", "--threads", "1", "--resume") == 0
    statuses = {(r["method"], r["seed"]): r["status"] for r in json.loads((out / "runs.json").read_text())}
    assert statuses[(finished[0]["method"], finished[0]["seed"])] == "reused"
    assert (kept / "metrics.jsonl").read_text() == kept_log  # the finished run was not touched
    assert_same_study(out, serial_study)


def test_workers_without_ray_is_one_line_with_the_install_command(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    assert _bench(tmp_path / "study", "--workers", "2") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "kc-splatfacto[cluster]" in err[0] and "--workers 2" in err[0]
    assert not (tmp_path / "study" / "runs").exists()  # refused before any run
