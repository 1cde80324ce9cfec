"""MCMC densification: the relocation formula against the kernel's double sum written in float64, relocation, growth
and noise against their definitions, the cap over a real run, the start-above-cap error, resume, and the methods."""

from __future__ import annotations

import copy
import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from scipy.special import binom

from kc_splatfacto.engine import training_state
from kc_splatfacto.engine.optimizers import OptimizersConfig
from kc_splatfacto.engine.trainer import Trainer
from kc_splatfacto.engine.training_state import TrainingState
from kc_splatfacto.model import ops
from kc_splatfacto.model.mcmc import GaussianCapError, MCMCStrategy
from kc_splatfacto.model.relocation import MAX_COPIES, compute_relocation, relocation_torch
from kc_splatfacto.model.splatfacto import SplatfactoModelConfig
from method_configs import splatfacto_configs
from tests.engine.test_host_syncs import KEPT, _by_function, host_syncs
from tests.training_utils import stop_after, tiny_demo_config

PROJECT_ROOT = Path(__file__).resolve().parents[2]


def kernel_relocation_float64(opacity: float, scales: np.ndarray, n: int) -> tuple[float, np.ndarray]:
    """gsplat's relocation kernel (relocation.cu, the paper's eq. 9) as written there, a double sum, in float64."""
    n = min(max(n, 1), MAX_COPIES)
    new_opacity = 1.0 - (1.0 - opacity) ** (1.0 / n)
    denominator = 0.0
    for i in range(1, n + 1):
        for k in range(i):
            denominator += binom(i - 1, k) * (-1.0) ** k / np.sqrt(k + 1.0) * new_opacity ** (k + 1)
    return new_opacity, opacity / denominator * scales


def test_relocation_matches_the_kernels_double_sum():
    rng = np.random.default_rng(0)
    m = 300
    opacities = rng.uniform(0.005, 0.999, m)
    scales = np.exp(rng.normal(-3.0, 1.0, (m, 3)))
    ratios = np.concatenate([rng.integers(1, 8, m - 60), rng.integers(8, 70, 60)])  # some past the clamp at 51
    new_o, new_s = relocation_torch(torch.from_numpy(opacities), torch.from_numpy(scales), torch.from_numpy(ratios))
    for i in range(m):
        want_o, want_s = kernel_relocation_float64(opacities[i], scales[i], int(ratios[i]))
        assert float(new_o[i]) == pytest.approx(want_o, rel=1e-9)
        np.testing.assert_allclose(new_s[i].numpy(), want_s, rtol=1e-8)
    # the n copies composite back to the source's opacity
    n = np.clip(ratios, 1, MAX_COPIES)
    np.testing.assert_allclose(1.0 - (1.0 - new_o.numpy()) ** n, opacities, rtol=1e-12)
    # float32 in, float32 out, to float32 precision
    o32, s32 = relocation_torch(torch.from_numpy(opacities).float(), torch.from_numpy(scales).float(),
                                torch.from_numpy(ratios))
    assert o32.dtype == s32.dtype == torch.float32
    np.testing.assert_allclose(s32.numpy(), new_s.numpy(), rtol=2e-5)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA (gsplat's relocation kernel)")
def test_relocation_on_cuda_is_gsplats_kernel_and_agrees_with_the_torch_formula():
    pytest.importorskip("gsplat")
    gen = torch.Generator().manual_seed(1)
    opacities = 0.005 + 0.98 * torch.rand(1000, generator=gen)
    scales = torch.exp(torch.randn(1000, 3, generator=gen) - 3)
    ratios = torch.randint(1, 9, (1000,), generator=gen)  # few copies: the kernel sums in float32
    cuda_o, cuda_s = compute_relocation(opacities.cuda(), scales.cuda(), ratios.cuda())
    torch_o, torch_s = relocation_torch(opacities.double(), scales.double(), ratios)
    np.testing.assert_allclose(cuda_o.cpu().double().numpy(), torch_o.numpy(), rtol=1e-5)
    np.testing.assert_allclose(cuda_s.cpu().double().numpy(), torch_s.numpy(), rtol=1e-3)


def _gaussians(n: int, seed: int = 0, dead: int = 0) -> tuple[torch.nn.ParameterDict, dict[str, torch.optim.Adam]]:
    """``n`` random Gaussians (the first ``dead`` at opacity 0.001) and one Adam per group, stepped once so that
    every moment is non-zero."""
    gen = torch.Generator().manual_seed(seed)
    opacity = 0.05 + 0.9 * torch.rand(n, 1, generator=gen)
    opacity[:dead] = 0.001
    params = torch.nn.ParameterDict({
        "means": torch.nn.Parameter(torch.randn(n, 3, generator=gen)),
        "scales": torch.nn.Parameter(torch.randn(n, 3, generator=gen) - 3),
        "quats": torch.nn.Parameter(torch.randn(n, 4, generator=gen)),
        "opacities": torch.nn.Parameter(torch.logit(opacity)),
        "features_dc": torch.nn.Parameter(torch.randn(n, 3, generator=gen)),
    })
    optimizers = {name: torch.optim.Adam([p], lr=1e-3) for name, p in params.items()}
    for name, p in params.items():
        p.grad = torch.randn(p.shape, generator=gen)
        optimizers[name].step()
    return params, optimizers


def _rows(params) -> dict[str, np.ndarray]:
    return {name: p.detach().numpy().reshape(len(p), -1).copy() for name, p in params.items()}


def test_relocate_keeps_the_count_and_moves_every_dead_gaussian_onto_a_live_one():
    n, dead, min_opacity = 60, 15, 0.005
    params, optimizers = _gaussians(n, dead=dead)
    before = _rows(params)
    moments = {name: opt.state[params[name]]["exp_avg"].clone().reshape(n, -1) for name, opt in optimizers.items()}
    torch.manual_seed(3)
    mask = torch.sigmoid(params["opacities"].detach().flatten()) <= min_opacity
    assert int(mask.sum()) == dead
    assert ops.relocate(params, optimizers, {}, mask, min_opacity) == dead
    after = _rows(params)
    assert all(len(rows) == n for rows in after.values())
    live_means = {tuple(before["means"][i]): i for i in range(dead, n)}
    copies: dict[int, list[int]] = {}
    for i in range(dead):  # each dead row is now a copy of a live source, itself updated
        source = live_means[tuple(after["means"][i])]
        copies.setdefault(source, []).append(i)
        for name in after:
            np.testing.assert_array_equal(after[name][i], after[name][source], err_msg=name)
    sigmoid = lambda x: 1.0 / (1.0 + np.exp(-x.astype(np.float64)))  # noqa: E731
    for i in range(dead, n):
        if i in copies:  # a source shares its opacity with its copies: together they composite to the old one
            o_old, o_new = sigmoid(before["opacities"][i][0]), sigmoid(after["opacities"][i][0])
            assert 1.0 - (1.0 - o_new) ** (len(copies[i]) + 1) == pytest.approx(o_old, rel=1e-5)
            want_o, want_s = kernel_relocation_float64(o_old, np.exp(before["scales"][i].astype(np.float64)),
                                                       len(copies[i]) + 1)
            np.testing.assert_allclose(np.exp(after["scales"][i]), want_s, rtol=1e-5)
            for name, opt in optimizers.items():  # gsplat's choice: the sources' moments restart from zero
                assert not opt.state[params[name]]["exp_avg"].reshape(n, -1)[i].any(), name
        else:  # a live Gaussian not drawn is untouched, moments included
            for name in after:
                np.testing.assert_array_equal(after[name][i], before[name][i], err_msg=name)
                np.testing.assert_array_equal(
                    optimizers[name].state[params[name]]["exp_avg"].reshape(n, -1)[i], moments[name][i])


def test_growth_is_at_most_five_percent_per_refinement_and_never_past_the_cap():
    params, optimizers = _gaussians(100, seed=1)
    strategy = MCMCStrategy(cap_max=118, refine_start_iter=0, refine_every=1, min_opacity=0.005)
    state = strategy.initialize_state()
    torch.manual_seed(0)
    counts = [100]
    for step in range(1, 8):
        old = _rows(params)
        report = strategy.step_post_backward(params, optimizers, state, step, {}, lr=0.0)  # no noise
        n_old, n_new = counts[-1], len(params["means"])
        counts.append(n_new)
        assert n_new - n_old == report["added"] <= 0.05 * n_old
        assert n_new <= 118
        new = _rows(params)
        old_means = {tuple(m) for m in old["means"]}
        assert all(tuple(m) in old_means for m in new["means"][n_old:])  # the added ones are copies of old ones
        for name, opt in optimizers.items():  # and start with zero moments
            assert not opt.state[params[name]]["exp_avg"].reshape(n_new, -1)[n_old:].any(), name
    assert counts == [100, 105, 110, 115, 118, 118, 118, 118]


def test_noise_on_the_means_is_the_covariance_times_the_gate_times_lr_times_noise_lr():
    n = 40
    params, optimizers = _gaussians(n, seed=2)
    with torch.no_grad():  # opacities from nearly transparent (gate ~1) to opaque (gate ~0); means at 0, so what
        params["opacities"].copy_(torch.logit(torch.linspace(0.0005, 0.99, n))[:, None])  # moved them is the noise
        params["means"].zero_()
    strategy = MCMCStrategy(noise_lr=5e5, refine_start_iter=100)
    lr = 1.6e-4
    torch.manual_seed(11)
    strategy.step_post_backward(params, optimizers, strategy.initialize_state(), 7, {}, lr=lr)  # no refinement
    torch.manual_seed(11)
    z = torch.randn(n, 3).double().numpy()
    wxyz = params["quats"].detach().double().numpy()
    rotations = Rotation.from_quat(wxyz[:, [1, 2, 3, 0]]).as_matrix()  # scipy: xyzw, normalizes
    scales = np.exp(params["scales"].detach().double().numpy())
    covariances = rotations @ (scales[:, :, None] ** 2 * np.transpose(rotations, (0, 2, 1)))
    opacity = 1.0 / (1.0 + np.exp(-params["opacities"].detach().double().numpy()[:, 0]))
    gate = 1.0 / (1.0 + np.exp(-100.0 * ((1.0 - opacity) - 0.995)))
    want = np.einsum("nij,nj->ni", covariances, z * gate[:, None] * lr * 5e5)
    moved = params["means"].detach().double().numpy()
    np.testing.assert_allclose(moved, want, rtol=1e-4, atol=1e-6 * np.abs(want).max())
    assert np.abs(moved[-5:]).max() < 1e-6 * np.abs(moved[:5]).max()  # opaque Gaussians stay put


def test_a_cap_below_the_seed_points_is_a_one_line_error_naming_the_field():
    config = SplatfactoModelConfig(strategy="mcmc", max_gs_num=10)

    def train(model_config, **setup):  # the training state builds density control
        return TrainingState(model_config.setup(**setup), OptimizersConfig())

    with pytest.raises(GaussianCapError) as raised:
        train(config, seed_points=(torch.rand(25, 3), None))
    message = str(raised.value)
    assert isinstance(raised.value, ValueError) and "\n" not in message
    assert "max_gs_num (10)" in message and "25" in message and "--pipeline.model.max-gs-num" in message
    with pytest.raises(GaussianCapError):  # random initialization counts too
        train(dataclasses.replace(config, num_random=11))
    assert train(dataclasses.replace(config, num_random=10)).model.num_points == 10  # at the cap is allowed


def _tiny_mcmc_config(output_dir: Path, iterations: int, cap: int):
    config = tiny_demo_config("splatfacto", output_dir, iterations=iterations, strategy="mcmc", max_gs_num=cap)
    config.machine.seed = 5
    return config


def test_a_run_never_holds_more_gaussians_than_its_cap(tmp_path):
    # the demo scene's 2000 seed points; refinement every 2 steps after step 10 (steps_scale 0.02): 5% growth reaches
    # the cap of 2300 at the third refinement, and the next ones only relocate
    trainer = Trainer(_tiny_mcmc_config(tmp_path, iterations=30, cap=2300))
    train_iteration, counts = trainer.train_iteration, []

    def counted(step):
        result = train_iteration(step)
        counts.append(trainer.model.num_points)
        return result

    trainer.train_iteration = counted
    run_dir = trainer.train()
    assert len(counts) == 30 and max(counts) <= 2300
    seed_count = counts[0]  # no refinement at step 0
    assert seed_count < 2300 == counts[-1]  # it grew, up to the cap
    from kc_splatfacto.engine.metrics_log import read_metrics

    records = read_metrics(run_dir / "metrics.jsonl")
    densify = [r for r in records if r["kind"] == "densify"]
    assert any(r["relocated"] > 0 for r in densify) and sum(r["added"] for r in densify) == 2300 - seed_count
    train = [r for r in records if r["kind"] == "train"]
    assert all(r["mcmc_opacity_reg"] > 0 and r["mcmc_scale_reg"] > 0 for r in train)


def test_resume_of_an_mcmc_run_is_bit_identical(tmp_path):
    # refinements at steps 12, 14, ...: the stop after step 13 falls between two, with noise on every step
    full = Trainer(_tiny_mcmc_config(tmp_path / "full", iterations=20, cap=2150))
    full.train()
    stopped = Trainer(_tiny_mcmc_config(tmp_path / "stopped", iterations=20, cap=2150))
    stop_after(stopped, 13)
    run_dir = stopped.train()
    resume_config = _tiny_mcmc_config(tmp_path / "stopped", iterations=20, cap=2150)
    resume_config.load_dir = run_dir / "nerfstudio_models"
    resumed = Trainer(resume_config)
    resumed.train()
    assert resumed.start_step == 13
    assert full.model.num_points == resumed.model.num_points == 2150
    for name, param in full.model.gauss_params.items():
        assert torch.equal(param, resumed.model.gauss_params[name]), name


def test_the_mcmc_methods_are_splatfacto_and_kc_splatfacto_with_the_strategy_swapped():
    pairs = {"splatfacto-mcmc": (splatfacto_configs.splatfacto_mcmc, splatfacto_configs.splatfacto),
             "kc-splatfacto-mcmc": (splatfacto_configs.kc_splatfacto_mcmc, splatfacto_configs.kc_splatfacto)}
    for name, (mcmc, base) in pairs.items():
        assert mcmc.config.method_name == name
        model = copy.deepcopy(mcmc.config.pipeline.model)
        strategy = model.density_strategy(12)
        assert model.strategy == "mcmc" and isinstance(strategy, MCMCStrategy)
        assert strategy.min_opacity == MCMCStrategy.min_opacity == 0.005  # gsplat's default, the paper's
        base_model = base.config.pipeline.model
        assert dataclasses.replace(model, strategy="default", cull_alpha_thresh=base_model.cull_alpha_thresh) == base_model
    tomllib = pytest.importorskip("tomllib", reason="Python 3.11's TOML reader")
    entry_points = tomllib.loads((PROJECT_ROOT / "pyproject.toml").read_text())["project"]["entry-points"]
    ours = entry_points["kc_splatfacto.method_configs"]
    assert ours["splatfacto-mcmc"] == "method_configs.splatfacto_configs:splatfacto_mcmc"
    assert ours["kc-splatfacto-mcmc"] == "method_configs.splatfacto_configs:kc_splatfacto_mcmc"
    plugin = entry_points["nerfstudio.method_configs"]  # ns-train's, through the plugin's model
    assert plugin["splatfacto-mcmc"] == "kc_splatfacto.nerfstudio_plugin.entry_points:splatfacto_mcmc"
    assert plugin["kc-splatfacto-mcmc"] == "kc_splatfacto.nerfstudio_plugin.entry_points:kc_splatfacto_mcmc"


def test_kc_train_with_a_cap_below_the_seed_points_prints_one_line_naming_the_flag(tmp_path, capsys):
    from kc_splatfacto.cli import train as kc_train

    argv = ["splatfacto", "--data", "demo", "--output-dir", str(tmp_path), "--max-num-iterations", "1",
            "--pipeline.model.strategy", "mcmc", "--pipeline.model.max-gs-num", "10"]
    assert kc_train.entrypoint(argv) == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("kc-train: error: max_gs_num (10) is smaller than the "), lines
    assert lines[0].endswith("raise --pipeline.model.max-gs-num to at least 2000")


@pytest.mark.parametrize("step_verdict", ["host", "device"])
def test_an_ordinary_mcmc_step_adds_no_host_synchronisation(tmp_path, step_verdict):
    # the noise on the means and the two loss terms run every step: device work only (relocation and growth, every
    # refine_every steps, read their counts on the host)
    config = tiny_demo_config("splatfacto", tmp_path, iterations=40, steps_scale=1.0, strategy="mcmc",
                              cull_alpha_thresh=0.005)
    config.machine.step_verdict = step_verdict
    config.logging.steps_per_log = 1000
    config.logging.steps_per_gradient_shares = 0
    trainer = Trainer(config)
    trainer.setup()
    for step in range(30):  # warm
        trainer.train_iteration(step)
    steps = list(range(30, 36))
    assert all(s % training_state.PARAMETER_SCAN_EVERY for s in steps)
    found = host_syncs.count_ordinary_steps(trainer, steps, warm=2)  # as CUDA counts them (tests/engine)
    assert _by_function(found.ours(), len(steps) - 2) == KEPT[step_verdict]  # the step verdict's, as without MCMC
