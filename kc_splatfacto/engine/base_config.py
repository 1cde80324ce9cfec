"""The engine's configs that build nothing themselves (nerfstudio's ``configs/base_config.py``): where to run
(:class:`MachineConfig`), what to log (:class:`LoggingConfig`; engine/loggers.py builds its backends) and how to watch
(:class:`ViewerConfig`; the viewer package builds the viewer from it).

Every config that builds something lives beside the class it builds and has ``setup()``:
``trainer.TrainerConfig -> Trainer``, ``pipeline.PipelineConfig -> Pipeline``, ``datamanager.DataManagerConfig ->
DataManager``, ``model.splatfacto.SplatfactoModelConfig -> SplatfactoModel``, ``optimizers.OptimizersConfig``. This
module imports none of them: it is a leaf of the engine.
"""

from __future__ import annotations

import random
import re
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from kc_splatfacto.errors import UserError
from kc_splatfacto.settings import SEED_MAX, Rule, integer, real, setting

DEVICE_NAME = re.compile(r"^(auto|cpu|cuda(:\d+)?)$")
"""the devices a run can train on: the CPU, or CUDA through gsplat (any other torch device has no rasterizer)"""


def device_name() -> Rule:
    """``--machine.device``'s range: checked with the other settings, before torch is asked to parse it."""
    return Rule(lambda value: isinstance(value, str) and DEVICE_NAME.match(value) is not None,
                "'auto', 'cpu', 'cuda' or 'cuda:N' (N the index of a GPU)")


def _gsplat_importable() -> bool:
    try:
        import gsplat  # noqa: F401
    except Exception:  # ImportError, or a CUDA build failing at import
        return False
    return True


@dataclass
class MachineConfig:
    """Where and how reproducibly to run."""

    seed: int = setting(42, integer(0, SEED_MAX))
    """seed of torch, numpy and python's random"""
    device: str = setting("auto", device_name())
    """'auto' (CUDA when available and gsplat imports, else CPU), 'cpu', 'cuda', 'cuda:1', ..."""
    memory_budget_gb: float = setting(0.0, real(0.0))
    """memory (GB; RAM, or the GPU's on CUDA) past which density control adds no Gaussians, so that a run stops
    growing instead of being killed; 0: 85% of what the process may use when the run starts (engine/memory.py)"""
    step_verdict: Literal["auto", "host", "device"] = "auto"
    """where a step's verdict (is the render, loss and gradient finite?) is taken: 'host' reads it before the update
    (one synchronisation per step; a bad step is reported at once), 'device' skips a bad update on the device (Adam's
    found_inf) and reports it at the next log, evaluation or checkpoint; 'auto': device on CUDA, host on the CPU"""

    def resolve_device(self) -> torch.device:
        if self.device == "auto":
            # CUDA only pays with gsplat's kernels: the rasterizer "auto" refuses CUDA tensors without
            # gsplat (the compiled rasterizer is CPU-only), so without gsplat training stays on the CPU
            return torch.device("cuda" if torch.cuda.is_available() and _gsplat_importable() else "cpu")
        if not device_name().check(self.device):  # a config built in Python, never validated
            raise UserError(f"--machine.device {self.device!r} is not a device: use {device_name().allowed}")
        device = torch.device(self.device)
        if device.type == "cuda" and not torch.cuda.is_available():
            raise UserError(f"--machine.device {self.device}: CUDA is not available here; use 'cpu' or 'auto'")
        if device.type == "cuda" and device.index is not None and device.index >= torch.cuda.device_count():
            raise UserError(f"--machine.device {self.device}: this machine has {torch.cuda.device_count()} GPU(s), "
                            f"numbered from 0; use 'cuda' or 'cuda:0'")
        return device

    def seed_everything(self) -> None:
        random.seed(self.seed)
        np.random.seed(self.seed)
        torch.manual_seed(self.seed)


@dataclass
class LoggingConfig:
    """What the trainer writes while it runs."""

    steps_per_log: int = setting(10, integer(1))
    """train records in metrics.jsonl (with per-band kurtosis) every this many steps"""
    progress_bar: bool = True
    """progress on stderr: a tqdm bar on a terminal, else a line every ``steps_per_progress_line`` steps"""
    steps_per_progress_line: int = setting(100, integer(1))
    """when stderr is not a terminal (a log file, CI): one progress line every this many steps"""
    profile_phases: bool = False
    """synchronize and time each phase of a step (render, losses, backward, optimizer, density control)"""
    steps_per_gradient_shares: int = setting(100, integer(0))
    """every this many steps a ``gradient_shares`` record: each loss term's image-gradient norm relative to the
    photometric term's (engine/gradient_shares.py; ~60 ms on a 192x128 CPU render, excluded from train_s); 0 turns it off"""
    tensorboard: bool = False
    """also write tensorboard event files into the run folder (loss terms, PSNR/SSIM/LPIPS, Gaussian count, step
    time, eval images); needs ``pip install 'kc-splatfacto[tensorboard]'``"""
    wandb: bool = False
    """also log to wandb, offline, into the run folder's wandb/ (``wandb sync`` uploads it later); needs
    ``pip install 'kc-splatfacto[wandb]'``"""
    wandb_project: str = "kc-splatfacto"
    """the wandb project the offline run belongs to"""
    eval_images: int = setting(1, integer(0))
    """eval views whose render beside the ground truth tensorboard/wandb receive at each evaluation (0: none)"""


@dataclass
class ViewerConfig:
    """The live viewer of ``kc-train --viewer True`` (viser, in the browser); ``kc-viewer`` reads the same fields."""

    enabled: bool = False
    """serve the scene in the browser while it trains (needs ``pip install 'kc-splatfacto[viewer]'``)"""
    host: str = "127.0.0.1"
    """address the viewer listens on ('0.0.0.0' for other machines)"""
    port: int = setting(7007, integer(0, 65535))
    """port of the viewer (nerfstudio's default); the next free one when taken"""
    max_render_pixels: int = setting(160 * 120, integer(1))
    """the largest render the viewer asks of the rasterizer while training (the browser scales it up)"""
    render_share: float = setting(0.05, real(0.0, 1.0, low_open=True))
    """at most this fraction of the wall-clock time goes into viewer renders while training (nerfstudio's
    'train util' is 1 minus it)"""
    quit_on_train_completion: bool = False
    """exit when training ends instead of serving the finished scene until Ctrl-C"""
