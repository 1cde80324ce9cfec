"""kc-render on a tiny demo run: side-by-side PNGs hold the render and the GT, the mp4 opens with every frame."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch

from kc_splatfacto.cli import render as kc_render
from kc_splatfacto.engine.run_io import load_run
from tests._demo_runs import demo_run

NUM_FRAMES = 8


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    config = demo_run(tmp_path_factory)
    out = tmp_path_factory.mktemp("render")
    argv = ["--load-config", str(config), "--output-dir", str(out), "--num-frames", str(NUM_FRAMES), "--fps", "10",
            "--diagnostics"]
    assert kc_render.entrypoint(argv) == 0
    return config, out


def _uint8(rgb: torch.Tensor) -> np.ndarray:
    return (rgb.clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)


def test_side_by_side_pngs(rendered):
    config, out = rendered
    loaded = load_run(config)
    dataset = loaded.test_dataset
    pngs = sorted((out / "views").glob("*.png"))
    assert len(pngs) == len(dataset) > 0
    for i, png in enumerate(pngs):
        image = cv2.imread(str(png), cv2.IMREAD_COLOR)[..., ::-1]  # BGR -> RGB
        gt = dataset.image_float(i)
        h, w = gt.shape[:2]
        assert image.shape == (h, 2 * w, 3)
        with torch.no_grad():
            pred = loaded.model.get_outputs(dataset.cameras[i])["rgb"]
        assert np.abs(image[:, :w].astype(int) - _uint8(pred).astype(int)).max() <= 1
        assert np.abs(image[:, w:].astype(int) - _uint8(gt).astype(int)).max() <= 1


def test_video_opens_with_every_frame(rendered):
    config, out = rendered
    loaded = load_run(config)
    capture = cv2.VideoCapture(str(out / "path.mp4"))
    assert capture.isOpened()
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(frame[..., ::-1].astype(np.float64) / 255.0)
    capture.release()
    assert len(frames) == NUM_FRAMES
    h, w = loaded.test_dataset.image_float(0).shape[:2]
    assert frames[0].shape == (h, w, 3)
    # The path starts at the first test camera: frame 0 is (up to the codec's loss) that camera's render.
    with torch.no_grad():
        first = loaded.model.get_outputs(loaded.test_dataset.cameras[0])["rgb"].numpy()
    mse = np.mean((frames[0] - first) ** 2)
    assert -10 * np.log10(mse) > 25.0
    assert np.mean((frames[0] - frames[NUM_FRAMES // 2]) ** 2) > 0  # the camera moves


def test_diagnostics_pngs(rendered):
    _, out = rendered
    for name in ("view_000_wavelets.png", "kurtosis_history.png"):
        image = cv2.imread(str(out / "diagnostics" / name), cv2.IMREAD_COLOR)
        assert image is not None and image.std() > 0, name


def test_write_video_refuses_empty(tmp_path):
    with pytest.raises(ValueError, match="no frames"):
        kc_render.write_video([], tmp_path / "v.mp4", 10)
