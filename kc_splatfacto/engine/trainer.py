"""The training loop: ``Trainer(config).train() -> run folder``.

The trainer keeps the loop, the clocks, checkpoints, evaluation and logging; each step is the training state's
(:class:`~kc_splatfacto.engine.training_state.TrainingState`: the model, its optimizers, density control). A bad step
(non-finite render, loss or gradient) is skipped, non-finite Gaussians are removed, and Ctrl-C or SIGTERM saves a
checkpoint from which a resume continues bit for bit. Step convention, records, resume rules and stiff cases:
docs/training.md and docs/stability.md.
"""

from __future__ import annotations

import copy
import datetime
import functools
import random
import time
import warnings
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import torch

from kc_splatfacto.data.base import DataParserConfig
from kc_splatfacto.engine.base_config import LoggingConfig, MachineConfig, ViewerConfig
from kc_splatfacto.engine.callbacks import RecordSink, TrainingCallback, TrainingCallbackLocation, run_callbacks
from kc_splatfacto.engine.checkpoints import (
    CHECKPOINT_DIR,
    RUN_IDENTITY_KEY,
    as_random_state,
    run_identity,
    save_checkpoint,
)
from kc_splatfacto.engine.config_file import save_config
from kc_splatfacto.engine.evaluation import FINAL_LPIPS_NETS
from kc_splatfacto.engine.gradient_shares import gradient_shares
from kc_splatfacto.engine.loggers import check_backends, logging_sinks
from kc_splatfacto.engine.memory import MemoryGuard
from kc_splatfacto.engine.metrics_log import LoggingFailedError, MetricsWriter, ProgressBar
from kc_splatfacto.engine.optimizers import OptimizersConfig
from kc_splatfacto.engine.pipeline import Pipeline, PipelineConfig
from kc_splatfacto.engine.run_guard import (
    announce_seed_points,
    check_training_image_sizes,
    plan_run,
    recorded_dataparser,
)
from kc_splatfacto.engine.scene_planning import apply_recorded_plan, plan_is_on, plan_scene
from kc_splatfacto.engine.signals import install_stop_handlers, restore_handlers
from kc_splatfacto.engine.training_state import BadStep, StepHooks, StepResult, TrainingState
from kc_splatfacto.engine.validation import validate_config
from kc_splatfacto.lpips import NETWORKS
from kc_splatfacto.plan.scene_plan import apply_choices
from kc_splatfacto.settings import drawn_from, each, integer, path_component, setting

PHASES = ("render", "losses", "backward", "optimizer", "density_control")


TIMESTAMP_FORMAT = "%Y-%m-%d_%H%M%S"


@dataclass
class TrainerConfig:
    """One training run (nerfstudio's ``TrainerConfig``/``ExperimentConfig`` field names); ``setup()`` builds the
    :class:`Trainer`."""

    method_name: str = "splatfacto"
    """registered method this config came from (a run folder component)"""
    experiment_name: str | None = setting(None, path_component())
    """run folder component; defaults to the scene folder's name"""
    output_dir: Path = Path("outputs")
    """root of the run folders"""
    timestamp: str = setting("{timestamp}", path_component())
    """run folder component; '{timestamp}' is replaced by the start time"""
    max_num_iterations: int = setting(30000, integer(1))
    """number of optimization steps"""
    steps_per_save: int = setting(2000, integer(1))
    """write a checkpoint every this many steps (and at the last one)"""
    steps_per_eval_all_images: int = setting(1000, integer(0))
    """evaluate the whole eval split every this many steps (0 turns it off; the last step is always evaluated)"""
    eval_at_steps: tuple[int, ...] = setting((), each(integer(0)))
    """extra evaluation steps (e.g. log-spaced ones for quality-against-time reports)"""
    final_lpips_nets: tuple[str, ...] = setting(FINAL_LPIPS_NETS, drawn_from(*NETWORKS))
    """further LPIPS backbones of the last step's evaluation (``lpips_vgg`` in its record; every evaluation has alex)"""
    eval_lpips_nets: tuple[str, ...] = setting((), drawn_from(*NETWORKS))
    """further LPIPS backbones of every evaluation (a study's LPIPS-VGG along training; ~10x AlexNet's time)"""
    save_only_latest_checkpoint: bool = True
    """delete older checkpoints after writing a new one"""
    load_dir: Path | None = None
    """resume from the newest checkpoint in this nerfstudio_models folder (or a run folder)"""
    load_step: int | None = setting(None, integer(0, optional=True))
    """resume from this step's checkpoint instead of the newest"""
    resume_from_other_run: bool = False
    """allow --load-dir of another scene's, method's or dataparser's run (continued in a new run folder)"""
    max_consecutive_bad_steps: int = setting(5, integer(1))
    """stop with an error after this many non-finite steps in a row (the last good state is saved)"""
    machine: MachineConfig = field(default_factory=MachineConfig)
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    optimizers: OptimizersConfig = field(default_factory=OptimizersConfig)
    logging: LoggingConfig = field(default_factory=LoggingConfig)
    viewer: ViewerConfig = field(default_factory=ViewerConfig)

    @classmethod
    def upgrade_fields(cls, fields: dict[str, Any]) -> dict[str, Any]:
        """A ``config.yml`` of an earlier version had a ``data`` field here (the ``--data`` alias, always empty in the
        files runs wrote): the scene is the dataparser's ``data``."""
        data = fields.pop("data", None)
        if data is not None and "pipeline" in fields:
            fields["pipeline"].datamanager.set_scene(data)
        return fields

    def base_dir(self, scene: Path) -> Path:
        """``output_dir/experiment/method/timestamp``, with '{timestamp}' filled in; the experiment defaults to the
        name of ``scene`` (the resolved dataparser's ``data``)."""
        experiment = self.experiment_name
        if experiment is None:
            experiment = Path(str(scene)).name or "unnamed"
        timestamp = self.timestamp
        if timestamp == "{timestamp}":
            timestamp = datetime.datetime.now().strftime(TIMESTAMP_FORMAT)
            self.timestamp = timestamp
        return Path(self.output_dir) / experiment / self.method_name / timestamp

    def setup(self) -> Trainer:
        return Trainer(self)


_T = TypeVar("_T")


def _set_up(value: _T | None, name: str) -> _T:
    """``value``, or a RuntimeError naming ``Trainer.<name>`` when it is None (setup() has not run)."""
    if value is None:
        raise RuntimeError(f"Trainer.{name} is set by Trainer.setup(), which has not run")
    return value


class StepLosses(Mapping[str, float]):
    """A step's loss terms and their sum ``loss`` as Python floats, read from the device on first access (all in
    one host synchronisation: on a logging step, a progress line, a callback), not after every step. The values are
    those of ``float(term)`` and their Python sum."""

    def __init__(self, terms: dict[str, torch.Tensor]):
        self._terms = terms
        self._floats: dict[str, float] | None = None

    def _read(self) -> dict[str, float]:
        if self._floats is None:
            values = torch.stack([t.reshape(()).double() for t in self._terms.values()]).tolist() if self._terms else []
            self._floats = dict(zip(self._terms, values))
            self._floats["loss"] = sum(values)
        return self._floats

    def __getitem__(self, key: str) -> float:
        return self._read()[key]

    def __iter__(self) -> Iterator[str]:
        return iter([*self._terms, "loss"])

    def __len__(self) -> int:
        return len(self._terms) + 1


def _warn_one_line(line: str) -> None:
    warnings.warn(line, RuntimeWarning, stacklevel=3)


class TrainingDivergedError(RuntimeError):
    """Too many consecutive non-finite steps."""


class Trainer:
    """Trains ``config.pipeline.model`` on ``config.pipeline.datamanager``'s scene."""

    def __init__(self, config: TrainerConfig):
        # the trainer fills in what it resolves (the timestamp) on its own copy: the caller's config stays as given,
        # and config.yml records the resolved one
        config = copy.deepcopy(config)
        validate_config(config)  # once per run, before anything is resolved, loaded or written
        self.config = config
        self.device = config.machine.resolve_device()
        # set by setup(): read through the properties below, which say so when setup() has not run
        self._run_dir: Path | None = None
        self._dataparser: DataParserConfig | None = None  # the resolved one, from plan_run
        self._pipeline: Pipeline | None = None
        self._state: TrainingState | None = None
        self.start_step = 0
        self.interrupted = False
        self.phase_times = {name: 0.0 for name in PHASES}
        self.phase_steps = 0
        self.last_eval: dict[str, Any] | None = None
        self.last_losses: Mapping[str, float] = {}  # the last step's loss terms (for callbacks)
        self._writer: MetricsWriter | None = None  # opened by train()
        self._last_outputs: dict[str, Any] | None = None  # the last good step's render and batch (train records)
        self._last_batch: dict[str, Any] | None = None
        self._stop_requested = False
        self._elapsed_offset = 0.0
        self._train_s = 0.0
        self._train_cpu_s = 0.0  # CPU seconds of the training steps (all threads): a clock other processes barely move
        self._side_s = 0.0  # logging work inside a step (gradient shares), kept out of train_s
        self._side_cpu_s = 0.0
        self._memory: MemoryGuard | None = None  # the run's memory budget (setup)
        self._t0 = self._lap_start = time.perf_counter()  # both restarted when train() begins
        self.callbacks: list[TrainingCallback] = []
        self.record_sinks: list[RecordSink] = []

    def add_callbacks(self, callbacks: Sequence[TrainingCallback] = (), sinks: Sequence[RecordSink] = ()) -> None:
        """Register what watches the run (a viewer, a logger): see :mod:`kc_splatfacto.engine.callbacks`."""
        self.callbacks.extend(callbacks)
        self.record_sinks.extend(sinks)

    @property
    def pipeline(self) -> Pipeline:
        return _set_up(self._pipeline, "pipeline")

    @property
    def state(self) -> TrainingState:
        """The training state: the model, its optimizers and schedules, density control and its state."""
        return _set_up(self._state, "state")

    @property
    def optimizers(self) -> dict[str, torch.optim.Optimizer]:
        """The training state's optimizers, one per parameter group."""
        return self.state.optimizers

    @property
    def schedulers(self) -> dict[str, Any]:
        """The training state's learning-rate schedules."""
        return self.state.schedulers

    @property
    def run_dir(self) -> Path:
        return _set_up(self._run_dir, "run_dir")

    @property
    def dataparser(self) -> DataParserConfig:
        return _set_up(self._dataparser, "dataparser")

    @property
    def writer(self) -> MetricsWriter:
        """The run's ``metrics.jsonl`` writer (and its sinks), open while :meth:`train` runs."""
        if self._writer is None:
            raise RuntimeError("Trainer.writer is opened by Trainer.train(), which has not started")
        return self._writer

    @property
    def train_seconds(self) -> float:
        """Wall-clock seconds spent in training steps so far (evaluation, checkpoints and logging left out)."""
        return self._train_s

    @property
    def stop_requested(self) -> bool:
        """Whether Ctrl-C, SIGTERM or :meth:`request_stop` asked the run to stop after the current step."""
        return self._stop_requested

    @property
    def model(self):
        """The model, or None before setup()."""
        return self._pipeline.model if self._pipeline is not None else None

    @property
    def datamanager(self):
        """The data manager, or None before setup()."""
        return self._pipeline.datamanager if self._pipeline is not None else None

    # ----------------------------------------------------------------------------------------------- set-up
    def setup(self) -> None:
        cfg = self.config
        check_backends(cfg.logging)  # a logging package that cannot load: refused before any folder is made
        apply_recorded_plan(cfg)  # a resume continues with the plan its run recorded
        plan = plan_run(cfg, map_location=self.device)  # foreign resumes, unwritable folders refused before data loads
        self._dataparser = plan.dataparser
        cfg.machine.seed_everything()
        datamanager = cfg.pipeline.datamanager.setup(seed=cfg.machine.seed, dataparser=plan.dataparser)
        self.scene_plan = None
        if plan_is_on(cfg) and plan.checkpoint is None:
            self.scene_plan = plan_scene(cfg, datamanager)
            apply_choices(cfg, self.scene_plan.choices())
            print(self.scene_plan.table(), flush=True)
        self._pipeline = cfg.pipeline.setup(device=self.device, seed=cfg.machine.seed, dataparser=plan.dataparser,
                                            datamanager=datamanager)
        check_training_image_sizes(self.datamanager, cfg.pipeline.model)
        announce_seed_points(self.datamanager, cfg.pipeline.model)
        self.model.train()
        self._state = TrainingState(self.model, cfg.optimizers, device_verdict=self._device_verdict())
        checkpoint = plan.checkpoint
        self._run_dir = plan.run_dir or self._new_run_dir()
        self.run_dir.mkdir(parents=True, exist_ok=True)
        save_config(recorded_config(cfg, plan.dataparser), self.run_dir / "config.yml")  # the planned values
        if self.scene_plan is not None:
            self.scene_plan.write(self.run_dir)
        self.datamanager.save_dataparser_transform(self.run_dir / "dataparser_transforms.json")
        if checkpoint is not None:
            self._restore(checkpoint)
        self._start_memory_guard(checkpoint.get("memory_cap") if checkpoint is not None else None)

    def _start_memory_guard(self, cap: int | None) -> None:
        """The run's memory budget: a warning when the Gaussian cap would not fit it; a cap the checkpoint recorded
        (the budget was reached before) applied again, so a resumed run grows as the uninterrupted one."""
        cameras = self.datamanager.train_dataset.cameras
        pixels = int((cameras.widths.long() * cameras.heights.long()).max())
        self._memory = MemoryGuard.start(self.device, self.config.machine.memory_budget_gb,
                                         self.config.pipeline.model.max_num_gaussians, self.model.num_points, pixels,
                                         announce=_warn_one_line)
        if cap is not None:
            self._memory.cap = int(cap)
            self.state.cap_gaussians(int(cap))

    def _check_memory(self, step: int) -> None:
        """After density control changed the count: growth capped at the memory budget (one line, one record)."""
        if self._memory is None:
            return
        line = self._memory.after_density_control(step, self.model.num_points, self.state.cap_gaussians)
        if line is not None:
            self.writer.write({"kind": "memory_cap", "step": step, "elapsed_s": self._elapsed(),
                               "train_s": self._train_s, "gaussian_count": self.model.num_points,
                               "budget_bytes": self._memory.budget})

    def _new_run_dir(self) -> Path:
        base = self.config.base_dir(self.dataparser.data)
        candidate, n = base, 1
        while (candidate / CHECKPOINT_DIR).exists() or (candidate / "metrics.jsonl").exists():
            candidate = base.with_name(f"{base.name}_{n}")
            n += 1
        if candidate != base:
            self.config.timestamp = candidate.name
        return candidate

    # ----------------------------------------------------------------------------------------------- checkpoints
    def _checkpoint_payload(self, step: int) -> dict[str, Any]:
        return {
            "step": step,
            RUN_IDENTITY_KEY: run_identity(self.config),
            **self.pipeline.state_dict(),  # model, datamanager (top-level: the format stays readable)
            **self.state.state_dict(),  # strategy_state, optimizers, schedulers
            "rng": {
                "torch": torch.get_rng_state(),
                "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None,
                "numpy": np.random.get_state(),
                "python": random.getstate(),
            },
            "elapsed_s": self._elapsed(),
            "train_s": self._train_s,
            "train_cpu_s": self._train_cpu_s,
            "memory_cap": self._memory.cap if self._memory is not None else None,
        }

    def save_checkpoint(self, step: int) -> Path:
        # a bad step waiting unread is recorded before the state it left is saved
        self._record_bad_steps(self.state.read_verdicts(), now=step)
        path = save_checkpoint(
            self.run_dir / CHECKPOINT_DIR, step, self._checkpoint_payload(step), self.config.save_only_latest_checkpoint
        )
        self.writer.write({"kind": "checkpoint", "step": step, "elapsed_s": self._elapsed(),
                           "train_s": self._train_s, "path": str(path)})
        return path

    def _restore(self, ckpt: dict[str, Any]) -> None:
        self.pipeline.load_state_dict(ckpt, step=int(ckpt["step"]))
        self.state.load_state_dict(ckpt)
        rng = ckpt["rng"]
        torch.set_rng_state(rng["torch"].cpu())
        if rng.get("cuda") is not None and torch.cuda.is_available():
            torch.cuda.set_rng_state_all([s.cpu() for s in rng["cuda"]])
        np.random.set_state(rng["numpy"])
        random.setstate(as_random_state(rng["python"]))
        self.start_step = int(ckpt["step"])
        self._elapsed_offset = float(ckpt.get("elapsed_s", 0.0))
        self._train_s = float(ckpt.get("train_s", 0.0))
        self._train_cpu_s = float(ckpt.get("train_cpu_s", 0.0))

    # ----------------------------------------------------------------------------------------------- helpers
    def _elapsed(self) -> float:
        return self._elapsed_offset + (time.perf_counter() - self._t0)

    def _sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    def _lap(self, phase: str) -> None:
        """Charge the time since the previous lap to ``phase`` (synchronized when ``profile_phases``)."""
        if self.config.logging.profile_phases:
            self._sync()
        now = time.perf_counter()
        self.phase_times[phase] += now - self._lap_start
        self._lap_start = now

    def _on_sigint(self, signum, frame) -> None:  # noqa: ARG002
        if self._stop_requested:  # a second Ctrl-C aborts at once
            raise KeyboardInterrupt
        self._stop_requested = True

    def request_stop(self) -> None:
        """Finish the current step, save a checkpoint and return (what Ctrl-C does)."""
        self._stop_requested = True

    def evaluate(self, step: int) -> dict[str, Any]:
        final = step == self.config.max_num_iterations
        nets = (*self.config.eval_lpips_nets, *(self.config.final_lpips_nets if final else ()))
        result = self.pipeline.get_average_eval_image_metrics(extra_lpips_nets=tuple(dict.fromkeys(nets)))
        record = {"kind": "eval", "step": step, "elapsed_s": self._elapsed(), "train_s": self._train_s,
                  "train_cpu_s": self._train_cpu_s, "split": self.config.pipeline.datamanager.eval_split}
        record.update({k: v for k, v in result.items() if k != "per_image"})
        record["per_image_psnr"] = [r["psnr"] for r in result["per_image"]]
        record["per_image"] = result["per_image"]
        self.writer.write(record)
        self.last_eval = record
        return record

    def _should_eval(self, step: int) -> bool:
        every = self.config.steps_per_eval_all_images
        return step in self.config.eval_at_steps or (every > 0 and step % every == 0) or step == self.config.max_num_iterations

    # ----------------------------------------------------------------------------------------------- one step
    def _device_verdict(self) -> bool:
        """``machine.step_verdict`` resolved: 'auto' takes it on the device on CUDA, where the host would wait for the
        step; on the CPU the wait costs nothing and a bad step is reported at once."""
        choice = self.config.machine.step_verdict
        return choice == "device" or (choice == "auto" and self.device.type == "cuda")

    def _record_bad_steps(self, bad_steps: list[BadStep], now: int) -> None:
        """Write out the bad steps the training state's verdicts gave (``now``: the steps taken so far, later than a
        bad step whose device verdict was read late: the state a divergence saves); stop a run diverging."""
        for bad in bad_steps:
            self.writer.write({"kind": "bad_step", "step": bad.step, "elapsed_s": self._elapsed(),
                               "train_s": self._train_s, "reason": bad.reason, "consecutive": bad.consecutive})
            warnings.warn(f"step {bad.step}: {bad.reason}; step skipped", RuntimeWarning, stacklevel=2)
            if bad.consecutive >= self.config.max_consecutive_bad_steps:
                path = self.save_checkpoint(now)  # bad updates were never applied
                raise TrainingDivergedError(
                    f"{bad.consecutive} consecutive bad steps (last: {bad.reason}) at step {bad.step}: training "
                    f"stopped. The last good state is saved in {path}. Lower the loss weights or the learning rates "
                    f"(see docs/stability.md)."
                )

    def _verdicts_due(self, taken: int) -> bool:
        """Whether the device verdicts waiting must be read after ``taken`` steps: before a log, an evaluation, a
        checkpoint or a stop (the training state reads them anyway when ``VERDICTS_READ_EVERY`` wait)."""
        cfg = self.config
        return (taken % cfg.logging.steps_per_log == 0 or self._should_eval(taken) or taken % cfg.steps_per_save == 0
                or taken == cfg.max_num_iterations or self._stop_requested)

    def train_iteration(self, step: int) -> Mapping[str, float]:
        """Take optimization step ``step`` (0-based) on the next training view: the training state's step, its bad
        steps written out. Returns the loss terms and ``loss`` as a :class:`StepLosses` (read from the device only
        when asked; empty for a skipped step, and for a bad one whose device verdict is read at once)."""
        self._lap_start = time.perf_counter()
        hooks = StepHooks(lap=self._lap, inspect_loss=functools.partial(self._log_gradient_shares, step + 1))
        result: StepResult = self.state.step(step, self.datamanager.next_train, hooks,
                                             read_verdicts=self._verdicts_due(step + 1))
        if any(result.density.values()):  # empty on a skipped step
            self.writer.write({"kind": "densify", "step": step + 1, "elapsed_s": self._elapsed(),
                               "train_s": self._train_s, "gaussian_count": self.model.num_points, **result.density})
            self._check_memory(step + 1)
        self.phase_steps += 1
        self._record_bad_steps(result.bad_steps, now=step + 1)
        if result.known_bad:
            return {}
        self._last_outputs, self._last_batch = result.outputs, result.batch
        return StepLosses(result.losses)

    # ----------------------------------------------------------------------------------------------- the loop
    def train(self) -> Path:
        """Run (or resume) training; returns the run folder."""
        if self._pipeline is None:
            self.setup()
        cfg = self.config
        # (no warnings.catch_warnings around the loop: mutating filters re-enables once-only warnings every step)
        recorded = recorded_config(cfg, self.dataparser) if cfg.logging.wandb else None
        sinks = logging_sinks(cfg.logging, self.run_dir, self.pipeline, recorded)
        self._writer = MetricsWriter(self.run_dir / "metrics.jsonl", sinks=[*sinks, *self.record_sinks])
        self._t0 = time.perf_counter()
        previous_handlers = install_stop_handlers(self._on_sigint)  # SIGINT and SIGTERM: save and return
        bar = ProgressBar(cfg.max_num_iterations, self.start_step, enabled=cfg.logging.progress_bar,
                          line_every=cfg.logging.steps_per_progress_line)
        step = self.start_step
        try:
            if step == 0 and 0 in cfg.eval_at_steps:
                self.evaluate(0)
            losses: Mapping[str, float] = {}
            while step < cfg.max_num_iterations and not self._stop_requested:
                run_callbacks(self.callbacks, step, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
                t_step, t_step_cpu = time.perf_counter(), time.process_time()
                losses = self.train_iteration(step)
                self._train_s += time.perf_counter() - t_step - self._side_s
                self._train_cpu_s += time.process_time() - t_step_cpu - self._side_cpu_s
                self._side_s = self._side_cpu_s = 0.0
                step += 1
                if losses and step % cfg.logging.steps_per_log == 0:
                    self._log_train(step, losses)
                bar.update(step, functools.partial(losses.get, "loss"), self.model.num_points)  # read when shown
                if self._should_eval(step):
                    self.evaluate(step)
                if step % cfg.steps_per_save == 0 or step == cfg.max_num_iterations:
                    self.save_checkpoint(step)
                self.last_losses = losses
                run_callbacks(self.callbacks, step, TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
                if self.writer.failure is not None:  # the step is whole: its state is saved, then one line
                    self._stop_for_logging(step)
            if self._stop_requested and step < cfg.max_num_iterations:
                self.interrupted = True
                path = self.save_checkpoint(step)
                bar.close()
                print(f"interrupted at step {step}: checkpoint saved to {path}; resume with --load-dir {path.parent}")
                return self.run_dir
            bar.update(step, losses.get("loss") if losses else None, self.model.num_points, force=True)
            bar.close()
        finally:
            bar.close()
            restore_handlers(previous_handlers)
            self.writer.close()
        return self.run_dir

    def _stop_for_logging(self, step: int) -> None:
        failure = self.writer.failure
        path = self.save_checkpoint(step)
        raise LoggingFailedError(
            f"{failure} at step {step}: training stopped, its state saved in {path}; fix the cause and resume with "
            f"--load-dir {path.parent} (the records of the steps after the failure are not in metrics.jsonl)"
        )

    def _log_gradient_shares(self, step: int, loss_dict: dict[str, torch.Tensor], image: torch.Tensor,
                             loss: torch.Tensor) -> None:
        """Between a step's loss and its backward (:class:`StepHooks`): the share of each loss term in the image's
        gradient, every ``steps_per_gradient_shares`` steps; its time is left out of the step's."""
        every = self.config.logging.steps_per_gradient_shares
        if every > 0 and step % every == 0 and bool(torch.isfinite(loss)):  # a bad step has no shares to log
            start, start_cpu = time.perf_counter(), time.process_time()
            record = {"kind": "gradient_shares", "step": step, "elapsed_s": self._elapsed(),
                      "train_s": self._train_s, "reference": "main_loss", **gradient_shares(loss_dict, image)}
            self.writer.write(record)
            self._side_s += time.perf_counter() - start
            self._side_cpu_s += time.process_time() - start_cpu
        self._lap_start = time.perf_counter()  # the shares are logging, not a phase of the step

    def _log_train(self, step: int, losses: Mapping[str, float]) -> None:
        record: dict[str, Any] = {"kind": "train", "step": step, "elapsed_s": self._elapsed(), "train_s": self._train_s,
                                  "train_cpu_s": self._train_cpu_s}
        record.update(losses)
        assert self._last_outputs is not None and self._last_batch is not None  # a good step came before
        metrics = self.pipeline.get_train_metrics_dict(self._last_outputs, self._last_batch)
        record.update(metrics)
        record["lr_means"] = self.optimizers["means"].param_groups[0]["lr"]
        record.update(self.model.schedule_state())
        self.writer.write(record)


def recorded_config(config: TrainerConfig, dataparser_config: DataParserConfig) -> TrainerConfig:
    """What ``config.yml`` records: the user's config with the dataparser it resolved to (so the run can be rebuilt
    whatever the detection would say later), its scene paths made absolute (so kc-eval / kc-render work from any
    folder), as a copy: the user's config object is left as given."""
    recorded = copy.deepcopy(config)
    recorded.pipeline.datamanager.dataparser = recorded_dataparser(copy.deepcopy(dataparser_config))
    return recorded
