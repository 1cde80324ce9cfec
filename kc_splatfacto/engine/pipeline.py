"""The pipeline (nerfstudio's ``VanillaPipeline``): owns the data manager and the model, and the step's state.

A training step through the pipeline, as the trainer takes it (the trainer times the calls and owns the optimizers):

1. :meth:`Pipeline.train_view`: the model is set to the step (``model.set_step``, the one place a step is set), the
   data manager draws the next view (camera, uint8 image, index), the model renders it (``model.get_outputs``) and
   density control's pre-backward hook runs on what rendering produced (``model.before_backward(outputs)``);
2. :meth:`Pipeline.train_losses`: the render against the ground truth (``model.get_loss_dict``);
3. the trainer's backward, optimizer step and schedule update, then :meth:`Pipeline.after_optimizer_step`: density
   control with the same ``outputs`` and the optimizers (``model.step_post_backward``; MCMC reads the means' learning
   rate from theirs).

Besides: the logged training metrics, the evaluation of a split and the checkpointed state (Gaussians,
density-control statistics, image order). ``load_run`` (kc-eval, kc-render, kc-export, kc-viewer) builds the same
pipeline and uses its model and datasets.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import torch

from kc_splatfacto.data.base import DataParserConfig
from kc_splatfacto.engine.datamanager import DataManager, DataManagerConfig
from kc_splatfacto.engine.evaluation import evaluate_split
from kc_splatfacto.model.splatfacto import SplatfactoModel, SplatfactoModelConfig


@dataclass
class PipelineConfig:
    """The data manager and the model; ``setup()`` builds the :class:`Pipeline`."""

    datamanager: DataManagerConfig = field(default_factory=DataManagerConfig)
    model: SplatfactoModelConfig = field(default_factory=SplatfactoModelConfig)

    def setup(self, *, device: torch.device | str = "cpu", seed: int = 42,
              dataparser: DataParserConfig | None = None) -> Pipeline:
        return Pipeline(self, device=device, seed=seed, dataparser=dataparser)


class Pipeline:
    """The scene's data and model.

    Args:
        config: the pipeline config (left unchanged; the resolved dataparser is ``datamanager.dataparser_config``).
        device: where the model lives.
        seed: seed of the training-image order.
        dataparser: the run's resolved dataparser config (see :meth:`DataManagerConfig.setup`).
    """

    def __init__(self, config: PipelineConfig, *, device: torch.device | str = "cpu", seed: int = 42,
                 dataparser: DataParserConfig | None = None):
        self.config = config
        self.datamanager: DataManager = config.datamanager.setup(seed=seed, dataparser=dataparser)
        train_outputs = self.datamanager.train_outputs
        self.model: SplatfactoModel = config.model.setup(
            scene_scale=float(train_outputs.scene_scale),
            num_train_data=len(self.datamanager.train_dataset),
            seed_points=self.datamanager.seed_points(),
        ).to(device)

    @property
    def device(self) -> torch.device:
        return self.model.device

    def train_view(self, step: int) -> tuple[dict[str, Any], dict[str, Any]]:
        """Step 1 of a training step (module docstring): the model set to ``step`` (0-based), the next training
        view drawn and rendered, ready for backward. Returns (outputs, batch)."""
        self.model.set_step(step)
        batch = self.datamanager.next_train()
        outputs = self.model.get_outputs(batch["camera"])
        self.model.before_backward(outputs)
        return outputs, batch

    def train_losses(self, outputs: dict[str, Any], batch: dict[str, Any]) -> dict[str, torch.Tensor]:
        """Step 2: the loss terms of a training render. A non-finite render gives non-finite losses, not an error:
        the trainer checks the loss and the gradients once after backward (one host synchronisation per step)."""
        return self.model.get_loss_dict(outputs, batch)

    def get_train_loss_dict(self, step: int) -> tuple[dict[str, Any], dict[str, torch.Tensor], dict[str, Any]]:
        """:meth:`train_view` then :meth:`train_losses` (nerfstudio's name): (outputs, loss_dict, batch)."""
        outputs, batch = self.train_view(step)
        return outputs, self.train_losses(outputs, batch), batch

    def after_optimizer_step(self, outputs: dict[str, Any], optimizers: dict[str, torch.optim.Optimizer]) -> dict[str, int]:
        """Step 3: density control after the optimizer step, from the step's ``outputs``; the counts of what it
        did (default: duplicated, split, pruned, opacity_reset; mcmc: relocated, added)."""
        return self.model.step_post_backward(optimizers, outputs)

    def get_train_metrics_dict(self, outputs: dict[str, Any], batch: dict[str, Any]) -> dict[str, Any]:
        """The logged training metrics of one step (PSNR, Gaussian count, per-band kurtosis of render and GT)."""
        return self.model.get_metrics_dict(outputs, batch, with_kurtosis=True)

    def get_average_eval_image_metrics(
        self, *, split: str = "eval", with_lpips: bool = True, extra_lpips_nets: Sequence[str] = ()
    ) -> dict[str, Any]:
        """Render every image of the eval (or train) split: mean PSNR/SSIM/LPIPS and per-image values
        (see :func:`kc_splatfacto.engine.evaluation.evaluate_split`; ``extra_lpips_nets`` adds ``lpips_<net>``)."""
        dataset = self.datamanager.train_dataset if split == "train" else self.datamanager.eval_dataset
        return evaluate_split(self.model, dataset, with_lpips=with_lpips, extra_lpips_nets=extra_lpips_nets)

    # --------------------------------------------------------------------------------------------- state
    def state_dict(self) -> dict[str, Any]:
        """The Gaussians (``model``), the density-control statistics and the training-image order."""
        return {
            "model": self.model.gaussian_state(),
            "strategy_state": dict(self.model.strategy_state),
            "datamanager": self.datamanager.state_dict(),
        }

    def load_state_dict(self, state: dict[str, Any], step: int) -> None:
        """Restore :meth:`state_dict`'s content (any subset of its keys; ``model`` is required) at ``step``."""
        self.model.load_gauss_params(state["model"])
        if "strategy_state" in state:
            self.model.strategy_state = {
                k: (v.to(self.device) if isinstance(v, torch.Tensor) else v) for k, v in state["strategy_state"].items()
            }
        if "datamanager" in state:
            self.datamanager.load_state_dict(state["datamanager"])
        self.model.set_step(step)
