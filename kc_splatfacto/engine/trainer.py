"""The training loop: ``Trainer(config).train() -> run folder``.

Step convention: ``step`` in checkpoints and ``metrics.jsonl`` is the number of optimization steps completed
(``step-000000300.ckpt`` holds the state after 300 steps; an eval record with step 0 is the initial render). Inside an
iteration ``model.step`` is the 0-based index of the step being taken, which every schedule reads.

Stiff cases: a non-finite render, loss or gradient skips the step (no update, no density-control statistics; the
learning-rate schedule still advances so the run keeps its length); Gaussians whose parameters are non-finite are
removed (with their optimizer state) and that step is skipped: found by the rasterizer while it reads them, and by a
full scan every ``PARAMETER_SCAN_EVERY`` steps for values that render finitely. Each is a ``bad_step`` record. After ``max_consecutive_bad_steps`` in a row the state (still the last good
one, since bad updates were never applied) is saved and :class:`TrainingDivergedError` raised. Ctrl-C (SIGINT) or SIGTERM ends
the current step, saves a checkpoint and returns cleanly.

Resume (``load_dir``) restores the Gaussians, every optimizer and schedule, the density-control statistics, the
image order and the torch / numpy / python RNG states, so a resumed run continues exactly where it stopped.
"""

from __future__ import annotations

import math
import random
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch

from kc_splatfacto.engine.checkpoints import CHECKPOINT_DIR, save_checkpoint
from kc_splatfacto.engine.config import TrainerConfig, save_config
from kc_splatfacto.engine.evaluation import evaluate_split
from kc_splatfacto.engine.gradient_shares import gradient_shares
from kc_splatfacto.engine.logging import MetricsWriter, ProgressBar
from kc_splatfacto.engine.run_guard import announce_seed_points, plan_run, store_absolute_scene_path
from kc_splatfacto.engine.signals import install_stop_handlers, restore_handlers
from kc_splatfacto.model import ops
from kc_splatfacto.model.strategy import NoGaussiansLeftError
from kc_splatfacto.render.errors import NonFiniteInputError

GRAD_OVERFLOW = 1e18
"""a gradient this large would overflow Adam's squared-gradient average in float32 (1e36 < 3.4e38 just fits)"""
PARAMETER_SCAN_EVERY = 100
"""steps between full scans of the parameters for NaN/inf (the rasterizer reports what it reads every step)"""
PHASES = ("render", "losses", "backward", "optimizer", "density_control")

# a skipped (non-finite) step still advances the schedules, which torch reports as a misuse; it is deliberate here
warnings.filterwarnings("ignore", message="Detected call of `lr_scheduler.step\\(\\)` before `optimizer.step\\(\\)`")


def _max_abs(tensor: torch.Tensor) -> torch.Tensor:
    """max |x| (NaN if any x is NaN) in one read of the tensor: aminmax, not an |x| copy then a max."""
    if tensor.numel() == 0:
        return tensor.new_zeros(())
    low, high = torch.aminmax(tensor)
    return torch.maximum(-low, high)


class TrainingDivergedError(RuntimeError):
    """Too many consecutive non-finite steps."""


class Trainer:
    """Trains ``config.pipeline.model`` on ``config.pipeline.datamanager``'s scene."""

    def __init__(self, config: TrainerConfig):
        config.resolve_aliases()
        self.config = config
        self.device = config.machine.resolve_device()
        self.run_dir: Path | None = None
        self.model = None
        self.datamanager = None
        self.optimizers: dict[str, torch.optim.Optimizer] = {}
        self.schedulers: dict[str, Any] = {}
        self.start_step = 0
        self.interrupted = False
        self.phase_times = {name: 0.0 for name in PHASES}
        self.phase_steps = 0
        self.last_eval: dict[str, Any] | None = None
        self._stop_requested = False
        self._elapsed_offset = 0.0
        self._train_s = 0.0
        self._side_s = 0.0  # logging work inside a step (gradient shares), kept out of train_s
        self._bad_in_a_row = 0

    # ----------------------------------------------------------------------------------------------- set-up
    def setup(self) -> None:
        cfg = self.config
        plan = plan_run(cfg, map_location=self.device)  # bad settings and foreign resumes refused before data loads
        cfg.machine.seed_everything()
        self.datamanager = cfg.pipeline.datamanager.setup(seed=cfg.machine.seed)
        cfg.pipeline.datamanager.dataparser = self.datamanager.dataparser_config  # config.yml rebuilds the run
        store_absolute_scene_path(cfg)
        train_outputs = self.datamanager.train_outputs
        self.model = cfg.pipeline.model.setup(
            scene_scale=float(train_outputs.scene_scale),
            num_train_data=len(self.datamanager.train_dataset),
            seed_points=self.datamanager.seed_points(),
        ).to(self.device)
        announce_seed_points(self.datamanager, cfg.pipeline.model)
        self.model.train()
        self._build_optimizers()
        checkpoint = plan.checkpoint
        self.run_dir = plan.run_dir or self._new_run_dir()
        self.run_dir.mkdir(parents=True, exist_ok=True)
        save_config(cfg, self.run_dir / "config.yml")
        self.datamanager.save_dataparser_transform(self.run_dir / "dataparser_transforms.json")
        if checkpoint is not None:
            self._restore(checkpoint)

    def _new_run_dir(self) -> Path:
        base = self.config.base_dir()
        candidate, n = base, 1
        while (candidate / CHECKPOINT_DIR).exists() or (candidate / "metrics.jsonl").exists():
            candidate = base.with_name(f"{base.name}_{n}")
            n += 1
        if candidate != base:
            self.config.timestamp = candidate.name
        return candidate

    def _build_optimizers(self) -> None:
        # nominal schedules (nerfstudio's): steps_scale only, never max_num_iterations, so a short run is the first
        # steps of the full one
        self.optimizers, self.schedulers = self.config.optimizers.setup(
            self.model.gauss_params, steps_scale=self.config.pipeline.model.steps_scale
        )

    # ----------------------------------------------------------------------------------------------- checkpoints
    def _checkpoint_payload(self, step: int) -> dict[str, Any]:
        return {
            "step": step,
            "model": {k: v.detach().clone() for k, v in self.model.gauss_params.items()},
            "optimizers": {k: opt.state_dict() for k, opt in self.optimizers.items()},
            "schedulers": {k: s.state_dict() for k, s in self.schedulers.items()},
            "strategy_state": dict(self.model.strategy_state),
            "datamanager": self.datamanager.state_dict(),
            "rng": {
                "torch": torch.get_rng_state(),
                "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None,
                "numpy": np.random.get_state(),
                "python": random.getstate(),
            },
            "elapsed_s": self._elapsed(),
            "train_s": self._train_s,
        }

    def save_checkpoint(self, step: int) -> Path:
        path = save_checkpoint(
            self.run_dir / CHECKPOINT_DIR, step, self._checkpoint_payload(step), self.config.save_only_latest_checkpoint
        )
        self.writer.write({"kind": "checkpoint", "step": step, "elapsed_s": self._elapsed(),
                           "train_s": self._train_s, "path": str(path)})
        return path

    def _restore(self, ckpt: dict[str, Any]) -> None:
        self.model.load_gauss_params(ckpt["model"])
        self._build_optimizers()
        for name, state in ckpt["optimizers"].items():
            self.optimizers[name].load_state_dict(state)
        for name, state in ckpt["schedulers"].items():
            self.schedulers[name].load_state_dict(state)
        self.model.strategy_state = {
            k: (v.to(self.device) if isinstance(v, torch.Tensor) else v) for k, v in ckpt["strategy_state"].items()
        }
        self.datamanager.load_state_dict(ckpt["datamanager"])
        rng = ckpt["rng"]
        torch.set_rng_state(rng["torch"].cpu())
        if rng.get("cuda") is not None and torch.cuda.is_available():
            torch.cuda.set_rng_state_all([s.cpu() for s in rng["cuda"]])
        np.random.set_state(rng["numpy"])
        version, internal, gauss = rng["python"]
        random.setstate((version, tuple(internal), gauss))
        self.start_step = int(ckpt["step"])
        self.model.step = self.start_step
        self._elapsed_offset = float(ckpt.get("elapsed_s", 0.0))
        self._train_s = float(ckpt.get("train_s", 0.0))

    # ----------------------------------------------------------------------------------------------- helpers
    def _elapsed(self) -> float:
        return self._elapsed_offset + (time.perf_counter() - self._t0)

    def _sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    def _tick(self, phase: str, since: float) -> float:
        if self.config.logging.profile_phases:
            self._sync()
        now = time.perf_counter()
        self.phase_times[phase] += now - since
        return now

    def _on_sigint(self, signum, frame) -> None:  # noqa: ARG002
        if self._stop_requested:  # a second Ctrl-C aborts at once
            raise KeyboardInterrupt
        self._stop_requested = True

    def request_stop(self) -> None:
        """Finish the current step, save a checkpoint and return (what Ctrl-C does)."""
        self._stop_requested = True

    def evaluate(self, step: int) -> dict[str, Any]:
        result = evaluate_split(self.model, self.datamanager.eval_dataset)
        record = {"kind": "eval", "step": step, "elapsed_s": self._elapsed(), "train_s": self._train_s,
                  "split": self.config.pipeline.datamanager.eval_split}
        record.update({k: v for k, v in result.items() if k != "per_image"})
        record["per_image_psnr"] = [r["psnr"] for r in result["per_image"]]
        self.writer.write(record)
        self.last_eval = record
        return record

    def _should_eval(self, step: int) -> bool:
        every = self.config.steps_per_eval_all_images
        return step in self.config.eval_at_steps or (every > 0 and step % every == 0) or step == self.config.max_num_iterations

    # ----------------------------------------------------------------------------------------------- one step
    def _bad_step(self, step: int, reason: str) -> None:
        for param in self.model.gauss_params.values():
            param.grad = None
        self._bad_in_a_row += 1
        self.writer.write({"kind": "bad_step", "step": step, "elapsed_s": self._elapsed(), "train_s": self._train_s,
                           "reason": reason, "consecutive": self._bad_in_a_row})
        warnings.warn(f"step {step}: {reason}; step skipped", RuntimeWarning, stacklevel=2)
        if self._bad_in_a_row >= self.config.max_consecutive_bad_steps:
            path = self.save_checkpoint(step)  # bad updates were never applied: this is the last good state
            raise TrainingDivergedError(
                f"{self._bad_in_a_row} consecutive bad steps (last: {reason}) at step {step}: training stopped. "
                f"The last good state is saved in {path}. Lower the loss weights or the learning rates "
                f"(see docs/stability.md)."
            )

    def _grad_problem(self) -> str | None:
        params = [(k, p) for k, p in self.model.gauss_params.items() if p.grad is not None]
        if not params:
            return None
        peaks = torch.stack([_max_abs(p.grad) for _, p in params])
        if bool(torch.isfinite(peaks).all()) and float(peaks.max()) < GRAD_OVERFLOW:
            return None
        bad = [k for (k, _), v in zip(params, peaks.tolist()) if not (math.isfinite(v) and v < GRAD_OVERFLOW)]
        return f"non-finite or overflowing gradient of {bad}"

    @torch.no_grad()
    def _remove_non_finite_gaussians(self) -> int:
        params = self.model.gauss_params
        if all(bool(torch.isfinite(p).all()) for p in params.values()):
            return 0
        bad_rows = torch.zeros(len(params["means"]), dtype=torch.bool, device=params["means"].device)
        for p in params.values():
            bad_rows |= ~torch.isfinite(p.reshape(len(p), -1)).all(dim=-1)
        ops.remove(params, self.optimizers, self.model.strategy_state, bad_rows)
        if len(params["means"]) == 0:
            raise NoGaussiansLeftError("every Gaussian had non-finite parameters and was removed: nothing left to train")
        return int(bad_rows.sum())

    def _render_or_remove_non_finite(self, camera, step: int) -> tuple[dict[str, Any] | None, int]:
        """Render, or remove the Gaussians with non-finite parameters: (outputs, 0) or (None, count removed).

        The rasterizer finds NaN/inf in what it reads (``NonFiniteInputError``) at no extra cost; values that render
        finitely (an infinite opacity logit, a scale logit of -inf) are caught by a full scan every
        ``PARAMETER_SCAN_EVERY`` steps instead of every step.
        """
        if step % PARAMETER_SCAN_EVERY == 0:
            removed = self._remove_non_finite_gaussians()
            if removed:
                return None, removed
        try:
            return self.model.get_outputs(camera), 0
        except NonFiniteInputError:
            removed = self._remove_non_finite_gaussians()
            if not removed:  # a non-finite camera, not a parameter: a real error
                raise
            return None, removed

    def train_iteration(self, step: int) -> dict[str, Any]:
        """Take optimization step ``step`` (0-based). Returns the loss dict as floats (empty for a skipped step)."""
        model = self.model
        model.step = step
        index, camera, image = self.datamanager.next_train()
        bad = None
        loss_dict: dict[str, torch.Tensor] = {}
        t = time.perf_counter()
        outputs, removed = self._render_or_remove_non_finite(camera, step)
        t = self._tick("render", t)
        if removed:
            bad = f"non-finite parameters: {removed} Gaussians removed"
        if bad is not None:
            pass
        elif not bool(torch.isfinite(outputs["rgb"]).all()):
            bad = "non-finite render"
        else:
            loss_dict = model.get_loss_dict(outputs, {"image": image, "image_idx": index})
            loss = torch.stack(list(loss_dict.values())).sum()
            t = self._tick("losses", t)
            if not bool(torch.isfinite(loss)):
                bad = "non-finite loss (" + ", ".join(f"{k}={float(v.detach()):.4g}" for k, v in loss_dict.items()) + ")"
            else:
                self._log_gradient_shares(step + 1, loss_dict, outputs["rgb"])
                t = time.perf_counter()
                loss.backward()
                t = self._tick("backward", t)
                bad = self._grad_problem()
        if bad is None:
            for optimizer in self.optimizers.values():
                optimizer.step()
                optimizer.zero_grad(set_to_none=True)
            t = self._tick("optimizer", t)
            report = model.step_post_backward(self.optimizers, step)
            t = self._tick("density_control", t)
            if any(report.values()):
                self.writer.write({"kind": "densify", "step": step + 1, "elapsed_s": self._elapsed(),
                                   "train_s": self._train_s, "gaussian_count": model.num_points, **report})
        for scheduler in self.schedulers.values():
            scheduler.step()
        self.phase_steps += 1
        if bad is not None:
            self._bad_step(step + 1, bad)
            return {}
        self._bad_in_a_row = 0
        result = {k: float(v.detach()) for k, v in loss_dict.items()}
        result["loss"] = sum(result.values())
        self._last_outputs, self._last_batch = outputs, {"image": image, "image_idx": index}
        return result

    # ----------------------------------------------------------------------------------------------- the loop
    def train(self) -> Path:
        """Run (or resume) training; returns the run folder."""
        if self.model is None:
            self.setup()
        cfg = self.config
        self.writer = MetricsWriter(self.run_dir / "metrics.jsonl")
        self._t0 = time.perf_counter()
        previous_handlers = install_stop_handlers(self._on_sigint)  # SIGINT and SIGTERM: save and return
        bar = ProgressBar(cfg.max_num_iterations, self.start_step, enabled=cfg.logging.progress_bar)
        step = self.start_step
        try:
            if True:  # (no warnings.catch_warnings here: mutating filters re-enables once-only warnings every step)
                if step == 0 and 0 in cfg.eval_at_steps:
                    self.evaluate(0)
                losses: dict[str, float] = {}
                while step < cfg.max_num_iterations and not self._stop_requested:
                    t_step = time.perf_counter()
                    losses = self.train_iteration(step)
                    self._train_s += time.perf_counter() - t_step - self._side_s
                    self._side_s = 0.0
                    step += 1
                    if losses and step % cfg.logging.steps_per_log == 0:
                        self._log_train(step, losses)
                    bar.update(step, losses.get("loss"), self.model.num_points)
                    if self._should_eval(step):
                        self.evaluate(step)
                    if step % cfg.steps_per_save == 0 or step == cfg.max_num_iterations:
                        self.save_checkpoint(step)
                if self._stop_requested and step < cfg.max_num_iterations:
                    self.interrupted = True
                    path = self.save_checkpoint(step)
                    bar.close()
                    print(f"interrupted at step {step}: checkpoint saved to {path}; resume with --load-dir {path.parent}")
                    return self.run_dir
            bar.update(step, losses.get("loss") if losses else None, self.model.num_points, force=True)
            bar.close()
        finally:
            restore_handlers(previous_handlers)
            self.writer.close()
        return self.run_dir

    def _log_gradient_shares(self, step: int, loss_dict: dict[str, torch.Tensor], image: torch.Tensor) -> None:
        every = self.config.logging.steps_per_gradient_shares
        if every <= 0 or step % every != 0:
            return
        start = time.perf_counter()
        record = {"kind": "gradient_shares", "step": step, "elapsed_s": self._elapsed(), "train_s": self._train_s,
                  "reference": "main_loss", **gradient_shares(loss_dict, image)}
        self.writer.write(record)
        self._side_s += time.perf_counter() - start

    def _log_train(self, step: int, losses: dict[str, float]) -> None:
        record: dict[str, Any] = {"kind": "train", "step": step, "elapsed_s": self._elapsed(), "train_s": self._train_s}
        record.update(losses)
        metrics = self.model.get_metrics_dict(self._last_outputs, self._last_batch, with_kurtosis=True)
        record.update(metrics)
        record["lr_means"] = self.optimizers["means"].param_groups[0]["lr"]
        record["sh_degree"] = self.model.sh_degree_to_use()
        record["train_downscale"] = self.model.get_downscale_factor()
        self.writer.write(record)
