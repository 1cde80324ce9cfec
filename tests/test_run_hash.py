"""benchmarks/run_hash.py: a run stopped before its last step gives no hash (its state is not the asked run's)."""

import importlib.util

from tests.conftest import PROJECT_ROOT, shared_scene

SPEC = importlib.util.spec_from_file_location("run_hash", PROJECT_ROOT / "benchmarks" / "run_hash.py")
run_hash = importlib.util.module_from_spec(SPEC)
SPEC.loader.exec_module(run_hash)


def _run(monkeypatch, capsys, trainer_class, steps: int) -> tuple[int, str, str]:
    monkeypatch.setattr(run_hash, "Trainer", trainer_class)
    monkeypatch.setattr("sys.argv", ["run_hash.py", "--method", "splatfacto", "--steps", str(steps),
                                     "--scene", str(shared_scene("castle-P30")), "--downscale", "8"])
    code = run_hash.main()
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_a_run_stopped_early_prints_no_hash(monkeypatch, capsys):
    """The stop arrives after step 1 of 3 (as SIGTERM would, through the trainer's own stop request): the script
    must fail without a hash line, where it printed the part-run's hash as the 3-step run's."""

    class StoppedAfterOneStep(run_hash.Trainer):
        def train_iteration(self, step):
            losses = super().train_iteration(step)
            self.request_stop()
            return losses

    code, out, err = _run(monkeypatch, capsys, StoppedAfterOneStep, steps=3)
    assert code == 130  # 128 + SIGINT, the kc-* tools' interrupted status
    assert "steps" not in out and "Gaussians" not in out
    assert "stopped before step 3" in err and "no hash" in err


def test_a_whole_run_prints_its_hash(monkeypatch, capsys):
    code, out, _ = _run(monkeypatch, capsys, run_hash.Trainer, steps=2)
    assert code == 0
    line = out.strip().splitlines()[-1]
    assert line.startswith("splatfacto 2 steps ") and "Gaussians" in line
    digest = line.split(": ")[1].split()[0]
    assert len(digest) == 16 and int(digest, 16) >= 0

