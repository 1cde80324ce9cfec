"""``kc-bench --resume`` on a tiny demo-scene study: finished runs reused, an interrupted run continued from its last
checkpoint to the same numbers as an uninterrupted study, no evaluation logged twice; a mismatching config refused."""

import json

import pytest

from kc_splatfacto.analysis import report
from kc_splatfacto.cli import bench
from kc_splatfacto.engine.metrics_log import read_metrics
from kc_splatfacto.engine.trainer import Trainer
from kc_splatfacto.study.machine import machine_signature, read_machines

# 12 steps, evaluations at log-spaced steps 1, 2, 5, 12; checkpoints every 4 steps; tiny images
ARGS = ["--data", "demo", "--methods", "splatfacto", "kc-splatfacto", "--seeds", "0", "--max-num-iterations", "12",
        "--num-evals", "4", "--steps-per-save", "4",
        "--set", "pipeline.model.steps_scale=0.02", "pipeline.model.num_downscales=0", "logging.steps_per_log=3"]
KILL_AT = 7  # steps completed when the second run dies: after the checkpoint at 4 and the evaluation at 5


def _bench(out, extra=()):
    return bench.entrypoint([*ARGS, "--output-dir", str(out), *extra])


def _metric_rows(out):
    return sorted((r["method"], r["step"], r["psnr"], r["ssim"], r["lpips"]) for r in report.read_rows_csv(out / "evals.csv"))


def test_resume_continues_an_interrupted_study(tmp_path, monkeypatch, capsys):
    assert bench.log_spaced_steps(12, 4) == (1, 2, 5, 12)
    reference = tmp_path / "uninterrupted"
    assert _bench(reference) == 0

    original = Trainer.train_iteration

    def dies_in_the_second_run(self, step):
        if self.config.method_name == "kc-splatfacto" and step == KILL_AT:
            raise RuntimeError("killed")  # as a killed process: no checkpoint written at the interruption
        return original(self, step)

    out = tmp_path / "study"
    monkeypatch.setattr(Trainer, "train_iteration", dies_in_the_second_run)
    assert _bench(out) == 1  # the failed run is reported with its folder and error; the study ends with exit 1
    monkeypatch.setattr(Trainer, "train_iteration", original)
    failed = [r for r in json.loads((out / "runs.json").read_text()) if r["status"] == "failed"]
    assert [(r["method"], r["error"].split(" (at")[0]) for r in failed] == [("kc-splatfacto", "RuntimeError: killed")]
    killed_dir = out / "runs" / "demo" / "kc-splatfacto" / "seed0"
    logged = read_metrics(killed_dir / "metrics.jsonl")
    assert [r["step"] for r in logged if r["kind"] == "eval"] == [1, 2, 5]  # the evaluation at 5 is past the checkpoint
    first_log = (out / "runs" / "demo" / "splatfacto" / "seed0" / "metrics.jsonl").read_text()

    # --report-only: the report of the finished run, nothing trained, the study's command kept
    command = (out / "command.txt").read_text()
    killed_log = (killed_dir / "metrics.jsonl").read_text()
    assert _bench(out, ["--report-only"]) == 0
    assert [(r["method"], r["status"]) for r in json.loads((out / "runs.json").read_text())] == [("splatfacto", "reused")]
    assert _metric_rows(out) == [row for row in _metric_rows(reference) if row[0] == "splatfacto"]
    assert (killed_dir / "metrics.jsonl").read_text() == killed_log and (out / "command.txt").read_text() == command

    assert _bench(out, ["--resume"]) == 0
    runs = json.loads((out / "runs.json").read_text())
    assert [(r["method"], r["status"]) for r in runs] == [("splatfacto", "reused"), ("kc-splatfacto", "resumed")]
    assert [r["run_dir"] for r in runs] == [str(out / "runs" / "demo" / m / "seed0") for m in ("splatfacto", "kc-splatfacto")]
    assert (out / "runs" / "demo" / "splatfacto" / "seed0" / "metrics.jsonl").read_text() == first_log  # untouched
    assert not (out / "runs" / "demo" / "kc-splatfacto" / "seed0_1").exists()
    # which machine trained which stretch: from step 0, then again from the step-4 checkpoint (machine.json)
    assert [e["from_step"] for e in read_machines(killed_dir)] == [0, 4]
    assert [e["from_step"] for e in read_machines(out / "runs" / "demo" / "splatfacto" / "seed0")] == [0]
    assert {r["cpu"] for r in report.read_rows_csv(out / "evals.csv")} == {machine_signature()["kind"]}

    records = read_metrics(killed_dir / "metrics.jsonl")
    for kind in ("eval", "train", "checkpoint"):
        steps = [r["step"] for r in records if r["kind"] == kind]
        assert steps == sorted(set(steps)), (kind, steps)  # nothing logged twice
    assert [r["step"] for r in records if r["kind"] == "eval"] == [1, 2, 5, 12]
    # CPU resume is bit-identical, so the continued study reports exactly the uninterrupted study's numbers
    assert _metric_rows(out) == _metric_rows(reference)

    # a third --resume reuses everything and appends nothing; the report is written once, not once per reused run
    writes = []
    monkeypatch.setattr(bench, "write_report", lambda *a, **k: writes.append(a) or report.write_report(*a, **k))
    assert _bench(out, ["--resume"]) == 0
    assert len(writes) == 1 and len(writes[0][0]) == len(report.read_rows_csv(reference / "evals.csv"))
    # both runs are in their folders: nothing is left to train from the first progress line on
    assert "[kc-bench] 0/2 finished, 1 running, 1 queued; ETA 0m00s" in capsys.readouterr().err
    assert [r["status"] for r in json.loads((out / "runs.json").read_text())] == ["reused", "reused"]
    assert read_metrics(killed_dir / "metrics.jsonl") == records
    assert _metric_rows(out) == _metric_rows(reference)


def test_a_run_cut_during_its_first_checkpoint_restarts_in_its_own_folder(tmp_path, monkeypatch):
    # a Ray task cancelled while it writes its first checkpoint leaves a checkpoint folder with no checkpoint (at most
    # the temp file of the unfinished write): the restarted run must train in the study's folder, where its
    # machine.json is, not in a sibling `seed0_1` whose report rows would have no CPU kind
    args = [*ARGS]
    args[args.index("--methods") + 1: args.index("--seeds")] = ["splatfacto"]
    reference, out = tmp_path / "uninterrupted", tmp_path / "study"
    assert bench.entrypoint([*args, "--output-dir", str(reference)]) == 0
    original = Trainer.train_iteration

    def dies_writing_the_first_checkpoint(self, step):
        if step == 3:
            folder = self.run_dir / "nerfstudio_models"
            folder.mkdir()
            (folder / ".step-000000004.ckpt.k3j2x9.tmp").write_bytes(b"half a checkpoint")
            raise RuntimeError("killed")
        return original(self, step)

    monkeypatch.setattr(Trainer, "train_iteration", dies_writing_the_first_checkpoint)
    assert bench.entrypoint([*args, "--output-dir", str(out)]) == 1
    monkeypatch.setattr(Trainer, "train_iteration", original)
    assert bench.entrypoint([*args, "--output-dir", str(out), "--resume"]) == 0
    run_dir = out / "runs" / "demo" / "splatfacto" / "seed0"
    [run] = json.loads((out / "runs.json").read_text())
    assert run["status"] == "restarted" and run["run_dir"] == str(run_dir)
    assert sorted(p.name for p in (out / "runs" / "demo" / "splatfacto").iterdir()) == ["seed0"]
    assert run["cpu"] == machine_signature()["kind"]
    assert {r["cpu"] for r in report.read_rows_csv(out / "evals.csv")} == {machine_signature()["kind"]}
    assert [e["from_step"] for e in read_machines(run_dir)] == [0]
    assert (run_dir / "nerfstudio_models.interrupted").is_dir() and (run_dir / "metrics.interrupted.jsonl").is_file()
    assert _metric_rows(out) == _metric_rows(reference)


def test_resume_refuses_a_run_folder_with_another_config(tmp_path, monkeypatch, capsys):
    out = tmp_path / "study"
    original = Trainer.train_iteration

    def dies(self, step):
        if step == KILL_AT:
            raise RuntimeError("killed")
        return original(self, step)

    monkeypatch.setattr(Trainer, "train_iteration", dies)
    assert _bench(out) == 1
    monkeypatch.setattr(Trainer, "train_iteration", original)
    other = ["--set", *ARGS[ARGS.index("--set") + 1:], "pipeline.model.ssim_lambda=0.5"]
    assert _bench(out, ["--resume", *other]) == 2
    err = capsys.readouterr().err
    assert "pipeline.model" in err and "seed0" in err and "--runs-dir" in err


@pytest.mark.parametrize("change", [["pipeline.model.ssim_lambda=0.5"], ["--downscale-factor", "2"]])
def test_resume_refuses_to_reuse_a_finished_run_of_other_settings(tmp_path, capsys, change):
    # a finished run is reused only when it was trained as this command asks: another model setting or another
    # dataparser setting (the image downscale) is an error naming the folder, not a silent reuse
    out = tmp_path / "study"
    args = [*ARGS]
    args[args.index("--methods") + 1: args.index("--seeds")] = ["splatfacto"]
    assert bench.entrypoint([*args, "--output-dir", str(out)]) == 0
    assert bench.entrypoint([*args, "--output-dir", str(out), "--resume"]) == 0  # same settings: reused
    assert json.loads((out / "runs.json").read_text())[0]["status"] == "reused"
    capsys.readouterr()
    assert bench.entrypoint([*args, *change, "--output-dir", str(out), "--resume"]) == 2
    err = capsys.readouterr().err
    assert "seed0" in err and "--runs-dir" in err


def test_runs_at_once_on_this_cpu_share_its_memory_budget(tmp_path, monkeypatch):
    """Issue 58 item 4: with --workers N on a local cluster each CPU run left at the default budget gets 1/N of the
    machine's (alone, each would count the memory the others are about to fill); a budget given is kept."""
    from kc_splatfacto.engine import memory

    monkeypatch.setattr(memory, "cpu_memory_it_may_use", lambda: 8_000_000_000)
    monkeypatch.setattr(bench, "cpu_memory_it_may_use", memory.cpu_memory_it_may_use)
    args = bench.build_parser().parse_args(["--data", "demo", "--methods", "splatfacto", "--seeds", "0", "1",
                                            "--max-num-iterations", "2", "--output-dir", str(tmp_path)])
    bench.check_bench_args(args)
    specs = bench.plan_runs(args, bench.discover_methods(), tmp_path / "runs")
    specs[1].config.machine.memory_budget_gb = 3.0
    bench.share_memory_budget(specs, workers=2)
    assert specs[0].config.machine.memory_budget_gb == round(8 * memory.BUDGET_FRACTION / 2, 2)
    assert specs[1].config.machine.memory_budget_gb == 3.0


def test_also_against_must_name_another_of_the_methods(tmp_path):
    def check(*extra):
        args = bench.build_parser().parse_args(["--data", "demo", "--methods", "splatfacto", "kc-splatfacto",
                                                "--output-dir", str(tmp_path), *extra])
        bench.check_bench_args(args)
        return args

    assert check("--also-against", "kc-splatfacto").also_against == ["kc-splatfacto"]
    with pytest.raises(bench.UserError, match="--also-against kc-splatfaco is not among --methods .*kc-splatfacto"):
        check("--also-against", "kc-splatfaco")
    with pytest.raises(bench.UserError, match="--also-against splatfacto is the baseline"):
        check("--also-against", "splatfacto")
