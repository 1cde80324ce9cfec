"""The Splatfacto-like model (nerfstudio 1.1.5's ``SplatfactoModel``) with KC-3DGS's wavelet-domain losses.

``kc-splatfacto`` is this model with non-zero ``frequency`` weights (``wavelet_weight``, ``kc_weight``, ``cbc_weight``:
:class:`~kc_splatfacto.losses.frequency.FrequencyLossConfig`); with all three at zero it is the ``splatfacto`` baseline (loss 0.8 L1 + 0.2 (1 - SSIM)).

``steps_scale`` multiplies every step-based schedule (warm-up, refinement period, opacity reset, stop of splitting and
of screen-size culling, SH degree interval, resolution schedule): ``steps_scale=0.02`` plays Splatfacto's 30000-step
schedule in 600 steps, for short CPU runs.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass
from typing import Any, Literal

import torch
import torch.nn.functional as F

from kc_splatfacto.data.outputs import Cameras
from kc_splatfacto.losses.frequency import (
    FrequencyLoss,
    FrequencyLossConfig,
    WaveletBands,
    mean_band_kurtosis,
    target_key,
)
from kc_splatfacto.losses.layout import channels_first, composite_with_background
from kc_splatfacto.losses.wavelets import dropped_levels_phrase, supported_levels
from kc_splatfacto.metrics import mean_ssim, psnr
from kc_splatfacto.model.gaussians import init_gaussian_params
from kc_splatfacto.model.image_loss import ImageLoss
from kc_splatfacto.model.mcmc import MCMCStrategy, mcmc_regularization, splatfacto_mcmc
from kc_splatfacto.model.strategy import DefaultStrategy
from kc_splatfacto.render import SplitSH, rasterization
from kc_splatfacto.render.constants import FAR_PLANE, NEAR_PLANE, SH_MAX_DEGREE
from kc_splatfacto.render.rasterization import Rasterizer, RenderMode
from kc_splatfacto.settings import integer, real, setting

PlanDecision = Literal["schedule", "downscales", "background", "levels", "sh"]
PLAN_DECISIONS: tuple[str, ...] = PlanDecision.__args__  # type: ignore[attr-defined]
"""the scene plan's decisions (kc_splatfacto/plan/scene_plan.py), each one config field"""
EVAL_BACKGROUND = (0.1490, 0.1647, 0.2157)
"""Splatfacto's fixed background outside training when training uses random backgrounds (viser's grey)"""
SCALE_REG_WEIGHT = 0.1
"""PhysGaussian scale regularization weight in Splatfacto"""
SCALE_REG_EVERY = 10
"""Splatfacto evaluates the scale regularizer every 10th step only"""


def scale_steps(steps: int, steps_scale: float, at_least: int = 1) -> int:
    """A nominal step count compressed by ``steps_scale``: round(steps x steps_scale), at least ``at_least`` (the one
    rounding of every step-based schedule: the model's and the optimizers')."""
    return max(at_least, int(round(steps * steps_scale)))


@dataclass(frozen=True)
class StepSchedule:
    """The model config's step counts after ``steps_scale`` (each at least 1); ``reset_alpha_every`` in steps."""

    warmup_length: int
    refine_every: int
    reset_alpha_every: int
    resolution_schedule: int
    sh_degree_interval: int
    stop_screen_size_at: int
    stop_split_at: int


@dataclass
class SplatfactoModelConfig:
    """Splatfacto 1.1.5's defaults, plus KC-3DGS's frequency-domain losses (off by default)."""

    warmup_length: int = setting(500, integer(0))
    """period of steps where refinement is turned off"""
    refine_every: int = setting(100, integer(1))
    """period of steps where Gaussians are culled and densified"""
    resolution_schedule: int = setting(3000, integer(1))
    """training starts at 1/2^num_downscales resolution; every this many steps the resolution doubles"""
    background_color: Literal["random", "black", "white"] = "random"
    """background the render is composited over in training ('random': a new colour every step, viser's grey
    outside training); RGBA ground truth is composited over the same one"""
    num_downscales: int = setting(2, integer(0, 8))
    """training starts at 1/2^num_downscales resolution (see resolution_schedule)"""
    cull_alpha_thresh: float = setting(0.1, real(0.0, 1.0))
    """opacity below which Gaussians are culled"""
    cull_scale_thresh: float = setting(0.5, real(0.0, low_open=True))
    """scale (x scene scale) above which Gaussians are culled"""
    reset_alpha_every: int = setting(30, integer(1))
    """every this many refinements, reset the opacities"""
    densify_grad_thresh: float = setting(0.0008, real(0.0, low_open=True))
    """threshold of the (absolute) 2D mean gradient for densification"""
    use_absgrad: bool = True
    """use the absolute gradient (AbsGS) for densification"""
    densify_size_thresh: float = setting(0.01, real(0.0, low_open=True))
    """below this size (x scene scale) Gaussians are duplicated, otherwise split"""
    n_split_samples: int = setting(2, integer(1))
    """number of Gaussians a split Gaussian becomes"""
    max_num_gaussians: int | None = setting(2_000_000, integer(1, optional=True))
    """cap on densification (not in Splatfacto): beyond it only the highest-gradient candidates grow; None: no cap"""
    strategy: Literal["default", "mcmc"] = "default"
    """density control: 'default' (3DGS's split / duplicate / prune, Splatfacto 1.1.5's) or 'mcmc' (relocation of
    transparent Gaussians, growth by 5% per refinement up to max_gs_num, noise on the means; nerfstudio's main)"""
    max_gs_num: int = setting(1_000_000, integer(1))
    """mcmc: most Gaussians the run may hold (at least the number of seed points)"""
    noise_lr: float = setting(5e5, real(0.0))
    """mcmc: the means' noise is scaled by this times their learning rate"""
    mcmc_opacity_reg: float = setting(0.01, real(0.0))
    """mcmc: weight of the mean opacity in the loss (pushes unneeded Gaussians to transparency, then relocation)"""
    mcmc_scale_reg: float = setting(0.01, real(0.0))
    """mcmc: weight of the mean scale (exp of the log scales) in the loss"""
    sh_degree_interval: int = setting(1000, integer(1))
    """every this many steps turn on another SH degree"""
    cull_screen_size: float = setting(0.15, real(0.0, low_open=True))
    """cull Gaussians larger than this fraction of the screen"""
    split_screen_size: float = setting(0.05, real(0.0, low_open=True))
    """split Gaussians larger than this fraction of the screen"""
    stop_screen_size_at: int = setting(4000, integer(0))
    """stop culling/splitting by screen size at this step"""
    random_init: bool = False
    """initialize randomly even when the scene has seed points"""
    num_random: int = setting(50000, integer(1))
    """number of random initial Gaussians (random_init, or a scene without points)"""
    random_scale: float = setting(10.0, real(0.0, low_open=True))
    """side (x scene scale) of the cube random initial Gaussians fill"""
    ssim_lambda: float = setting(0.2, real(0.0, 1.0))
    """weight of the D-SSIM term in the main loss (1 - ssim_lambda) L1 + ssim_lambda (1 - SSIM)"""
    stop_split_at: int = setting(15000, integer(0))
    """stop densification (splitting and duplication) at this step"""
    sh_degree: int = setting(3, integer(0, SH_MAX_DEGREE))
    """maximum degree of the spherical harmonics of the colours (0: plain RGB)"""
    sh_views_per_coefficient: float = setting(0.0, real(0.0))
    """> 0: the SH degree also follows the number of training views, the largest d <= sh_degree whose (d+1)^2
    coefficients per colour each have at least this many views (2: degree 1 on 12 views, 0 on 5, 3 from 32 views);
    0: sh_degree as given"""
    use_scale_regularization: bool = False
    """PhysGaussian's scale regularization (penalizes max/min scale ratios above max_gauss_ratio)"""
    max_gauss_ratio: float = setting(10.0, real(1.0))
    """largest max/min scale ratio the scale regularization tolerates"""
    output_depth_during_training: bool = False
    """render the expected depth in training too (evaluation always renders it)"""
    rasterize_mode: Literal["classic", "antialiased"] = "classic"
    """'antialiased': gsplat's 2D filter with opacity compensation (Mip-Splatting), 'classic': 3DGS's"""
    rasterizer: Rasterizer = "auto"
    """which rasterizer renders: 'auto' (gsplat on CUDA when installed, the compiled CPU one otherwise), 'cpu',
    'torch' (the slow reference), 'gsplat'"""
    loss_cuda_graphs: bool = True
    """on CUDA, replay the image-space loss (L1, D-SSIM, the frequency terms) as a CUDA graph per training
    resolution, checked against the eager loss at first use (model/image_loss.py); no effect on the CPU"""
    steps_scale: float = setting(1.0, real(0.0, low_open=True))
    """multiplies every step-based schedule (see the module docstring)"""
    plan: Literal["on", "off"] = "off"
    """'on': the scene plan sets the step count (the asked one a budget), the warm-up, the background, the
    finest DWT levels left out and the SH degree from measurements of the training views, prints its table and
    writes plan.json (kc_splatfacto/plan/scene_plan.py); 'off': the fixed settings (the paper's, Splatfacto's)"""
    plan_skip: tuple[PlanDecision, ...] = ()
    """decisions of the scene plan that keep this config's value (schedule, downscales, background,
    levels, sh)"""
    frequency: FrequencyLossConfig = setting(default_factory=FrequencyLossConfig.off)
    """KC-3DGS's wavelet-domain losses (wavelet L1, KC, CBC) and their DWT; every weight 0 here (Splatfacto): the
    kc-splatfacto methods set the paper's (FrequencyLossConfig's defaults)"""

    @classmethod
    def upgrade_fields(cls, fields: dict[str, Any]) -> dict[str, Any]:
        """A ``config.yml`` of an earlier version held the frequency-loss settings as model fields (``kc_weight``,
        ...): gathered into ``frequency`` (the settings such a file lacks are Splatfacto's: weights 0); and
        ``rasterizer`` was ``rasterization_backend``."""
        if "rasterization_backend" in fields and "rasterizer" not in fields:  # the field's name before
            fields["rasterizer"] = fields.pop("rasterization_backend")
        names = [field.name for field in dataclasses.fields(FrequencyLossConfig)]
        flat = {name: fields.pop(name) for name in names if name in fields}
        if flat and "frequency" not in fields:
            fields["frequency"] = dataclasses.replace(FrequencyLossConfig.off(), **flat)
        elif flat:  # both forms: hand-edited; put the flat names back so the reader names them as unknown
            fields.update(flat)
        return fields

    def scaled(self, steps: int) -> int:
        """A step count compressed by ``steps_scale`` (at least 1)."""
        return scale_steps(steps, self.steps_scale)

    def step_schedule(self) -> StepSchedule:
        """Every step-based schedule with ``steps_scale`` applied (once: the model reads only this)."""
        return StepSchedule(
            warmup_length=self.scaled(self.warmup_length),
            refine_every=self.scaled(self.refine_every),
            reset_alpha_every=self.scaled(self.reset_alpha_every * self.refine_every),
            resolution_schedule=self.scaled(self.resolution_schedule),
            sh_degree_interval=self.scaled(self.sh_degree_interval),
            stop_screen_size_at=self.scaled(self.stop_screen_size_at),
            stop_split_at=self.scaled(self.stop_split_at),
        )

    def sh_degree_for_views(self, num_views: int) -> int:
        """The SH degree a scene of ``num_views`` training views gets: ``sh_degree``, capped by
        ``sh_views_per_coefficient`` (a view-dependent colour of degree d has (d+1)^2 unknowns per channel, and a
        Gaussian is seen by at most ``num_views`` views: with fewer views than unknowns it fits the training views'
        colours and guesses the rest)."""
        if self.sh_views_per_coefficient <= 0:
            return self.sh_degree
        degree = 0
        while degree < self.sh_degree and (degree + 2) ** 2 * self.sh_views_per_coefficient <= num_views:
            degree += 1
        return degree

    def density_strategy(self, num_train_data: int) -> DefaultStrategy | MCMCStrategy:
        """Density control as Splatfacto configures gsplat's strategies from these fields (step counts after
        ``steps_scale``): ``DefaultStrategy`` as 1.1.5 does (``num_train_data`` sets the pause after each opacity
        reset), ``MCMCStrategy`` as nerfstudio's main branch does (dead below ``cull_alpha_thresh``)."""
        schedule = self.step_schedule()
        if self.strategy == "mcmc":
            return splatfacto_mcmc(self, schedule.warmup_length, schedule.stop_split_at, schedule.refine_every)
        refine_every = schedule.refine_every
        reset_every = schedule.reset_alpha_every
        return DefaultStrategy(
            prune_opa=self.cull_alpha_thresh,
            grow_grad2d=self.densify_grad_thresh,
            grow_scale3d=self.densify_size_thresh,
            grow_scale2d=self.split_screen_size,
            prune_scale3d=self.cull_scale_thresh,
            prune_scale2d=self.cull_screen_size,
            refine_scale2d_stop_iter=schedule.stop_screen_size_at,
            refine_start_iter=schedule.warmup_length,
            refine_stop_iter=schedule.stop_split_at,
            reset_every=reset_every,
            refine_every=refine_every,
            # Splatfacto waits one pass over the training images after a reset; under heavy step compression that
            # pass could outlast the reset period, so it is capped at half of it.
            pause_refine_after_reset=min(int(num_train_data) + refine_every, reset_every // 2),
            absgrad=self.use_absgrad,
            n_split_samples=self.n_split_samples,
            max_gaussians=self.max_num_gaussians,
        )

    def setup(
        self,
        *,
        scene_scale: float = 1.0,
        num_train_data: int = 1,
        seed_points: tuple[torch.Tensor, torch.Tensor | None] | None = None,
    ) -> "SplatfactoModel":
        return SplatfactoModel(self, scene_scale=scene_scale, num_train_data=num_train_data, seed_points=seed_points)


def _max_abs(tensor: torch.Tensor) -> torch.Tensor:
    """max |x| (NaN if any x is NaN) in one read of the tensor: aminmax, not an |x| copy then a max."""
    if tensor.numel() == 0:
        return tensor.new_zeros(())
    low, high = torch.aminmax(tensor)
    return torch.maximum(-low, high)


def resize_image(image: torch.Tensor, d: int) -> torch.Tensor:
    """[H, W, C] -> [H // d, W // d, C] by d x d box averaging (Splatfacto's ``resize_image``)."""
    if d == 1:
        return image
    return F.avg_pool2d(image.permute(2, 0, 1)[None], kernel_size=d, stride=d)[0].permute(1, 2, 0)


def downscale_mask(mask: torch.Tensor, d: int) -> torch.Tensor:
    """[H, W, 1] bool -> [H // d, W // d, 1] float: 1 where all d x d pixels are set (a min-pool), else 0."""
    mask = mask.float()
    if d == 1:
        return mask
    return -F.max_pool2d(-mask.permute(2, 0, 1)[None], kernel_size=d, stride=d)[0].permute(1, 2, 0)


def host_to_device(tensor: torch.Tensor, device: torch.device) -> torch.Tensor:
    """``tensor`` on ``device`` without making the host wait for the device: from host memory to a CUDA device
    through a pinned staging copy and an asynchronous transfer (a blocking copy waits for every kernel queued before
    it: a host synchronisation per call); torch's pinned-memory allocator reuses the staging block only once the
    transfer is done. A tensor already on ``device`` is returned as it is."""
    if tensor.device.type == "cpu" and device.type == "cuda":
        tensor = tensor.pin_memory()
    return tensor.to(device, non_blocking=True)


def rescale_cameras(camera: Cameras, d: int) -> Cameras:
    """Cameras rendering 1/d of the resolution (intrinsics scaled, sizes floored as nerfstudio does)."""
    if d == 1:
        return camera
    Ks = camera.Ks.clone()
    Ks[:, :2, :] /= d
    return Cameras(camera.viewmats, Ks, camera.widths // d, camera.heights // d)


class SplatfactoModel(torch.nn.Module):
    """The Gaussians of one scene, their rendering and the losses (density control, the optimizers and the taking of
    a step belong to :class:`~kc_splatfacto.engine.training_state.TrainingState`).

    Args:
        config: the model config.
        scene_scale: radius of the normalized scene (density-control thresholds multiply it).
        num_train_data: number of training images (density control pauses that long after each opacity reset; with
            ``sh_views_per_coefficient`` it caps the SH degree).
        seed_points: ([M, 3] points, [M, 3] uint8 colours or None), or None for random initialization.
    """

    def __init__(
        self,
        config: SplatfactoModelConfig,
        *,
        scene_scale: float = 1.0,
        num_train_data: int = 1,
        seed_points: tuple[torch.Tensor, torch.Tensor | None] | None = None,
    ):
        super().__init__()
        self.config = config
        self.schedule = config.step_schedule()
        self.scene_scale = float(scene_scale)
        self.num_train_data = int(num_train_data)
        self.sh_degree = config.sh_degree_for_views(self.num_train_data)
        """the SH degree this scene's Gaussians hold (``config.sh_degree`` unless the views cap it)"""
        seeds = seed_points if seed_points is not None and not config.random_init else (None, None)
        self.gauss_params = init_gaussian_params(
            seeds[0],
            seeds[1],
            sh_degree=self.sh_degree,
            scene_scale=self.scene_scale,
            num_random=config.num_random,
            random_scale=config.random_scale,
        )
        self.step = 0
        """0-based index of the training step being taken, which every schedule reads (written by :meth:`set_step`
        alone)"""
        self.register_buffer("background_color", self._fixed_background(), persistent=False)
        self._frequency_loss: FrequencyLoss | None = None
        self._kurtosis_probe: FrequencyLoss | None = None
        self._image_loss: ImageLoss | None = None
        self._noted_sizes: set[tuple[int, int]] = set()  # training sizes (W, H) whose dropped levels were warned of

    # ----------------------------------------------------------------------------------------------- the step
    def set_step(self, step: int) -> None:
        """Make ``step`` (0-based) the step being taken: the resolution, the SH degree and density control follow
        it. The training state calls it at each training step, the pipeline when it restores a checkpoint."""
        self.step = int(step)

    def schedule_state(self) -> dict[str, int]:
        """What the schedules give at the current step: the SH degree in use and the training downscale factor."""
        return {"sh_degree": self.sh_degree_to_use(), "train_downscale": self.get_downscale_factor()}

    # ----------------------------------------------------------------------------------------------- parameters
    def parameter_groups(self) -> dict[str, torch.nn.Parameter]:
        """The Gaussian parameters by group name (nerfstudio's ``get_gaussian_param_groups``): what the optimizers
        step. Density control replaces a group's tensor, so ask again after it rather than keeping these."""
        return dict(self.gauss_params.items())

    def gaussian_state(self) -> dict[str, torch.Tensor]:
        """A detached copy of every Gaussian parameter by name (``means`` [N, 3], ... ``features_rest`` [N, K, 3]):
        what a checkpoint or a PLY export holds; :meth:`load_gauss_params` takes it back."""
        return {name: param.detach().clone() for name, param in self.gauss_params.items()}

    def gradient_peaks(self) -> tuple[list[str], torch.Tensor]:
        """(names, [G] max |gradient| of each group that has a gradient; NaN where one is NaN), on the device: read
        once with the rest of the step's verdict (one host synchronisation)."""
        names = [name for name, param in self.gauss_params.items() if param.grad is not None]
        if not names:
            return [], self.means.new_zeros(1)
        return names, torch.stack([_max_abs(self.gauss_params[name].grad) for name in names])

    @property
    def device(self) -> torch.device:
        return self.gauss_params["means"].device

    @property
    def num_points(self) -> int:
        return int(self.gauss_params["means"].shape[0])

    @property
    def means(self) -> torch.Tensor:
        return self.gauss_params["means"]

    @property
    def scales(self) -> torch.Tensor:
        return self.gauss_params["scales"]

    @property
    def quats(self) -> torch.Tensor:
        return self.gauss_params["quats"]

    @property
    def opacities(self) -> torch.Tensor:
        return self.gauss_params["opacities"]

    @property
    def features_dc(self) -> torch.Tensor:
        return self.gauss_params["features_dc"]

    @property
    def features_rest(self) -> torch.Tensor:
        return self.gauss_params["features_rest"]

    def load_gauss_params(self, state: dict[str, torch.Tensor]) -> None:
        """Replace the Gaussians by a checkpoint's (any N), keeping device and Parameter objects fresh."""
        device = self.device
        for name in list(self.gauss_params.keys()):
            key = name if name in state else f"gauss_params.{name}"
            if key not in state:
                raise KeyError(f"checkpoint has no Gaussian parameter '{name}'")
            self.gauss_params[name] = torch.nn.Parameter(state[key].detach().clone().to(device))

    def _fixed_background(self) -> torch.Tensor:
        colors = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0), "random": EVAL_BACKGROUND}
        return torch.tensor(colors[self.config.background_color], dtype=torch.float32)

    def _get_background_color(self) -> torch.Tensor:
        if self.training and self.config.background_color == "random":
            return torch.rand(3, device=self.device)
        return self.get_buffer("background_color").to(self.device)

    def sh_degree_to_use(self) -> int:
        return min(self.step // self.schedule.sh_degree_interval, self.sh_degree)

    def get_downscale_factor(self) -> int:
        """Training resolution divisor: 2^num_downscales at the start, halved every ``resolution_schedule`` steps."""
        if not self.training:
            return 1
        return 2 ** max(self.config.num_downscales - self.step // self.schedule.resolution_schedule, 0)

    # ----------------------------------------------------------------------------------------------- rendering
    def get_outputs(self, camera: Cameras, absgrad: bool = False) -> dict[str, Any]:
        """Render one camera.

        Args:
            camera: Cameras of length 1.
            absgrad: also accumulate the absolute gradient of the projected means (``info["means2d"].absgrad``),
                for a density-control strategy that reads it.
        Returns:
            ``rgb`` [H, W, 3] in [0, 1], ``depth`` [H, W, 1] (expected depth; None in training unless
            ``output_depth_during_training``), ``accumulation`` [H, W, 1], ``background`` [3], and ``info``: the
            rasterizer's (``means2d``, ``radii``, ...), what density control reads (the training state's strategy,
            :mod:`kc_splatfacto.engine.training_state`). In training H, W are the size at the current training
            resolution.
        """
        if len(camera) != 1:
            raise ValueError(f"get_outputs renders one camera at a time, got {len(camera)}")
        # the camera stays where the dataset holds it (host memory): its size is read there without waiting for the
        # device, and only the two matrices the rasterizer reads travel, asynchronously
        camera = rescale_cameras(camera, self.get_downscale_factor())
        width, height = int(camera.widths[0]), int(camera.heights[0])
        colors: torch.Tensor | SplitSH
        if self.sh_degree > 0:
            # the two parameters as they are: the cpu backend reads them in place (no [N, 16, 3] copy per step)
            colors = SplitSH(self.features_dc[:, None, :], self.features_rest)
            sh_degree = self.sh_degree_to_use()
        else:
            colors = torch.sigmoid(self.features_dc)
            sh_degree = None
        render_mode: RenderMode = "RGB+ED" if (self.config.output_depth_during_training or not self.training) else "RGB"
        render, alpha, info = rasterization(
            means=self.means,
            quats=self.quats,
            scales=torch.exp(self.scales),
            opacities=torch.sigmoid(self.opacities).squeeze(-1),
            colors=colors,
            viewmats=host_to_device(camera.viewmats.float(), self.device),
            Ks=host_to_device(camera.Ks.float(), self.device),
            width=width,
            height=height,
            sh_degree=sh_degree,
            near_plane=NEAR_PLANE,
            far_plane=FAR_PLANE,
            render_mode=render_mode,
            rasterize_mode=self.config.rasterize_mode,
            absgrad=absgrad,
            rasterizer=self.config.rasterizer,
        )
        background = self._get_background_color()
        alpha = alpha[0]
        rgb = torch.clamp(render[0, ..., :3] + (1 - alpha) * background, 0.0, 1.0)
        depth = None
        if render_mode == "RGB+ED":
            depth = render[0, ..., 3:4]
            depth = torch.where(alpha > 0, depth, depth.detach().max())
        return {"rgb": rgb, "depth": depth, "accumulation": alpha, "background": background, "info": info}

    def get_gt_img(self, image: torch.Tensor) -> torch.Tensor:
        """[H, W, C] uint8 or float -> float32 in [0, 1] at the current training resolution, on the model's device.

        C = 3, or 4 (straight alpha in, *premultiplied* alpha out: colours are multiplied by alpha before the box
        downscale, so a transparent pixel's colour never leaks into its neighbours; see :func:`composite_with_background`).
        """
        image = host_to_device(image, self.device)
        image = image.float() / 255.0 if image.dtype == torch.uint8 else image.float()
        if image.shape[-1] == 4:
            image = torch.cat([image[..., :3] * image[..., 3:4], image[..., 3:4]], dim=-1)
        return resize_image(image, self.get_downscale_factor())

    def get_gt_and_mask(
        self, outputs: dict[str, Any], batch: dict[str, Any]
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The ground truth the render is compared with, and where.

        The GT (RGBA: composited over ``outputs["background"]``, the background this render used, as nerfstudio
        does) at the render's resolution [h, w, 3], and ``batch["mask"]`` at that resolution as [h, w, 1] float
        (None without a mask). A low-resolution pixel counts only when every full-resolution pixel it averages does
        (a min-pool), so no masked-out pixel ever reaches a loss or a metric.
        """
        gt_img = composite_with_background(self.get_gt_img(batch["image"]), outputs["background"], premultiplied=True)
        mask = batch.get("mask")
        if mask is not None:
            mask = downscale_mask(host_to_device(mask, self.device), self.get_downscale_factor())
            if mask.shape[:2] != gt_img.shape[:2]:
                raise ValueError(f"mask {tuple(mask.shape)} and ground truth {tuple(gt_img.shape)} differ in size")
        return gt_img, mask

    def _masked_pair(
        self, outputs: dict[str, Any], batch: dict[str, Any]
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """(pred, gt, mask) as [h, w, 3], [h, w, 3], [h, w, 1] or None; with a mask both images are multiplied by
        it (nerfstudio's masking: every term then compares zeros outside the mask)."""
        gt_img, mask = self.get_gt_and_mask(outputs, batch)
        pred_img = outputs["rgb"]
        if gt_img.shape != pred_img.shape:
            raise ValueError(f"render {tuple(pred_img.shape)} and ground truth {tuple(gt_img.shape)} differ in size")
        if mask is not None:
            gt_img, pred_img = gt_img * mask, pred_img * mask
        return pred_img, gt_img, mask

    # ----------------------------------------------------------------------------------------------- losses
    @property
    def frequency_loss(self) -> FrequencyLoss | None:
        """KC-3DGS's wavelet/KC/CBC module, built from the config on first use (None when every weight is zero)."""
        if self._frequency_loss is None:
            settings = self.config.frequency
            if not settings.active:
                return None
            self._frequency_loss = settings.setup()
            # a non-finite render is caught once per step with the loss and gradients (TrainingState._verdict), not
            # by a check of its own: each is a host synchronisation on CUDA
            self._frequency_loss.check_finite = False
            # too small an image for the DWT's levels is said here, in the resolution schedule's terms
            # (:meth:`_warn_dropped_levels`)
            self._frequency_loss.warn_dropped_levels = False
        return self._frequency_loss

    def _warn_dropped_levels(self, height: int, width: int, full_height: int, full_width: int) -> None:
        """Once per training size: the frequency loss's DWT leaves out levels a (height x width) training image is
        too small for; the warning names the size W x H, the resolution schedule's fraction of the full
        (full_width x full_height) image, and the step from which all levels fit (if any)."""
        settings = self.config.frequency
        wave, levels = settings.wave, settings.wavelet_levels
        kept = supported_levels(height, width, wave, levels)
        if kept >= levels or (width, height) in self._noted_sizes:
            return
        self._noted_sizes.add((width, height))
        d = self.get_downscale_factor()
        if d > 1:
            where = f"while training at 1/{d} resolution ({width}x{height} of {full_width}x{full_height})"
        else:
            where = f"at {width}x{height}"
        until = ""
        finer = d // 2
        while finer >= 1:
            if supported_levels(full_height // finer, full_width // finer, wave, levels) == levels:
                step = (self.config.num_downscales - finer.bit_length() + 1) * self.schedule.resolution_schedule
                size = "full resolution" if finer == 1 else f"1/{finer} resolution"
                until = f" until step {step} ({size}, {full_width // finer}x{full_height // finer})"
                break
            finer //= 2
        warnings.warn(
            f"FrequencyLoss: {where} a {wave} DWT supports only {kept} of the {levels} requested levels; "
            f"{dropped_levels_phrase(levels - kept, levels)} left out{until}",
            stacklevel=3,
        )

    def wavelet_target_key(self, batch: dict[str, Any]) -> tuple[int, int] | None:
        """Where the frequency loss caches this batch's GT target: (training image, resolution) when the composited
        GT is the same at every visit (RGB, or RGBA over a fixed background), else None (an RGBA image over a random
        background changes with every draw)."""
        return target_key(batch, self.get_downscale_factor(),
                          self.training and self.config.background_color == "random")

    def get_loss_dict(self, outputs: dict[str, Any], batch: dict[str, Any]) -> dict[str, torch.Tensor]:
        """Splatfacto's ``main_loss`` = (1 - ssim_lambda) L1 + ssim_lambda (1 - SSIM); ``scale_reg`` when enabled;
        ``wavelet_loss`` / ``kc_loss`` / ``cbc_loss`` (already weighted) only when their weight is non-zero.

        Every term compares ``pred * mask`` with ``gt * mask`` (see :meth:`_masked_pair`; docs/losses.md says what
        that means for the band statistics), the GT composited over the render's background.

        Args:
            outputs: from :meth:`get_outputs`.
            batch: ``image`` [H, W, 3|4] (uint8 or float, full resolution), ``image_idx`` (int, the cache key) and
                optionally ``mask`` [H, W, 1] (bool, True = use the pixel).
        """
        pred_img, gt_img, _ = self._masked_pair(outputs, batch)
        if self.frequency_loss is not None:
            self._warn_dropped_levels(*pred_img.shape[:2], *batch["image"].shape[:2])
            self.frequency_loss.downscale = self.get_downscale_factor()  # the finest levels it leaves out follow it
        loss_dict = self.image_loss(pred_img, gt_img, key=self.wavelet_target_key(batch))
        if self.config.use_scale_regularization:
            if self.step % SCALE_REG_EVERY == 0:
                scale_exp = torch.exp(self.scales)
                ratio = scale_exp.amax(dim=-1) / scale_exp.amin(dim=-1)
                max_ratio = ratio.new_full((), self.config.max_gauss_ratio)  # filled on the device: no copy
                loss_dict["scale_reg"] = SCALE_REG_WEIGHT * (torch.maximum(ratio, max_ratio) - max_ratio).mean()
            else:
                loss_dict["scale_reg"] = torch.zeros((), device=self.device)
        loss_dict.update(self.mcmc_regularization())
        return loss_dict

    @property
    def image_loss(self) -> ImageLoss:
        """The main loss and the frequency terms of a (composited, masked) render: :class:`ImageLoss`."""
        if self._image_loss is None:
            self._image_loss = ImageLoss(self.config.ssim_lambda, self.frequency_loss, self.config.loss_cuda_graphs)
        return self._image_loss

    def mcmc_regularization(self) -> dict[str, torch.Tensor]:
        """With the mcmc strategy, nerfstudio main's opacity and scale terms (:func:`~.mcmc.mcmc_regularization`);
        otherwise nothing."""
        if self.config.strategy != "mcmc":
            return {}
        return mcmc_regularization(self.config, self.opacities, self.scales)

    @torch.no_grad()
    def get_metrics_dict(
        self, outputs: dict[str, Any], batch: dict[str, Any], with_kurtosis: bool = False
    ) -> dict[str, Any]:
        """``psnr`` and ``gaussian_count``; with ``with_kurtosis`` (logging steps only: two DWTs) also
        ``kurtosis_render`` / ``kurtosis_gt``: per detail band (finest level first, H V D), channel-averaged."""
        pred_img, gt_img, mask = self._masked_pair(outputs, batch)
        metrics: dict[str, Any] = {
            "psnr": float(psnr(channels_first(pred_img), channels_first(gt_img),
                               mask=None if mask is None else channels_first(mask))),
            "gaussian_count": self.num_points,
        }
        if with_kurtosis:
            frequency_loss = self.frequency_loss
            cached = None if frequency_loss is None else frequency_loss.cached_target(self.wavelet_target_key(batch))
            if cached is not None and cached.skipped_levels:  # the log holds every level's bands
                cached = None
            metrics["kurtosis_render"] = self.band_kurtosis(pred_img)
            metrics["kurtosis_gt"] = self.band_kurtosis(cached or gt_img)
        return metrics

    @torch.no_grad()
    def get_image_metrics(self, outputs: dict[str, Any], batch: dict[str, Any]) -> tuple[dict[str, float], Any]:
        """Evaluation metrics of one view: ``psnr`` and ``ssim`` (mean of the SSIM map), both over the mask when the
        batch has one; also returns (pred, gt) as [1, 3, H, W] (masked) for further metrics (LPIPS)."""
        pred_img, gt_img, mask = self._masked_pair(outputs, batch)
        pred_bchw, gt_bchw = channels_first(pred_img).float(), channels_first(gt_img)
        mask = None if mask is None else channels_first(mask)
        metrics = {"psnr": float(psnr(pred_bchw, gt_bchw, mask=mask)),
                   "ssim": float(mean_ssim(pred_bchw, gt_bchw, mask=mask))}
        return metrics, (pred_bchw, gt_bchw)

    def band_kurtosis(self, image: Any) -> list[float]:
        """Excess kurtosis of every detail subband, channel-averaged: 3 x levels values.

        ``image`` is an [H, W, 3] image or the GT's cached WaveletBands (whose kurtosis is read, not recomputed).
        """
        if not isinstance(image, WaveletBands):
            if self._kurtosis_probe is None:
                # the loss itself (which get_loss_dict has warned about a too small image for), or (every weight
                # zero: no wavelet loss to warn about) a silent module with the same DWT settings; either way a
                # level an image is too small for is absent from the logged values
                self._kurtosis_probe = self.frequency_loss or self.config.frequency.setup()
                self._kurtosis_probe.warn_dropped_levels = False
            with torch.no_grad():
                image = self._kurtosis_probe.bands(channels_first(image.detach().float()), covariance=False,
                                                   every_level=True)
        return mean_band_kurtosis(image)
