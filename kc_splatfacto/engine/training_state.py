"""The training state: the one owner of what a training step changes (gsplat ``simple_trainer``'s Runner, less the
loop).

:class:`TrainingState` holds the model (the Gaussians, their rendering and the loss), one Adam per parameter group
and the learning-rate schedules, the density-control strategy (a :class:`~kc_splatfacto.model.strategy.DensityStrategy`, gsplat's ``Strategy``
interface plus ``refines_at`` and ``cap``: :class:`~kc_splatfacto.model.strategy.DefaultStrategy`,
:class:`~kc_splatfacto.model.mcmc.MCMCStrategy`; anything else a TypeError naming what it lacks) and the strategy's
state. :meth:`TrainingState.step` takes one step on one batch:

1. the model set to the step, the batch's camera rendered, the strategy's pre-backward hook on the render's ``info``;
2. the loss terms (``model.get_loss_dict``), their sum, backward;
3. the verdict: a non-finite render, loss or gradient, or a gradient that would overflow Adam, skips the update
   (:class:`StepVerdicts` keeps every step's, in step order, and gives the bad ones as :class:`BadStep` records);
4. the optimizers step and the schedules advance, before density control: MCMC's noise reads the means' rate of the
   next step, as gsplat's ``simple_trainer`` and nerfstudio pass it;
5. density control on the render's ``info``, with the optimizers, whose state it rewrites when it adds, splits,
   relocates or removes Gaussians.

The verdict is taken on the host (one synchronisation: the update waits for it) or, with ``device_verdict``, on the
device: the flag goes to fused Adam as its ``found_inf`` (the update and Adam's step count left as they were on a bad
step, as under a gradient scaler), the render is made invisible to density control (radii 0, MCMC's noise scaled by
0), and the :class:`StepVerdict` comes back unread. A step on which density control grows, prunes, relocates or resets
still takes the host verdict: that work reads the host anyway. On a good step both ways are the same arithmetic.

Every ``PARAMETER_SCAN_EVERY`` steps a full scan removes Gaussians with non-finite values first (the rasterizer finds
those it reads on the other steps). The render's ``info`` stays inside the step. The trainer keeps the loop, the
clocks, checkpoints, evaluation and logging (it writes the bad steps out and stops a run that diverges): it times the
phases and looks at the loss terms before backward through :class:`StepHooks`.

>>> import copy
>>> from kc_splatfacto.data.demo import DemoDataParserConfig
>>> from kc_splatfacto.registry import discover_methods
>>> config = copy.deepcopy(discover_methods()["kc-splatfacto"].config)
>>> config.pipeline.datamanager.dataparser = DemoDataParserConfig(width=64, height=48)
>>> pipeline = config.pipeline.setup(dataparser=config.pipeline.datamanager.resolve_dataparser())
>>> state = TrainingState(pipeline.model.train(), config.optimizers)
>>> result = state.step(0, pipeline.datamanager.next_train())
>>> result.skipped, sorted(result.losses)
(None, ['cbc_loss', 'kc_loss', 'main_loss', 'wavelet_loss'])
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from typing import Any, Callable

import torch

from kc_splatfacto.engine.optimizers import OptimizersConfig
from kc_splatfacto.model import ops
from kc_splatfacto.model.splatfacto import SplatfactoModel
from kc_splatfacto.model.strategy import DensityStrategy, NoGaussiansLeftError, as_density_strategy
from kc_splatfacto.render.non_finite import NonFiniteInputError

GRAD_OVERFLOW = 1e18
"""a gradient this large would overflow Adam's squared-gradient average in float32 (1e36 < 3.4e38 just fits)"""
PARAMETER_SCAN_EVERY = 100
"""steps between full scans of the parameters for NaN/inf (the rasterizer reports what it reads every step)"""
VERDICTS_READ_EVERY = 100
"""most steps whose device verdicts wait unread (``machine.step_verdict``; the trainer also has them read at each log,
evaluation and checkpoint)"""

# a skipped (non-finite) step still advances the schedules, which torch reports as a misuse when no optimizer step
# came before (a bad first step); it is deliberate here
_SCHEDULE_BEFORE_OPTIMIZER = "Detected call of `lr_scheduler.step\\(\\)` before `optimizer.step\\(\\)`"


def _nothing(*args: Any) -> None:
    return None


@dataclass
class StepHooks:
    """What the trainer sees inside a step. ``lap(phase)`` is called at the end of each phase ("render", "losses",
    "backward", "optimizer", "density_control"); ``inspect_loss(loss_dict, image, loss)`` once between the loss and
    backward (the trainer's gradient shares; its time is the caller's to leave out)."""

    lap: Callable[[str], None] = _nothing
    inspect_loss: Callable[[dict[str, torch.Tensor], torch.Tensor, torch.Tensor], None] = _nothing


@dataclass
class StepVerdict:
    """Whether a step was good, as device tensors: ``good`` (bool), and what :meth:`reason` reads to say why not (the
    render's and the loss's finiteness, the loss terms stacked in ``term_names``' order, the parameter groups' largest
    gradient magnitudes). Every tensor is the step's own: a term may be a CUDA graph's output buffer, which the next
    step's replay overwrites, so the terms are kept as the stack the step's sum was taken of."""

    good: torch.Tensor
    render_finite: torch.Tensor
    loss_finite: torch.Tensor
    terms: torch.Tensor
    term_names: list[str]
    groups: list[str]
    peaks: torch.Tensor

    def reason(self) -> str | None:
        """Why the step was skipped, or None for a good step (reads the device: one synchronisation when good)."""
        if bool(self.good):
            return None
        if not bool(self.render_finite):
            return "non-finite render"
        if not bool(self.loss_finite):
            terms = ", ".join(f"{k}={v:.4g}" for k, v in zip(self.term_names, self.terms.tolist()))
            return f"non-finite loss ({terms})"
        bad = [k for k, v in zip(self.groups, self.peaks.tolist()) if not (math.isfinite(v) and v < GRAD_OVERFLOW)]
        return f"non-finite or overflowing gradient of {bad}"


@dataclass(frozen=True)
class BadStep:
    """A step whose update was skipped, as the trainer records it: ``step`` (the steps taken with it, the records'
    1-based count), why, and how many bad steps in a row it ends (``consecutive``)."""

    step: int
    reason: str
    consecutive: int


class StepVerdicts:
    """Every step's verdict, in step order: a host verdict is known at once, a device verdict waits unread
    (:attr:`waiting`) until :meth:`read`; the bad steps come out as :class:`BadStep` records, counted in a row (a good
    step ends the row)."""

    def __init__(self) -> None:
        self.waiting: list[tuple[int, StepVerdict]] = []
        self.bad_in_a_row = 0

    def _judge(self, step: int, reason: str | None) -> BadStep | None:
        if reason is None:
            self.bad_in_a_row = 0
            return None
        self.bad_in_a_row += 1
        return BadStep(step, reason, self.bad_in_a_row)

    def read(self) -> list[BadStep]:
        """Read the device verdicts waiting (one synchronisation), in step order: the bad steps among them."""
        waiting, self.waiting = self.waiting, []
        return [bad for step, verdict in waiting if (bad := self._judge(step, verdict.reason())) is not None]

    def host(self, step: int, reason: str | None) -> list[BadStep]:
        """A verdict the host took (``reason`` None: good), after those waiting (they come first): the bad steps."""
        bad = self.read()
        this = self._judge(step, reason)
        return bad if this is None else [*bad, this]

    def wait(self, step: int, verdict: StepVerdict) -> None:
        self.waiting.append((step, verdict))


@dataclass
class StepResult:
    """One step's outcome.

    Attributes:
        skipped: why the update was skipped (non-finite render, loss, gradient or parameters), or None.
        losses: the loss terms, detached (empty on a skipped step).
        outputs: the render without the rasterizer's ``info`` (``rgb`` [H, W, 3], ...); None on a skipped step.
        batch: the batch the step rendered; None on a skipped step.
        density: the counts of what density control did (default: duplicated, split, pruned, opacity_reset; mcmc:
            relocated, added); empty on a skipped step.
        verdict: the step's device verdict (its update was applied only if it is good), read or not; None when the
            host took the verdict (then ``skipped`` says it).
        bad_steps: the bad steps whose verdicts this step read, in step order (this one's included when known).
        known_bad: this step's update is known not to have been applied (``skipped``, or its device verdict read
            bad at once).
    """

    skipped: str | None
    losses: dict[str, torch.Tensor] = field(default_factory=dict)
    outputs: dict[str, Any] | None = None
    batch: dict[str, Any] | None = None
    density: dict[str, int] = field(default_factory=dict)
    verdict: StepVerdict | None = None
    bad_steps: list[BadStep] = field(default_factory=list)
    known_bad: bool = False


class TrainingState:
    """The model, its optimizers and schedules, density control and its state.

    Args:
        model: the model (its Gaussians live in ``model.gauss_params``, which density control rewrites).
        optimizers: the optimizer and schedule of each parameter group.
        strategy: density control (:class:`~kc_splatfacto.model.strategy.DensityStrategy`); by default the one the
            model's config describes (``strategy: default | mcmc``).
        device_verdict: take the verdict of a step without refinement on the device (module docstring); it needs
            fused Adam and a strategy that says on which steps it refines (``refines_at``), else the host takes it.
    """

    def __init__(self, model: SplatfactoModel, optimizers: OptimizersConfig,
                 strategy: DensityStrategy | None = None, device_verdict: bool = False):
        self.model = model
        self.optimizers_config = optimizers
        self.device_verdict = device_verdict
        self.strategy: DensityStrategy = as_density_strategy(
            strategy if strategy is not None else model.config.density_strategy(model.num_train_data))
        self.optimizers: dict[str, torch.optim.Optimizer] = {}
        self.schedulers: dict[str, Any] = {}
        self._build_optimizers()
        self.strategy.check_sanity(model.gauss_params, self.optimizers)
        self.strategy_state: dict[str, Any] = self.strategy.initialize_state(scene_scale=model.scene_scale)
        #: the steps' verdicts in step order, the device's waiting unread (:meth:`read_verdicts`)
        self.verdicts = StepVerdicts()

    def _build_optimizers(self) -> None:
        # nominal schedules (nerfstudio's): steps_scale only, never the run's length, so a short run is the first
        # steps of the full one
        self.optimizers, self.schedulers = self.optimizers_config.setup(
            self.model.parameter_groups(), steps_scale=self.model.config.steps_scale
        )

    # ----------------------------------------------------------------------------------------------- the step
    def step(self, step: int, batch: dict[str, Any] | Callable[[], dict[str, Any]], hooks: StepHooks | None = None,
             read_verdicts: bool = False) -> StepResult:
        """Take training step ``step`` (0-based) on ``batch`` (``camera``, ``image``, ``image_idx``, optionally
        ``mask``; or a function that draws it, called after the parameter scan): render, loss, backward, update,
        density control (module docstring). Every ``PARAMETER_SCAN_EVERY`` steps a full scan first removes Gaussians
        whose values render finitely but are not (an infinite opacity logit, ...): a step that removed any is skipped
        before its batch is drawn. A step whose render meets non-finite Gaussians removes them and is skipped.
        ``read_verdicts``: read every device verdict waiting after this step (the trainer's logs, evaluations and
        checkpoints need them); they are read anyway when ``VERDICTS_READ_EVERY`` wait."""
        hooks = hooks or StepHooks()
        if step % PARAMETER_SCAN_EVERY == 0:
            removed = self.remove_non_finite_gaussians()
            hooks.lap("optimizer")
            if removed:
                return self.skip(step, f"non-finite parameters: {removed} Gaussians removed")
        if callable(batch):
            batch = batch()
        model = self.model
        model.set_step(step)
        try:
            outputs = model.get_outputs(batch["camera"], absgrad=self.strategy.absgrad)
        except NonFiniteInputError:
            removed = self.remove_non_finite_gaussians()
            if not removed:  # a non-finite camera, not a parameter: a real error
                raise
            return self.skip(step, f"non-finite parameters: {removed} Gaussians removed")
        self.strategy.step_pre_backward(model.gauss_params, self.optimizers, self.strategy_state, step,
                                        outputs["info"])
        hooks.lap("render")
        loss_dict = model.get_loss_dict(outputs, batch)
        hooks.lap("losses")
        terms = torch.stack(list(loss_dict.values()))
        loss = terms.sum()
        hooks.inspect_loss(loss_dict, outputs["rgb"], loss)
        loss.backward()
        hooks.lap("backward")
        verdict = self._verdict(loss, terms.detach(), list(loss_dict), outputs["rgb"])
        on_device = self._verdict_on_device_at(step)
        bad_steps: list[BadStep] = []
        if not on_device:
            problem = verdict.reason()  # the host waits for the step here
            if problem is not None:
                return self.skip(step, problem)
            bad_steps = self.verdicts.host(step + 1, None)
        found_inf = (~verdict.good).to(torch.float32) if on_device else None
        for optimizer in self.optimizers.values():
            self._optimizer_step(optimizer, found_inf)
            optimizer.zero_grad(set_to_none=True)
        self._advance_schedules()
        hooks.lap("optimizer")
        density = self._density_control(step, outputs["info"], verdict.good if on_device else None)
        hooks.lap("density_control")
        known_bad = False
        if on_device:
            self.verdicts.wait(step + 1, verdict)
            if read_verdicts or len(self.verdicts.waiting) >= VERDICTS_READ_EVERY:
                bad_steps = self.verdicts.read()
                known_bad = bool(bad_steps) and bad_steps[-1].step == step + 1
        render = {k: v for k, v in outputs.items() if k != "info"}
        losses = {k: v.detach() for k, v in loss_dict.items()}
        return StepResult(skipped=None, losses=losses, outputs=render, batch=batch, density=density,
                          verdict=verdict if on_device else None, bad_steps=bad_steps, known_bad=known_bad)

    def read_verdicts(self) -> list[BadStep]:
        """Read the device verdicts waiting (one synchronisation): the bad steps among them, in step order."""
        return self.verdicts.read()

    def skip(self, step: int, reason: str) -> StepResult:
        """Step ``step`` without an update: the gradients dropped, the schedules advanced (a skipped step still
        counts), the bad step recorded after the verdicts waiting."""
        self.model.zero_grad(set_to_none=True)
        with warnings.catch_warnings():  # only around a skipped step: a filter change re-arms once-only warnings
            warnings.filterwarnings("ignore", message=_SCHEDULE_BEFORE_OPTIMIZER)
            self._advance_schedules()
        return StepResult(skipped=reason, bad_steps=self.verdicts.host(step + 1, reason), known_bad=True)

    def _advance_schedules(self) -> None:
        for scheduler in self.schedulers.values():
            scheduler.step()

    def _verdict(self, loss: torch.Tensor, terms: torch.Tensor, term_names: list[str], rgb: torch.Tensor) -> StepVerdict:
        """The step's verdict as device tensors, unread (one flag reduced on the device)."""
        names, peaks = self.model.gradient_peaks()
        render_finite = torch.isfinite(rgb).all()
        loss_finite = torch.isfinite(loss)
        good = (render_finite & loss_finite & torch.isfinite(peaks).all()
                & (peaks.max() < GRAD_OVERFLOW))  # a non-finite render is skipped even where its loss is finite
        return StepVerdict(good, render_finite, loss_finite, terms, term_names, names, peaks)

    def _verdict_on_device_at(self, step: int) -> bool:
        """Whether step ``step`` takes its verdict on the device: asked for, fused Adam everywhere (its found_inf
        skips a bad update), and no refinement at this step."""
        if not self.device_verdict:
            return False
        if self.strategy.refines_at(step):
            return False
        return all(isinstance(opt, torch.optim.Adam) and opt.defaults.get("fused") for opt in self.optimizers.values())

    @staticmethod
    def _optimizer_step(optimizer: torch.optim.Optimizer, found_inf: torch.Tensor | None) -> None:
        """``optimizer.step()``; with ``found_inf`` (a device float, 1 for a bad step) fused Adam leaves the
        parameters, its moments and its step count as they were where it is 1 (torch's gradient-scaler protocol)."""
        if found_inf is None:
            optimizer.step()
            return
        optimizer.found_inf = found_inf  # type: ignore[attr-defined]  # Adam.step reads getattr(self, "found_inf", None)
        try:
            optimizer.step()
        finally:
            del optimizer.found_inf  # type: ignore[attr-defined]

    def _density_control(self, step: int, info: dict[str, Any], good: torch.Tensor | None = None) -> dict[str, int]:
        """Statistics from this step's render (after its backward), then grow / prune / reset on the schedule (mcmc:
        relocate / add, and noise scaled by the means' learning rate after this step's schedule update). ``good``, a
        device verdict: a bad step's render is invisible to the statistics (radii 0: its gradients never read) and
        its noise 0, so density control is left as a skipped step leaves it."""
        params = self.model.gauss_params
        if good is not None:
            info = {**info, "radii": info["radii"] * good}
        means_lr = self.optimizers["means"].param_groups[0]["lr"]
        factor = None if good is None else good.to(params["means"].dtype)
        return self.strategy.step_post_backward(params, self.optimizers, self.strategy_state, step, info,
                                                lr=means_lr, noise_factor=factor)

    # ----------------------------------------------------------------------------------------------- repairs, caps
    @torch.no_grad()
    def remove_non_finite_gaussians(self) -> int:
        """Remove every Gaussian with a non-finite parameter (with its optimizer state and density-control
        statistics); returns how many were removed. Raises NoGaussiansLeftError when none would be left."""
        params = self.model.gauss_params
        if all(bool(torch.isfinite(p).all()) for p in params.values()):
            return 0
        bad_rows = torch.zeros(len(params["means"]), dtype=torch.bool, device=params["means"].device)
        for p in params.values():
            bad_rows |= ~torch.isfinite(p.reshape(len(p), -1)).all(dim=-1)
        ops.remove(params, self.optimizers, self.strategy_state, bad_rows)
        if len(params["means"]) == 0:
            raise NoGaussiansLeftError("every Gaussian had non-finite parameters and was removed: nothing left to train")
        return int(bad_rows.sum())

    def cap_gaussians(self, count: int) -> None:
        """Density control adds no Gaussians past ``count`` from now on (a memory budget reached): the strategy's
        cap lowered (``max_gaussians``; an MCMC strategy's ``cap_max``), never raised."""
        self.strategy.cap(count)

    # ----------------------------------------------------------------------------------------------- checkpoints
    def state_dict(self) -> dict[str, Any]:
        """The density-control statistics (``strategy_state``) and the optimizers' and schedules' states; the
        Gaussians are the model's (the pipeline's ``state_dict``)."""
        return {
            "strategy_state": dict(self.strategy_state),
            "optimizers": {k: opt.state_dict() for k, opt in self.optimizers.items()},
            "schedulers": {k: s.state_dict() for k, s in self.schedulers.items()},
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`'s content after the model's Gaussians were loaded (the optimizers are built
        again on the loaded parameters, whose count may differ from the initial one)."""
        device = self.model.device
        if "strategy_state" in state:
            self.strategy_state = {
                k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in state["strategy_state"].items()
            }
        self._build_optimizers()
        for name, opt_state in state.get("optimizers", {}).items():
            self.optimizers[name].load_state_dict(opt_state)
        for name, sched_state in state.get("schedulers", {}).items():
            self.schedulers[name].load_state_dict(sched_state)
