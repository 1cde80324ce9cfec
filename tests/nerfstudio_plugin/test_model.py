"""``KCSplatfactoModel`` with nerfstudio installed: for the same render and ground truth its three loss terms equal
``kc-train``'s model's exactly (values and gradients; RGB, RGBA, masks), each present only when its weight is
non-zero, the ground truth's statistics computed once per image; on the CPU it trains: nerfstudio's own density
control (gsplat 1.4's ``DefaultStrategy``) runs on the CPU rasterizer's ``info`` and grows and prunes Gaussians."""

from __future__ import annotations

import pytest
import torch

pytest.importorskip("nerfstudio", reason="nerfstudio is not installed here: run `make test-nerfstudio`")

from nerfstudio.cameras.cameras import Cameras  # noqa: E402
from nerfstudio.data.scene_box import SceneBox  # noqa: E402

from kc_splatfacto.losses.frequency import FrequencyLossConfig  # noqa: E402
from kc_splatfacto.model.splatfacto import SplatfactoModelConfig  # noqa: E402
from kc_splatfacto.nerfstudio_plugin.model import KCSplatfactoModelConfig  # noqa: E402

TERMS = ("wavelet_loss", "kc_loss", "cbc_loss")
H, W = 48, 64


def _seed_points(n: int = 400, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    xyz = (torch.rand(n, 3, generator=g) - 0.5) * 1.5
    rgb = torch.randint(0, 256, (n, 3), generator=g, dtype=torch.uint8)
    return xyz, rgb


def plugin_model(**overrides):
    config = KCSplatfactoModelConfig(num_downscales=0, **overrides)
    model = config.setup(scene_box=SceneBox(aabb=torch.tensor([[-1.0] * 3, [1.0] * 3])), num_train_data=4,
                         seed_points=_seed_points(), device="cpu")
    return model.train()


def project_model(**overrides):
    return SplatfactoModelConfig(num_downscales=0, frequency=FrequencyLossConfig(), **overrides).setup(
        num_train_data=4).train()


def _inputs(channels: int = 3, seed: int = 1, mask: bool = False):
    g = torch.Generator().manual_seed(seed)
    gt = torch.randint(0, 256, (H, W, channels), generator=g, dtype=torch.uint8)
    batch = {"image": gt, "image_idx": 2}
    if mask:
        batch["mask"] = torch.rand(H, W, 1, generator=g) > 0.3
    pred = torch.rand(H, W, 3, generator=g).requires_grad_()
    return pred, batch


@pytest.mark.parametrize("channels,mask,background", [(3, False, "random"), (3, True, "random"), (4, False, "white")])
def test_the_three_terms_equal_kc_trains_for_the_same_render_and_ground_truth(channels, mask, background):
    pred, batch = _inputs(channels, mask=mask)
    outputs_bg = torch.tensor([0.2, 0.5, 0.7]) if background == "random" else torch.ones(3)
    ours, theirs = plugin_model(background_color=background), project_model(background_color=background)
    values, grads = {}, {}
    for name, model in (("plugin", ours), ("kc-train", theirs)):
        losses = model.get_loss_dict({"rgb": pred, "background": outputs_bg}, batch)
        values[name] = {term: losses[term] for term in TERMS}
        grads[name] = torch.autograd.grad(sum(values[name].values()), pred)[0]
    for term in TERMS:
        assert values["plugin"][term] > 0
        assert torch.equal(values["plugin"][term], values["kc-train"][term]), term
    assert torch.equal(grads["plugin"], grads["kc-train"])


def test_a_term_is_computed_only_when_its_weight_is_not_zero_and_the_target_is_cached_per_image():
    pred, batch = _inputs()
    background = torch.tensor([0.2, 0.5, 0.7])
    model = plugin_model(frequency=FrequencyLossConfig(kc_weight=0.0))
    first = model.get_loss_dict({"rgb": pred, "background": background}, batch)
    assert "kc_loss" not in first and "wavelet_loss" in first and "cbc_loss" in first
    assert list(model.frequency_loss._targets) == [(2, 1)]  # (image index, downscale factor)
    cached = model.frequency_loss.cached_target((2, 1))
    again = model.get_loss_dict({"rgb": pred, "background": background}, batch)
    assert model.frequency_loss.cached_target((2, 1)) is cached and torch.equal(again["cbc_loss"], first["cbc_loss"])
    plain = plugin_model(frequency=FrequencyLossConfig.off())
    assert plain.frequency_loss is None
    assert not set(TERMS) & set(plain.get_loss_dict({"rgb": pred, "background": background}, batch))


def _camera() -> Cameras:
    c2w = torch.eye(4)[:3][None]
    c2w[0, 2, 3] = 2.5  # looking down -z (OpenGL) at the seed cloud around the origin
    return Cameras(camera_to_worlds=c2w, fx=60.0, fy=60.0, cx=W / 2, cy=H / 2, width=W, height=H)


def train_by_hand(model, steps: int = 12, on_losses=None, on_density=None) -> list[int]:
    """nerfstudio's training step written out (its Trainer without the loop's extras): render, loss, backward, Adam,
    then the model's density control, on one random image. ``on_losses(step, outputs, losses)`` sees each step's
    loss terms; ``on_density(step, means)`` each step after density control, with the means before it. Returns the
    Gaussian count after each step."""
    optimizers = {name: torch.optim.Adam(params, lr=1e-2) for name, params in model.get_gaussian_param_groups().items()}
    model.optimizers = optimizers
    gt = (torch.rand(H, W, 3, generator=torch.Generator().manual_seed(3)) * 255).to(torch.uint8)
    counts = []
    for step in range(steps):
        model.step = step
        outputs = model.get_outputs(_camera())
        losses = model.get_loss_dict(outputs, {"image": gt, "image_idx": 0})
        if on_losses is not None:
            on_losses(step, outputs, losses)
        sum(losses.values()).backward()
        for optimizer in optimizers.values():
            optimizer.step()
            optimizer.zero_grad()
        means = model.gauss_params["means"].detach().clone()
        model.step_post_backward(step)
        if on_density is not None:
            on_density(step, means)
        counts.append(model.num_points)
    return counts


def test_it_trains_on_the_cpu_with_nerfstudios_density_control():
    # refinement at step 9: after the 2-step warm-up, every 3 steps, once the pause of num_train_data + refine_every
    # steps after the (step-0) opacity reset is over
    model = plugin_model(warmup_length=2, refine_every=3, densify_grad_thresh=1e-7, sh_degree_interval=2)

    def check(step, outputs, losses):
        assert outputs["rgb"].shape == (H, W, 3) and model.info["radii"].shape == (1, model.num_points)
        assert set(TERMS) <= set(losses)

    counts = train_by_hand(model, on_losses=check)
    # every Gaussian seen with a gradient above the threshold is split, then the transparent ones are pruned: gsplat
    # 1.4's DefaultStrategy on the CPU rasterizer's screen statistics
    assert counts[:9] == [400] * 9 and counts[9] == counts[-1] and 400 < counts[9] < 800
    assert all(torch.isfinite(p).all() for p in model.gauss_params.values())
    model.eval()
    rendered = model.get_outputs_for_camera(_camera())
    assert rendered["depth"].shape == (H, W, 1) and rendered["rgb"].shape == (H, W, 3)


def test_a_checkpoint_loads_whichever_lpips_wrote_it():
    model = plugin_model()
    state = model.state_dict()
    assert not [k for k in state if k.startswith("lpips.")]  # the offline LPIPS keeps its network out
    foreign = {**state, "lpips.net.net.slice1.0.weight": torch.zeros(64, 3, 11, 11)}  # as torchmetrics' on a GPU
    other = plugin_model()
    other.load_state_dict(foreign)
    assert torch.equal(other.means, model.means)


def test_with_mcmc_it_trains_on_the_cpu_holds_its_cap_and_adds_the_two_terms():
    # refinement at steps 3, 6, 9 (after the 2-step warm-up, every 3 steps): 400 -> 420 -> 440, then the cap holds
    model = plugin_model(strategy="mcmc", max_gs_num=440, warmup_length=2, refine_every=3, cull_alpha_thresh=0.005,
                         sh_degree_interval=2)

    def check_regularisers(step, outputs, losses):
        opacities = torch.sigmoid(model.gauss_params["opacities"].detach().double())
        scales = torch.exp(model.gauss_params["scales"].detach().double())
        assert float(losses["mcmc_opacity_reg"].detach()) == pytest.approx(0.01 * float(opacities.mean()), rel=1e-5)
        assert float(losses["mcmc_scale_reg"].detach()) == pytest.approx(0.01 * float(scales.mean()), rel=1e-5)

    def check_noise(step, means):
        if step % 3:  # no refinement: only the noise, scaled by the means' rate, moved the means
            assert not torch.equal(means, model.gauss_params["means"])

    counts = train_by_hand(model, on_losses=check_regularisers, on_density=check_noise)
    assert counts == [400] * 3 + [420] * 3 + [440] * 6
    assert all(torch.isfinite(p).all() for p in model.gauss_params.values())


def test_with_mcmc_a_cap_below_the_seed_points_is_the_projects_one_line_error():
    from kc_splatfacto.model.mcmc import GaussianCapError

    with pytest.raises(GaussianCapError, match=r"max_gs_num \(100\) is smaller than the 400 initial Gaussians"):
        plugin_model(strategy="mcmc", max_gs_num=100)
