"""The pipeline (nerfstudio's ``VanillaPipeline``): the scene's data manager and its model.

The trainer draws each training batch from the data manager (``pipeline.datamanager.next_train()``) and hands it to
the training state (:class:`~kc_splatfacto.engine.training_state.TrainingState`), which owns the optimizers, density
control and the step. Besides: the logged training metrics, the evaluation of a split and the checkpointed part of
the scene (Gaussians, image order). ``load_run`` (kc-eval, kc-render, kc-export, kc-viewer) builds the same pipeline
and uses its model and datasets.
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
              dataparser: DataParserConfig | None = None, datamanager: DataManager | None = None) -> Pipeline:
        return Pipeline(self, device=device, seed=seed, dataparser=dataparser, datamanager=datamanager)


class Pipeline:
    """The scene's data and model.

    Args:
        config: the pipeline config (left unchanged; the resolved dataparser is ``datamanager.dataparser_config``).
        device: where the model lives.
        seed: seed of the training-image order.
        dataparser: the run's resolved dataparser config (see :meth:`DataManagerConfig.setup`).
        datamanager: the data manager already built from ``config.datamanager`` (the trainer's, which the scene plan
            measured before the model was configured), or None to build it here.
    """

    def __init__(self, config: PipelineConfig, *, device: torch.device | str = "cpu", seed: int = 42,
                 dataparser: DataParserConfig | None = None, datamanager: DataManager | None = None):
        self.config = config
        self.datamanager: DataManager = (
            datamanager if datamanager is not None else config.datamanager.setup(seed=seed, dataparser=dataparser))
        train_outputs = self.datamanager.train_outputs
        self.model: SplatfactoModel = config.model.setup(
            scene_scale=float(train_outputs.scene_scale),
            num_train_data=len(self.datamanager.train_dataset),
            seed_points=self.datamanager.seed_points(),
        ).to(device)

    @property
    def device(self) -> torch.device:
        return self.model.device

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
        """The Gaussians (``model``) and the training-image order (``datamanager``)."""
        return {"model": self.model.gaussian_state(), "datamanager": self.datamanager.state_dict()}

    def load_state_dict(self, state: dict[str, Any], step: int) -> None:
        """Restore :meth:`state_dict`'s content (``datamanager`` optional; other keys, the training state's, are
        left to it) at ``step``."""
        self.model.load_gauss_params(state["model"])
        if "datamanager" in state:
            self.datamanager.load_state_dict(state["datamanager"])
        self.model.set_step(step)
