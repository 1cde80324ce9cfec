"""Tiny demo-scene training runs shared by the CLI tests: each (method, steps) is trained once per test session."""

from __future__ import annotations

from pathlib import Path

import pytest

from kc_splatfacto.cli.bench import build_run_config, log_spaced_steps

#: Steps of the shared run: enough for evaluations at several log-spaced steps, seconds on the demo scene.
DEMO_STEPS = 30
_CACHE: dict[tuple[str, int], Path] = {}


def demo_run(tmp_path_factory: pytest.TempPathFactory, method: str = "kc-splatfacto", steps: int = DEMO_STEPS) -> Path:
    """The config.yml of a finished `steps`-step demo run of `method` (CPU, seed 0)."""
    key = (method, steps)
    if key not in _CACHE:
        from kc_splatfacto.engine.trainer import Trainer
        from kc_splatfacto.registry import discover_methods

        config = build_run_config(
            discover_methods()[method].config, method=method, data=Path("demo"), seed=0, max_steps=steps,
            eval_steps=log_spaced_steps(steps, 4), runs_dir=tmp_path_factory.mktemp("runs"), experiment="demo",
            downscale_factor=None, steps_scale=steps / 30000, device="cpu",
        )
        config.logging.steps_per_log = 5
        # the demo's shading is Lambertian, so the scene plan would leave out its SH: the tools' tests read and write
        # SH coefficients (export formats, renders), so the run keeps the method's degree
        config.pipeline.model.plan_skip = ("sh",)
        run_dir = Path(Trainer(config).train())
        _CACHE[key] = run_dir / "config.yml"
    return _CACHE[key]
