"""The pipeline (nerfstudio's ``VanillaPipeline``): owns the data manager and the model.

Through the pipeline the trainer takes a step's losses (:meth:`Pipeline.get_train_loss_dict`: ``datamanager.next_train()``
gives a batch (camera, uint8 image, index) -> ``model.get_outputs(camera)`` renders it -> ``model.get_loss_dict(outputs,
batch)`` compares render and ground truth), its logged metrics, the evaluation of a split and the checkpointed state
(Gaussians, density-control statistics, image order). Beside it the trainer uses ``pipeline.model`` directly for what
is training state rather than the scene's: the parameters its optimizers step, density control after the step
(``step_post_backward``) and the removal of non-finite Gaussians; and ``pipeline.datamanager`` for the checks before
the first step and ``dataparser_transforms.json``. ``load_run`` (kc-eval, kc-render, kc-export, kc-viewer) builds the
same pipeline and uses its model and datasets.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

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

    def get_train_loss_dict(
        self, step: int, lap: Callable[[str], None] | None = None
    ) -> tuple[dict[str, Any], dict[str, torch.Tensor], dict[str, Any]]:
        """Render the next training view and its losses.

        Args:
            step: 0-based index of the optimization step being taken (every schedule reads it).
            lap: called with "render" after rendering and "losses" after the losses (phase timing).
        Returns:
            (outputs, loss_dict, batch). A non-finite render gives non-finite losses, not an error: the trainer checks
            the loss and the gradients once after backward (one host synchronisation per step, not one per check).
        """
        self.model.step = step
        batch = self.datamanager.next_train()
        outputs = self.model.get_outputs(batch["camera"])
        if lap is not None:
            lap("render")
        loss_dict = self.model.get_loss_dict(outputs, batch)
        if lap is not None:
            lap("losses")
        return outputs, loss_dict, batch

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
            "model": {k: v.detach().clone() for k, v in self.model.gauss_params.items()},
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
        self.model.step = int(step)
