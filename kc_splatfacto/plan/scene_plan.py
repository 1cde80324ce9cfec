"""The scene plan: what a scene needs, decided once before training from measurements of its training split.

Each :class:`Decision` names the config field it sets, the number measured, the rule, what the config asked and what
the plan chose. A field the user set (it differs from the method's own config), a decision in ``plan_skip`` and the
plan switched off (``pipeline.model.plan off``: the paper's and Splatfacto's fixed settings) keep the config's value.
What is left out is not computed: fewer steps are not run, a warm-up stage not planned is not trained.

The rules and the numbers behind them (docs/plan.md):

- **schedule** (``max_num_iterations``): a step trains one view, which updates the points it sees, so a point gets
  about end x coverage / views updates per view. study-30k's 12-view scenes peak in test PSNR and then fall; fitted
  on fern-12 and flower-12 (VISITS_PER_VIEW = 750 maximises their mean paired ΔPSNR against step 30000, +0.44 dB),
  checked on beer-12 and castle-P30. The end is that many visits, rounded up to 500 steps, never before the warm-up
  has trained :data:`FULL_RESOLUTION_STEPS` at full size, never past the asked ``max_num_iterations`` (a budget). Every
  other schedule (densification, opacity reset, learning rates) stays the asked one's: the planned run is the asked
  run's first steps, bit for bit.
- **downscales** (``num_downscales``): the warm-up's first stage must hold every DWT level the frequency loss asks
  (a 48x32 stage holds 2 of 3 db3 levels): the largest number of halvings, up to the asked one, at which the
  smallest training image still does. A method without a wavelet term keeps the asked warm-up.
- **cbc**: measured and reported, no longer decided. The rule that left the CBC term out below
  :data:`CBC_SHARE_FLOOR` of the wavelet L1's size on the ground truth (1.5e-5 to 4.2e-4 on the shared scenes at the
  paper's weights; gradient share on castle-P30 0.11 %) failed its paired study: on fern-12, flower-12 and beer-12,
  where it was the plan's only change at 7000 steps, it saved no time (0.97-1.06x) and was -0.11 dB over 12 pairs
  (beer-12 -0.28 [-1.37, +0.82]; docs/results/study-plan-7k). A rule that saves nothing must be harmless.
- **background** (``background_color``): white (black) when at least :data:`BACKDROP_SHARE` of the training images'
  border pixels are, else the asked one.
- **levels** (``frequency.skip_finest_levels``): the finest DWT levels whose ground-truth detail RMS is below
  :data:`NOISE_FLOOR_SNR` times the images' noise floor (Donoho's MAD estimate on the finest diagonal band: an
  orthogonal wavelet gives white noise of deviation s a deviation s in every band) supervise noise and are left out
  of every detail term, the coarsest level always kept; at a warm-up stage of 1/2^d, d fewer (the downscale averaged
  that noise away). On the shared scenes the lowest ratio is 2.8 (flower-12's finest level at 252x189), so no level
  is left out there.
- **sh** (``sh_degree``): degree 0 (no SH coefficients at all) when the colour spread at the seed points across the
  views is within :data:`SH_NOISE_RATIO` of what the images' noise alone gives, else the asked degree. Only a scene
  without measurable view dependence loses its SH: the measure does not tell where a lower degree pays on a sparse
  real scene (spread over noise 2.4 on entry-P10, where degree 0 helped its LPIPS in sparse-sh-7k, and 1.7 on
  flower-12, where a lower degree cost 0.41 dB), so no shared scene changes.
- Reported, not decided (the measurement is in the table; the choice is the config's): **kc bands** (coefficients
  per band at the first stage).
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from kc_splatfacto.atomic import atomic_write_text
from kc_splatfacto.data.outputs import Cameras
from kc_splatfacto.losses.wavelets import supported_levels
from kc_splatfacto.model.splatfacto import PLAN_DECISIONS, scale_steps
from kc_splatfacto.plan import measure

VISITS_PER_VIEW = 750
"""planned updates of a point per view that sees it (fitted on study-30k's fern-12 and flower-12; docs/plan.md)"""
END_QUANTUM = 500
"""the planned end is rounded up to a multiple of this many (nominal) steps"""
FULL_RESOLUTION_STEPS = 1000
"""the planned end leaves at least this many (nominal) steps after the warm-up's last stage began at full size"""
CBC_SHARE_FLOOR = 0.01
"""the share of the wavelet term below which the CBC term was left out, before its study (reported against it)"""
BACKDROP_SHARE = 0.9
"""a constant background when at least this share of the border pixels is white (black)"""
NOISE_FLOOR_SNR = 1.5
"""a level whose detail RMS is below this many times the noise floor supervises noise: RMS^2 = signal^2 + noise^2, so
1.5 is a signal RMS of 1.1 noise deviations: the noise is nearly half the band's energy"""
SH_NOISE_RATIO = 1.25
"""no SH above degree 0 when the colour spread across the views is at most this many times the spread the images'
noise alone gives: a colour that does not change with the view beyond the noise needs no view-dependent term (the
shared scenes measure 1.7 (flower-12) to 4.7 (castle-P30), and beer-12's flat backdrop has no noise floor)"""
PLAN_FILE = "plan.json"


@dataclass
class Decision:
    """One row of the plan: ``name`` (one of PLAN_DECISIONS or a reported measurement), ``field`` (the dotted config
    field, '' for a reported row), ``measured`` and ``rule`` (text), ``asked`` and ``chosen`` (values), ``source``:
    'plan' (the rule chose), 'yours' (the user set the field), 'skipped' (``plan_skip``), 'reported'."""

    name: str
    field: str
    measured: str
    rule: str
    asked: Any
    chosen: Any
    source: str

    @property
    def changes(self) -> bool:
        return self.source == "plan" and self.chosen != self.asked

    def choice(self, emphasis: str = "", yours: str = "set by you") -> str:
        """The choice as the table says it: the value, and why (a changed value between ``emphasis`` marks)."""
        if self.source == "reported":
            return f"{self.chosen} (reported)"
        if self.source == "plan":
            return f"{emphasis}{self.chosen}{emphasis} (asked {self.asked})" if self.changes else f"{self.chosen} (as asked)"
        return f"{self.chosen} ({yours if self.source == 'yours' else 'plan_skip'})"


@dataclass
class ScenePlan:
    """The plan of one run: its rows, and the scene and method it was made for."""

    method: str
    scene: str
    views: int
    size: str
    decisions: list[Decision] = field(default_factory=list)

    def table(self) -> str:
        """The plan as the one short table kc-train prints."""
        head = f"scene plan for {self.method} on {self.scene} ({self.views} training views, {self.size}):"
        rows = [("decision", "measured", "rule", "choice")]
        for d in self.decisions:
            rows.append((d.name, d.measured, d.rule, d.choice()))
        widths = [max(len(r[i]) for r in rows) for i in range(3)]
        lines = [head] + ["  " + "  ".join(r[i].ljust(widths[i]) for i in range(3)) + "  " + r[3] for r in rows]
        lines.append(f"  (the fields: {PLAN_FILE}; a flag you set wins; --pipeline.model.plan-skip NAME keeps the "
                     "config's value; --pipeline.model.plan off: the fixed settings)")
        return "\n".join(lines)

    def to_json(self) -> dict[str, Any]:
        return {"method": self.method, "scene": self.scene, "views": self.views, "size": self.size,
                "decisions": [dataclasses.asdict(d) for d in self.decisions]}

    def write(self, run_dir: Path) -> Path:
        path = Path(run_dir) / PLAN_FILE
        atomic_write_text(path, json.dumps(self.to_json(), indent=2, default=str) + "\n")
        return path

    def choices(self) -> dict[str, Any]:
        """{dotted field: value} the plan sets (its own decisions only)."""
        return {d.field: d.chosen for d in self.decisions if d.source == "plan" and d.field}


def get_field(config: Any, dotted: str) -> Any:
    for part in dotted.split("."):
        config = getattr(config, part)
    return config


def set_field(config: Any, dotted: str, value: Any) -> None:
    *parents, last = dotted.split(".")
    for part in parents:
        config = getattr(config, part)
    setattr(config, last, value)


def apply_choices(config: Any, choices: dict[str, Any]) -> None:
    """Set each dotted field of ``config`` (a TrainerConfig) to its planned value, in place."""
    for dotted, value in choices.items():
        set_field(config, dotted, value)


def read_choices(path: Path) -> dict[str, tuple[Any, Any]]:
    """{dotted field: (asked, chosen)} of the choices a run's ``plan.json`` recorded (what a resume applies again)."""
    data = json.loads(Path(path).read_text())
    return {d["field"]: (_value(d["asked"]), _value(d["chosen"])) for d in data.get("decisions", [])
            if d.get("source") == "plan" and d.get("field")}


def _value(value: Any) -> Any:
    return tuple(value) if isinstance(value, list) else value


def reapply_choices(config: Any, recorded: dict[str, tuple[Any, Any]]) -> dict[str, Any]:
    """A resume's plan: each recorded choice set again where the field still holds what the run asked (the same
    request); a field set otherwise now is the user's and wins (``--max-num-iterations`` beyond the plan's end
    trains on). In place; returns what it set."""
    applied = {}
    for dotted, (asked, chosen) in recorded.items():
        if get_field(config, dotted) == asked:
            set_field(config, dotted, chosen)
            applied[dotted] = chosen
    return applied


def leaves(value: Any, prefix: str = "") -> dict[str, Any]:
    """{dotted field: value} of every non-dataclass field of a config."""
    if not dataclasses.is_dataclass(value) or isinstance(value, type):
        return {prefix.rstrip("."): value}
    found: dict[str, Any] = {}
    for f in dataclasses.fields(value):
        found.update(leaves(getattr(value, f.name), f"{prefix}{f.name}."))
    return found


def user_set_fields(config: Any, method_default: Any | None) -> set[str]:
    """The dotted fields in which ``config`` differs from its method's own config (what the user set)."""
    if method_default is None:
        return set()
    before, after = leaves(method_default), leaves(config)
    return {name for name, value in after.items() if name in before and before[name] != value}


MODEL = "pipeline.model."


def make_scene_plan(config: Any, images: Sequence[torch.Tensor], cameras: Cameras, points: torch.Tensor | None,
                    scene: str, user_set: set[str] | frozenset[str] = frozenset()) -> ScenePlan:
    """The plan of ``config`` (a TrainerConfig, left unchanged) for the training split given by its ``images``
    ([H, W, C] uint8), ``cameras`` and seed ``points`` [M, 3] (or None)."""
    model = config.pipeline.model
    frequency = model.frequency
    height = min(int(image.shape[0]) for image in images)
    width = min(int(image.shape[1]) for image in images)
    plan = ScenePlan(config.method_name, scene, len(cameras), f"{width}x{height}")
    skip = set(model.plan_skip)

    def decide(name: str, dotted: str, measured: str, rule: str, chosen: Any) -> None:
        asked = get_field(config, dotted)
        if dotted in user_set and dotted != "max_num_iterations":  # the step count is a budget: the plan stops earlier
            plan.decisions.append(Decision(name, dotted, measured, rule, asked, asked, "yours"))
        elif name in skip:
            plan.decisions.append(Decision(name, dotted, measured, rule, asked, asked, "skipped"))
        else:
            plan.decisions.append(Decision(name, dotted, measured, rule, asked, chosen, "plan"))

    # downscales first: the schedule's floor follows the warm-up the plan chose
    asked_downscales = model.num_downscales
    wavelet_terms = [term.name for term, _ in frequency.active_terms()]
    if wavelet_terms:
        levels = frequency.wavelet_levels
        downscales = asked_downscales
        while downscales > 0 and supported_levels(height >> downscales, width >> downscales, frequency.wave,
                                                  levels) < levels:
            downscales -= 1
        first = f"{width >> asked_downscales}x{height >> asked_downscales}"
        held = supported_levels(height >> asked_downscales, width >> asked_downscales, frequency.wave, levels)
        decide("downscales", MODEL + "num_downscales", f"first stage {first}: {held} of {levels} "
               f"{frequency.wave} levels", "first stage holds them all", downscales)
    else:
        decide("downscales", MODEL + "num_downscales", "no wavelet term", "the asked warm-up", asked_downscales)
    planned_downscales = plan.decisions[-1].chosen

    coverage = measure.view_coverage(points, cameras)
    nominal = VISITS_PER_VIEW * coverage.views / max(coverage.coverage, 1e-6)
    floor = planned_downscales * model.resolution_schedule + FULL_RESOLUTION_STEPS
    nominal_end = max(math.ceil(nominal / END_QUANTUM) * END_QUANTUM, floor)
    steps_scale = getattr(model, "steps_scale", 1.0)  # ns-train's model config has none
    end = min(scale_steps(nominal_end, steps_scale), config.max_num_iterations)
    decide("schedule", "max_num_iterations",
           f"{coverage.views} views, coverage {coverage.coverage:.2f} ({coverage.points} points)",
           f"{VISITS_PER_VIEW} x views / coverage, within warm-up..asked", end)

    if frequency.cbc_weight > 0:
        share = measure.cross_band_share(images, frequency)
        plan.decisions.append(Decision(  # the rule "0 below 1 %" saved nothing where it fired (study-plan-7k)
            "cbc", "", f"CBC / wavelet L1 on GT {share:.2g}", "kept: its size does not tell its use",
            frequency.cbc_weight, frequency.cbc_weight, "reported"))

    border = measure.border_colour(images)
    background = "white" if border.white >= BACKDROP_SHARE else "black" if border.black >= BACKDROP_SHARE else None
    decide("background", MODEL + "background_color",
           f"border {100 * border.white:.0f} % white, {100 * border.black:.0f} % black",
           f"constant from {100 * BACKDROP_SHARE:.0f} %", background or model.background_color)

    if wavelet_terms:
        detail = measure.detail_levels(images, frequency.wave, frequency.wavelet_levels, planned_downscales)
        snr = ", ".join(f"{value:.1f}" for value in detail.snr)
        if any(name != "lowpass_loss" for name in wavelet_terms):  # a low-pass band holds the mean, not noise
            at_floor = next((j for j, value in enumerate(detail.snr) if value >= NOISE_FLOOR_SNR), len(detail.snr))
            decide("levels", MODEL + "frequency.skip_finest_levels", f"detail / noise {snr} (finest first)",
                   f"finest below {NOISE_FLOOR_SNR:g} left out, the coarsest kept",
                   min(at_floor, max(frequency.wavelet_levels - 1, 0)))
        counts = ", ".join(str(n) for n in detail.coefficients)
        plan.decisions.append(Decision(
            "kc bands", "", f"coefficients per band {counts}", "kurtosis s.e. ~ sqrt(24 / n)", "all kept", "all kept", "reported"))
    spread = measure.colour_spread(images, cameras, points)
    lambertian = not math.isnan(spread.spread) and spread.spread <= SH_NOISE_RATIO * spread.noise
    decide("sh", MODEL + "sh_degree", f"colour spread across views {spread.spread:.1f} / 255, noise {spread.noise:.1f}",
           f"0 within {SH_NOISE_RATIO:g}x the noise", 0 if lambertian else model.sh_degree)
    return plan


def planned_config(config: Any, plan: ScenePlan) -> Any:
    """A copy of ``config`` with the plan's choices."""
    planned = copy.deepcopy(config)
    apply_choices(planned, plan.choices())
    return planned


__all__ = ["PLAN_DECISIONS", "Decision", "ScenePlan", "make_scene_plan", "apply_choices", "read_choices", "reapply_choices",
           "user_set_fields", "planned_config", "PLAN_FILE"]
