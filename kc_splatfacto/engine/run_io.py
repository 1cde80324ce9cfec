"""Loading a finished (or interrupted) run for evaluation, rendering and export: :func:`load_run`."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from kc_splatfacto.data.base import DataParserConfig
from kc_splatfacto.data.dataset import ImageDataset
from kc_splatfacto.data.detect import DEMO_NAME
from kc_splatfacto.engine.checkpoints import (
    CHECKPOINT_DIR,
    CheckpointMismatchError,
    check_checkpoint_fits,
    checkpoint_step,
    find_checkpoint,
    load_checkpoint,
)
from kc_splatfacto.engine.config import load_config
from kc_splatfacto.engine.config_file import check_lines_kept, check_method_name
from kc_splatfacto.engine.pipeline import Pipeline
from kc_splatfacto.engine.trainer import TrainerConfig
from kc_splatfacto.errors import UserError
from kc_splatfacto.model.splatfacto import SplatfactoModel


@dataclass
class LoadedRun:
    """A trained pipeline: its model and datasets.

    Attributes:
        config: the run's TrainerConfig (as saved in config.yml).
        pipeline: the Pipeline built as training builds it, with the checkpoint's state.
        model: the SplatfactoModel in eval mode, with the checkpoint's Gaussians.
        step: the checkpoint's step (optimization steps completed).
        run_dir: the run folder (holds config.yml, metrics.jsonl, nerfstudio_models/).
        train_dataset, test_dataset: ImageDatasets of the train and eval splits.
        checkpoint_path: the checkpoint file loaded.
    """

    config: TrainerConfig
    pipeline: Pipeline
    model: SplatfactoModel
    step: int
    run_dir: Path
    train_dataset: ImageDataset
    test_dataset: ImageDataset
    checkpoint_path: Path


def check_stored_scene(parser: DataParserConfig, config_path: Path) -> None:
    """A scene path stored relative (runs written before paths were stored absolute) that does not resolve from here
    is a :class:`UserError` saying so, rather than a "check --data" message about a flag kc-eval does not have.
    ``parser``: the stored dataparser config with the stored scene handed to it."""
    data = parser.data
    if str(data).strip() in ("", "."):  # a hand-edited config.yml that lost its scene: never the current folder
        raise UserError(
            f"{config_path} names no scene (its dataparser's 'data:' is {str(data)!r}): set 'data:' in that config.yml "
            "to the scene folder the run trained on"
        )
    if str(data) == DEMO_NAME or Path(data).exists():
        return
    if Path(data).is_absolute():
        raise UserError(
            f"the scene {data} that {config_path} names does not exist (moved or deleted?): put the scene back there, "
            "or set 'data:' in that config.yml to where it is now"
        )
    raise UserError(
        f"{config_path} stores the scene as the relative path '{data}', which does not exist from {Path.cwd()}: run "
        "from the folder kc-train was started in, or make 'data:' in that config.yml absolute"
    )


def load_run(config_path: Path | str, step: int | None = None, device: str | torch.device = "cpu") -> LoadedRun:
    """Rebuild the model of a run from its ``config.yml`` and a checkpoint (the newest when ``step`` is None)."""
    config_path = Path(config_path)
    if config_path.is_dir():
        config_path = config_path / "config.yml"
    config = load_config(config_path)
    run_dir = config_path.parent
    checkpoint_path = find_checkpoint(run_dir / CHECKPOINT_DIR, step)
    datamanager_config = config.pipeline.datamanager
    check_stored_scene(datamanager_config.dataparser, config_path)
    dataparser = datamanager_config.resolve_dataparser()  # recorded resolved: a copy with the stored scene, no detection
    pipeline = config.pipeline.setup(device=device, seed=config.machine.seed, dataparser=dataparser)  # as in training
    checkpoint = load_checkpoint(checkpoint_path, map_location=device)
    try:
        check_checkpoint_fits(checkpoint, config, checkpoint_path)
    except CheckpointMismatchError as exc:  # a config.yml that lost a line is not another run's
        check_lines_kept(config_path, config, exc.recorded, f"it does not fit the checkpoint {checkpoint_path}")
        check_method_name(config_path, config.method_name, exc.recorded.get("method_name"))
        raise
    pipeline.load_state_dict({"model": checkpoint["model"]}, step=int(checkpoint["step"]))
    model = pipeline.model
    model.eval()
    datamanager = pipeline.datamanager
    return LoadedRun(
        config=config,
        pipeline=pipeline,
        model=model,
        step=checkpoint_step(checkpoint_path),
        run_dir=run_dir,
        train_dataset=datamanager.train_dataset,
        test_dataset=datamanager.eval_dataset,
        checkpoint_path=checkpoint_path,
    )
