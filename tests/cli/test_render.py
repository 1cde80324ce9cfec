"""kc-render on a tiny demo run: side-by-side PNGs hold the render and the GT; the H.264 video decodes back to every
frame at the render's size; nerfstudio camera-path JSON gives the cameras nerfstudio's get_path_from_json gives."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
import torch

from kc_splatfacto.analysis.camera_path import CameraPathError, camera_path_dict, read_camera_path
from kc_splatfacto.cli import render as kc_render
from kc_splatfacto.engine.run_io import load_run
from tests._demo_runs import demo_run

NUM_FRAMES = 8


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """Rendered into the run folder's renders/ (the default) of a copy of the shared demo run."""
    import shutil

    source = demo_run(tmp_path_factory).parent
    run = tmp_path_factory.mktemp("render-run") / "run"
    shutil.copytree(source, run)
    config = run / "config.yml"
    argv = ["--load-config", str(config), "--num-frames", str(NUM_FRAMES), "--fps", "10", "--diagnostics"]
    assert kc_render.entrypoint(argv) == 0
    return config, run / "renders"


def _uint8(rgb: torch.Tensor) -> np.ndarray:
    return (rgb.clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)


def decode(path):
    """Frames of ``path`` as float RGB [H,W,3], and its codec, decoded by OpenCV's own FFmpeg (an independent decoder
    from the ffmpeg executable that wrote it)."""
    capture = cv2.VideoCapture(str(path))
    assert capture.isOpened()
    fourcc = int(capture.get(cv2.CAP_PROP_FOURCC))
    codec = "".join(chr((fourcc >> 8 * i) & 0xFF) for i in range(4))
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(frame[..., ::-1].astype(np.float64) / 255.0)
    capture.release()
    return frames, codec


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


def test_h264_video_decodes_to_every_frame_of_the_path(rendered):
    config, out = rendered
    loaded = load_run(config)
    frames, codec = decode(out / "interpolate.mp4")
    assert codec.lower() in ("avc1", "h264"), codec
    assert len(frames) == NUM_FRAMES
    h, w = loaded.train_dataset.image_float(0).shape[:2]
    assert frames[0].shape == (h + h % 2, w + w % 2, 3)
    # The path starts at the first training camera: frame 0 is (up to the codec's loss) that camera's render.
    with torch.no_grad():
        first = loaded.model.get_outputs(loaded.train_dataset.cameras[0])["rgb"].numpy()
    mse = np.mean((frames[0][:h, :w] - first) ** 2)
    assert -10 * np.log10(mse) > 25.0
    assert np.mean((frames[0] - frames[NUM_FRAMES // 2]) ** 2) > 0  # the camera moves


def test_built_in_path_is_written_as_a_camera_path_that_renders_the_same(rendered, tmp_path):
    config, out = rendered
    path = read_camera_path(out / "interpolate_camera_path.json")
    assert len(path.cameras) == NUM_FRAMES and path.fps == 10
    loaded = load_run(config)
    keys = loaded.train_dataset.cameras
    # frame 0 is the first training view: same pose (the JSON keeps poses exactly, in float32 here)
    torch.testing.assert_close(path.cameras.viewmats[0], keys.viewmats[0], atol=1e-5, rtol=0)
    argv = ["--load-config", str(config), "--output-dir", str(tmp_path), "--camera-path-filename",
            str(out / "interpolate_camera_path.json"), "--codec", "mp4v"]
    assert kc_render.entrypoint(argv) == 0
    frames, codec = decode(tmp_path / "interpolate_camera_path.mp4")
    assert codec in ("mp4v", "FMP4") and len(frames) == NUM_FRAMES  # OpenCV reads mp4v as FMP4


def test_diagnostics_pngs(rendered):
    _, out = rendered
    for name in ("view_000_wavelets.png", "kurtosis_history.png"):
        image = cv2.imread(str(out / "diagnostics" / name), cv2.IMREAD_COLOR)
        assert image is not None and image.std() > 0, name


def test_write_video_refuses_empty(tmp_path):
    with pytest.raises(ValueError, match="no frames"):
        kc_render.write_video([], tmp_path / "v.mp4", 10)


def test_odd_sized_frames_and_mp4v_fallback(tmp_path, monkeypatch):
    frames = [np.full((21, 33, 3), 40 * i, dtype=np.uint8) for i in range(5)]
    result = kc_render.write_video(frames, tmp_path / "odd.mp4", 12)
    assert (result.codec, result.frames, result.size, result.fallback_reason) == ("h264", 5, (34, 22), None)
    monkeypatch.setattr(kc_render, "h264_unavailable", lambda: "imageio-ffmpeg is not installed")
    result = kc_render.write_video(frames, tmp_path / "fallback.mp4", 12)
    assert result.codec == "mp4v" and result.fallback_reason == "imageio-ffmpeg is not installed"
    decoded, codec = decode(tmp_path / "fallback.mp4")
    assert codec in ("mp4v", "FMP4") and len(decoded) == 5 and decoded[0].shape == (22, 34, 3)


# ------------------------------------------------------------------------------ nerfstudio's camera-path JSON


def nerfstudio_camera(c2w_gl: np.ndarray, fov: float, width: int, height: int):
    """What nerfstudio's get_path_from_json builds for one camera: c2w (OpenGL axes), fx = fy from the vertical fov
    as three.js defines it, principal point at the image centre."""
    focal = (height / 2.0) / np.tan(np.radians(fov) / 2.0)
    return c2w_gl, focal, width / 2.0, height / 2.0


def test_camera_path_json_gives_nerfstudio_cameras(tmp_path):
    rng = np.random.default_rng(0)
    from scipy.spatial.transform import Rotation

    width, height = 320, 180
    entries, truth = [], []
    for i in range(3):
        c2w = np.eye(4)
        c2w[:3, :3] = Rotation.random(random_state=i).as_matrix()
        c2w[:3, 3] = rng.normal(size=3)
        fov = 40.0 + 10 * i
        entries.append({"camera_to_world": c2w.reshape(-1).tolist(), "fov": fov, "aspect": width / height})
        truth.append(nerfstudio_camera(c2w, fov, width, height))
    file = tmp_path / "path.json"
    file.write_text(json.dumps({"camera_type": "perspective", "render_width": width, "render_height": height,
                                "seconds": 1.5, "camera_path": entries}))
    path = read_camera_path(file)
    assert path.fps == pytest.approx(2.0)  # nerfstudio: len(camera_path) / seconds
    assert path.cameras.widths.tolist() == [width] * 3 and path.cameras.heights.tolist() == [height] * 3
    for i, (c2w_gl, focal, cx, cy) in enumerate(truth):
        K = path.cameras.Ks[i].double().numpy()
        np.testing.assert_allclose(K, [[focal, 0, cx], [0, focal, cy], [0, 0, 1]], rtol=1e-6)
        # a point 5 units in front of the camera, 1 up (OpenGL: -z forward, +y up): above the image centre by
        # focal / 5 pixels, and the top edge of the image is fov / 2 above the axis
        viewmat = path.cameras.viewmats[i].double().numpy()
        for local, row in (([0.0, 1.0, -5.0], cy - focal / 5.0),
                           ([0.0, 5.0 * np.tan(np.radians(40.0 + 10 * i) / 2), -5.0], 0.0)):
            world = c2w_gl @ np.array([*local, 1.0])
            cam = viewmat @ world
            assert cam[2] > 0  # in front, OpenCV depth
            pixel = K @ (cam[:3] / cam[2])
            assert pixel[0] == pytest.approx(cx, abs=1e-3) and pixel[1] == pytest.approx(row, abs=1e-3)
    again = tmp_path / "again.json"
    again.write_text(json.dumps(camera_path_dict(path.cameras, 2.0)))
    back = read_camera_path(again)
    torch.testing.assert_close(back.cameras.viewmats, path.cameras.viewmats, atol=1e-5, rtol=0)
    torch.testing.assert_close(back.cameras.Ks, path.cameras.Ks, atol=1e-3, rtol=1e-6)


@pytest.mark.parametrize("content, message", [
    ("{", "not readable JSON"),
    ('{"render_width": 10, "render_height": 10}', "has no 'camera_path'"),
    ('{"render_width": 10, "render_height": 10, "camera_path": [{"fov": 50}]}', "has no 'camera_to_world'"),
    ('{"render_width": 10, "render_height": 10, "camera_path": [{"camera_to_world": [1, 2], "fov": 50}]}',
     "must be 16 numbers"),
    ('{"render_width": 10, "render_height": 10, "camera_path": [{"camera_to_world": '
     '[2,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1], "fov": 50}]}', "not a rigid pose"),
    ('{"render_width": 10, "render_height": 10, "camera_path": [{"camera_to_world": '
     '[1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1], "fov": 190}]}', "below 180"),
    ('{"camera_type": "fisheye", "render_width": 10, "render_height": 10, "camera_path": []}', "only 'perspective'"),
])
def test_bad_camera_path_json_is_named(tmp_path, content, message):
    file = tmp_path / "bad.json"
    file.write_text(content)
    with pytest.raises(CameraPathError, match=message):
        read_camera_path(file)


def _one_camera_path(tmp_path, fov, height: int = 48):
    file = tmp_path / "path.json"
    file.write_text(json.dumps({"render_width": height * 4 // 3, "render_height": height, "camera_path": [
        {"camera_to_world": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1], "fov": fov}]}))
    return file


@pytest.mark.parametrize("fov", [5e-324, 1e-300, 1e-9])
def test_a_field_of_view_too_narrow_to_render_is_named(tmp_path, fov):
    """5e-324 degrees divides by zero, 1e-300 gives an infinite float32 focal length (the rasterizer's traceback),
    1e-9 a pixel of 4e-13 rad, far below what float32 resolves: each is refused naming the camera and the smallest
    fov that renders 48 pixels high (48 x float32's epsilon, in degrees)."""
    with pytest.raises(CameraPathError, match=r"camera_path\[0\]\.fov is .* degrees, too narrow to render 48 pixels "
                                              r"high .*use a fov of at least 0\.00033 degrees"):
        read_camera_path(_one_camera_path(tmp_path, fov))


def test_a_telephoto_field_of_view_renders(tmp_path):
    """Half a degree over 4000 pixels (a 2000 mm lens on a full-frame sensor is 0.7 degrees) is read as given."""
    cameras = read_camera_path(_one_camera_path(tmp_path, 0.5, height=4000)).cameras
    assert float(cameras.Ks[0, 1, 1]) == pytest.approx(2000 / math.tan(math.radians(0.25)), rel=1e-6)


def test_bad_camera_path_is_one_line_exit_2(rendered, tmp_path, capsys):
    config, _ = rendered
    file = tmp_path / "bad.json"
    file.write_text("{")
    code = kc_render.entrypoint(["--load-config", str(config), "--camera-path-filename", str(file),
                                 "--output-dir", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.count("\n") == 0 and err.startswith("kc-render: error: camera path") and "bad.json" in err
    assert kc_render.entrypoint(["--load-config", str(config), "--pth", "spiral"]) == 2
    assert "did you mean --path" in capsys.readouterr().err


def test_spiral_circles_the_training_views_looking_at_the_scene(rendered, tmp_path):
    from kc_splatfacto.analysis.camera_path import spiral_camera_path

    config, _ = rendered
    loaded = load_run(config)
    keys = loaded.train_dataset.cameras
    means = loaded.model.means.detach().double().numpy()
    path = spiral_camera_path(keys, means, 16)
    centres = path.centers().double().numpy()
    key_centres = keys.centers().double().numpy()
    mean = key_centres.mean(axis=0)
    assert np.linalg.norm(centres - mean, axis=1).max() <= np.linalg.norm(key_centres - mean, axis=1).max() * 1.5
    # every frame sees the Gaussians' median point near the image centre
    focus_world = np.median(means, axis=0)
    viewmats = path.viewmats.double().numpy()
    for viewmat in viewmats:
        cam = viewmat[:3, :3] @ focus_world + viewmat[:3, 3]
        assert cam[2] > 0
    assert kc_render.entrypoint(["--load-config", str(config), "--output-dir", str(tmp_path), "--path", "spiral",
                                 "--num-frames", "6"]) == 0
    frames, _ = decode(tmp_path / "spiral.mp4")
    assert len(frames) == 6
