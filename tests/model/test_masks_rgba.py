"""Masks and RGBA ground truth reach every loss term and metric (issue 12, part 2).

Oracles: a second scene whose masked-out (or transparent) pixels hold random garbage must train bit-identically to
the clean one, while the same garbage without the mask must change training (so the comparison can fail); a render
equal to the RGBA ground truth composited over its own background has zero loss whatever that background is.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from kc_splatfacto.data.demo import DemoSceneSpec, ensure_demo_scene
from kc_splatfacto.data.spars3r import Spars3rDataParserConfig
from kc_splatfacto.engine.checkpoints import find_checkpoint, load_checkpoint
from kc_splatfacto.engine.metrics_log import read_metrics
from kc_splatfacto.engine.trainer import Trainer
from kc_splatfacto.study.runs import numbers_only
from tests.training_utils import TINY_HEIGHT, TINY_WIDTH, tiny_demo_config

STEPS = 16


def _hole(height: int, width: int) -> np.ndarray:
    """[H, W] bool: False in a rectangle (the excluded / transparent region) that is not block-aligned."""
    keep = np.ones((height, width), bool)
    keep[9:30, 13:41] = False
    return keep


def _scene(tmp_path: Path, name: str, *, garbage: bool, masks: bool, alpha: bool) -> Path:
    """The tiny demo scene as a SPARS3R folder, its images edited: garbage under the hole, a masks/ folder, or an
    alpha channel that is 0 in the hole (and 0.5 on its border row)."""
    src = ensure_demo_scene(DemoSceneSpec(width=TINY_WIDTH, height=TINY_HEIGHT))
    dst = tmp_path / name
    shutil.copytree(src, dst)
    rng = np.random.default_rng(5)
    for path in sorted((dst / "images").glob("*.png")):
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        keep = _hole(*image.shape[:2])
        if garbage:
            image[~keep] = rng.integers(0, 256, size=(int((~keep).sum()), 3), dtype=np.uint8)
        if alpha:
            a = np.where(keep, 255, 0).astype(np.uint8)
            a[8, 13:41] = 128
            image = np.concatenate([image, a[..., None]], axis=-1)
        assert cv2.imwrite(str(path), image)
        if masks:
            (dst / "masks").mkdir(exist_ok=True)
            assert cv2.imwrite(str(dst / "masks" / path.name), np.where(keep, 255, 0).astype(np.uint8))
    return dst


def _train(scene: Path, out: Path, *, masks: bool, background: str = "random") -> tuple[dict, list[dict]]:
    config = tiny_demo_config("kc-splatfacto", out, iterations=STEPS, background_color=background,
                              num_downscales=1, resolution_schedule=STEPS // 2 * 50)  # half the steps at 1/2 size
    config.pipeline.datamanager.dataparser = Spars3rDataParserConfig(
        data=scene, masks_path=Path("masks") if masks else None)
    config.logging.steps_per_log = 4
    run_dir = Trainer(config).train()
    checkpoint = load_checkpoint(find_checkpoint(run_dir / "nerfstudio_models"))
    records = numbers_only(read_metrics(run_dir / "metrics.jsonl"))  # without the clocks (TIMING_KEYS)
    for record in records:  # per-view metrics name their image file, which lies in this run's own scene copy
        if "per_image" in record:
            record["per_image"] = [{k: v for k, v in view.items() if k != "image"} for view in record["per_image"]]
    return checkpoint["model"], records


def _same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_garbage_in_a_masked_region_does_not_change_training(tmp_path):
    clean = _scene(tmp_path, "clean", garbage=False, masks=True, alpha=False)
    dirty = _scene(tmp_path, "dirty", garbage=True, masks=True, alpha=False)
    params_clean, log_clean = _train(clean, tmp_path / "runs-clean", masks=True)
    params_dirty, log_dirty = _train(dirty, tmp_path / "runs-dirty", masks=True)
    assert _same(params_clean, params_dirty)
    assert log_clean == log_dirty  # losses (wavelet/KC/CBC included), train PSNR, kurtosis, eval PSNR/SSIM
    assert any(r["kind"] == "eval" for r in log_clean) and any("kc_loss" in r for r in log_clean)
    # the control: the same garbage without its mask does change training
    params_unmasked, _ = _train(dirty, tmp_path / "runs-unmasked", masks=False)
    assert not _same(params_clean, params_unmasked)


@pytest.mark.parametrize("background", ["random", "white"])
def test_rgba_scene_ignores_the_colour_under_transparent_pixels(tmp_path, background):
    clean = _scene(tmp_path, "clean", garbage=False, masks=False, alpha=True)
    dirty = _scene(tmp_path, "dirty", garbage=True, masks=False, alpha=True)
    params_clean, log_clean = _train(clean, tmp_path / "runs-clean", masks=False, background=background)
    params_dirty, log_dirty = _train(dirty, tmp_path / "runs-dirty", masks=False, background=background)
    assert _same(params_clean, params_dirty)
    assert log_clean == log_dirty


@pytest.mark.parametrize("background", ["black", "white", "random"])
def test_a_render_equal_to_the_rgba_ground_truth_has_zero_loss_under_any_background(background):
    """The GT is composited over outputs["background"]: whatever the background, the render that shows the object
    over it is a perfect match (before, RGBA was composited over black at load: only a black background matched)."""
    from kc_splatfacto.losses.frequency import FrequencyLossConfig
    from kc_splatfacto.model.splatfacto import SplatfactoModelConfig

    torch.manual_seed(0)
    config = SplatfactoModelConfig(background_color=background, num_downscales=0, num_random=10, random_init=True,
                                   frequency=FrequencyLossConfig())
    model = config.setup().train()
    rgba = torch.rand(40, 48, 4)
    rgba[..., 3] = (rgba[..., 3] > 0.5).float() * torch.rand(40, 48)  # transparent, opaque and partial pixels
    rgba[:5, :, 3] = 0.0
    image = (rgba * 255).round().to(torch.uint8)
    straight = image.float() / 255
    bg = torch.rand(3) if background == "random" else model.background_color
    render = straight[..., :3] * straight[..., 3:] + bg * (1 - straight[..., 3:])
    outputs = {"rgb": render, "background": bg}
    losses = model.get_loss_dict(outputs, {"image": image, "image_idx": 0})
    for name, value in losses.items():
        assert abs(float(value)) < 1e-6, (name, float(value))
    old_gt = straight[..., :3] * straight[..., 3:]  # the old load-time compositing over black
    if background != "black":
        assert float((render - old_gt).abs().mean()) > 0.01  # what the old loss compared: far from zero


def test_both_splits_come_from_one_parse_of_the_model(monkeypatch, castle_p30):
    """The data manager asks for the train and the eval split; the COLMAP model (the slow part) is read once."""
    import kc_splatfacto.data.spars3r as spars3r
    from kc_splatfacto.data.detect import AutoDataParserConfig
    from kc_splatfacto.engine.datamanager import DataManagerConfig

    calls = []
    real = spars3r.read_colmap_model

    def counting(*args, **kwargs):
        calls.append(args)
        return real(*args, **kwargs)

    monkeypatch.setattr(spars3r, "read_colmap_model", counting)
    datamanager = DataManagerConfig(dataparser=AutoDataParserConfig(data=castle_p30, downscale_factor=4)).setup()
    assert len(calls) == 1
    assert len(datamanager.train_dataset) == 12 and len(datamanager.eval_dataset) == 12
    names = {Path(p).name for p in datamanager.train_dataset.image_filenames}
    assert not names & {Path(p).name for p in datamanager.eval_dataset.image_filenames}
