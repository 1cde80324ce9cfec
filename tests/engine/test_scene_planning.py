"""The scene plan in a run: nothing but its config values, printed, written, recorded, and applied again on resume."""

from __future__ import annotations

import json

import pytest
import torch

from kc_splatfacto.engine.config_file import read_config_file
from kc_splatfacto.engine.trainer import Trainer, TrainerConfig
from kc_splatfacto.model.splatfacto import PLAN_DECISIONS
from tests.training_utils import tiny_demo_config

STEPS = 12


def _config(tmp_path, name, **model):
    config = tiny_demo_config("kc-splatfacto", tmp_path / name, iterations=STEPS, **model)
    config.pipeline.datamanager.dataparser.demo_cache_dir = tmp_path / "demo-cache"
    config.pipeline.model.num_downscales = 2  # the method's: 64x48 halved twice holds 1 of 3 levels, the plan says 0
    return config


def _gaussians(trainer):
    return {name: param.detach().clone() for name, param in trainer.model.gauss_params.items()}


def _same(a, b):
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_the_plan_with_every_decision_skipped_trains_bit_for_bit_as_the_plan_off(tmp_path):
    """Measuring the scene (and building the data manager before the model) draws no random number and changes no
    data order: the plan-off run, today's fixed settings, is untouched by the plan's machinery."""
    off = Trainer(_config(tmp_path, "off"))
    off.train()
    skipped = Trainer(_config(tmp_path, "skipped", plan="on", plan_skip=PLAN_DECISIONS))
    skipped.train()
    assert skipped.scene_plan is not None and not skipped.scene_plan.choices()
    assert _same(_gaussians(off), _gaussians(skipped))


def test_a_planned_run_is_the_fixed_run_with_the_plans_values_and_says_so(tmp_path, capsys):
    planned = Trainer(_config(tmp_path, "planned", plan="on"))
    run_dir = planned.train()
    choices = planned.scene_plan.choices()
    assert choices["pipeline.model.num_downscales"] == 0 and "pipeline.model.frequency.cbc_weight" not in choices
    out = capsys.readouterr().out
    assert out.startswith("scene plan for kc-splatfacto on demo") and "0 (asked 2)" in out
    by_hand = _config(tmp_path, "by-hand")
    by_hand.pipeline.model.num_downscales = 0
    by_hand.pipeline.model.background_color = choices["pipeline.model.background_color"]
    by_hand.pipeline.model.sh_degree = choices["pipeline.model.sh_degree"]  # 0: the demo's shading is Lambertian
    fixed = Trainer(by_hand)
    fixed.train()
    assert _same(_gaussians(planned), _gaussians(fixed))
    recorded = read_config_file(run_dir / "config.yml", TrainerConfig)
    assert recorded.pipeline.model.num_downscales == 0  # config.yml holds the values the run trained with
    plan = json.loads((run_dir / "plan.json").read_text())
    assert {d["name"] for d in plan["decisions"]} >= {"schedule", "downscales", "cbc", "background"}


@pytest.mark.parametrize("from_folder_alone", [False, True])
def test_a_resume_continues_with_the_plan_the_run_recorded(tmp_path, from_folder_alone):
    """Stopped at step 6 and resumed to 12, bit for bit the uninterrupted planned run, whether the resume gives the
    full command again (the plan.json's choices applied again) or the run's config.yml alone."""
    full = Trainer(_config(tmp_path, "full", plan="on"))
    full.train()
    first = _config(tmp_path, "stopped", plan="on")
    first.max_num_iterations = STEPS // 2
    first.steps_per_save = STEPS // 2
    run_dir = Trainer(first).train()
    if from_folder_alone:
        again = read_config_file(run_dir / "config.yml", TrainerConfig)
    else:
        again = _config(tmp_path, "stopped", plan="on")
        again.max_num_iterations = STEPS // 2  # what the run asked (its plan's end: the same here)
    again.max_num_iterations = STEPS
    again.load_dir = run_dir
    resumed = Trainer(again)
    resumed.train()
    assert resumed.scene_plan is None  # not measured anew
    assert resumed.config.pipeline.model.num_downscales == 0
    assert _same(_gaussians(full), _gaussians(resumed))


def test_a_run_leaves_out_the_planned_finest_levels_at_full_size_and_one_fewer_per_halving(tmp_path):
    """skip_finest_levels 1 with one halving (steps_scale 0.01: 30 steps at 32x24, then 64x48): the ground truths'
    targets cached at half size compare every level, those at full size leave level 1 out; the logged band kurtosis
    keeps every level's bands."""
    config = tiny_demo_config("kc-splatfacto", tmp_path / "skip", iterations=45, steps_scale=0.01,
                              num_downscales=1)
    config.pipeline.datamanager.dataparser.demo_cache_dir = tmp_path / "demo-cache"
    config.pipeline.model.frequency.skip_finest_levels = 1
    trainer = Trainer(config)
    trainer.train()
    targets = trainer.model.frequency_loss._targets
    assert {downscale for _, downscale in targets} == {1, 2}
    assert all(target.skipped_levels == (1 if downscale == 1 else 0) for (_, downscale), target in targets.items())
    assert all(target.coeffs.levels == 2 for target in targets.values())  # 3 - 1 left out; 32x24 holds 2 of 3
    logged = [json.loads(line) for line in (trainer.run_dir / "metrics.jsonl").read_text().splitlines()]
    kurtosis = [row["kurtosis_gt"] for row in logged if "kurtosis_gt" in row and row["step"] > 30]
    assert kurtosis and all(len(values) == 9 for values in kurtosis)  # 3 levels x (H, V, D) at 64x48
