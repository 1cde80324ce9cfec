"""The viewer (kc_splatfacto/viewer/viewer.py) in a real browser, and its guarantee that training is unchanged."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest
import torch

from kc_splatfacto.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from kc_splatfacto.engine.checkpoints import CHECKPOINT_DIR
from kc_splatfacto.engine.trainer import Trainer
from kc_splatfacto.errors import UserError
from tests.training_utils import tiny_demo_config
from tests.viewer.browser import correlation, headless_chromium, screenshot, wait_for

pytest.importorskip("viser", reason="the viewer needs viser: pip install 'kc-splatfacto[viewer]'")

#: the screenshot region compared: the canvas below the notification viser shows about software WebGL and left
#: of the control panel floating on the right
TOP_FRACTION, LEFT_FRACTION = 0.4, 0.5
MATCH_CORRELATION = 0.8


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    config = tiny_demo_config("splatfacto", tmp_path_factory.mktemp("viewer-run"), iterations=80, steps_scale=0.05)
    config.pipeline.datamanager.dataparser.width, config.pipeline.datamanager.dataparser.height = 160, 120
    return Trainer(config).train() / "config.yml"


def _reference(model, camera, width: int, height: int) -> np.ndarray:
    """kc-render's render of ``camera``'s pose with its vertical field of view at ``width`` x ``height`` (the K
    built here, independently of the viewer's conversion)."""
    from kc_splatfacto.cli.eval import render_view
    from kc_splatfacto.data.outputs import Cameras

    fy = float(camera.Ks[0, 1, 1]) * height / float(camera.heights[0])
    K = torch.tensor([[[fy, 0, width / 2], [0, fy, height / 2], [0, 0, 1]]], dtype=torch.float32)
    cameras = Cameras(camera.viewmats.clone(), K, torch.tensor([width]), torch.tensor([height]))
    return render_view(model, cameras, 0)[0].numpy().astype(np.float64)


def _canvas(viewer, shot: np.ndarray) -> tuple[np.ndarray, int, int]:
    client = next(iter(viewer.server.get_clients().values()))
    width, height = client.camera.image_width, client.camera.image_height
    return shot[:height, :width], width, height


def _region(image: np.ndarray) -> np.ndarray:
    return image[int(TOP_FRACTION * image.shape[0]):, :int(LEFT_FRACTION * image.shape[1])].mean(axis=-1)


def test_kc_viewer_shows_the_scene_at_the_browsers_camera(finished_run):
    """Headless chromium opens kc-viewer's page; once a frame arrived (and the training-camera frustums are turned
    off in the panel), the screenshot's scene region correlates with kc-render's image of the camera the page starts at (the first test view), and clearly less with the
    image of another view (the screenshot shows *that* camera, not just the scene)."""
    from kc_splatfacto.cli.viewer import open_viewer

    driver = headless_chromium()
    viewer = open_viewer(finished_run, port=0)
    stop = threading.Event()
    thread = threading.Thread(target=viewer.serve_forever, args=(stop,), daemon=True)
    thread.start()
    try:
        driver.get(viewer.url)
        assert wait_for(lambda: viewer.frames_sent > 0, 120), "no frame was rendered for the browser within 120 s"
        viewer._frustum_box.value = False  # the panel's "Training cameras" box: a thumbnail would cover the view
        assert wait_for(lambda: not any(f.visible for f in viewer._frustums), 10)
        model, start_camera = viewer.model, viewer.initial_camera
        other = viewer.train_cameras[len(viewer.train_cameras) // 2]
        match = {}

        def matches() -> bool:
            canvas, width, height = _canvas(viewer, screenshot(driver))
            match["same"] = correlation(_region(canvas), _region(_reference(model, start_camera, width, height)))
            match["other"] = correlation(_region(canvas), _region(_reference(model, other, width, height)))
            return match["same"] > MATCH_CORRELATION

        assert wait_for(matches, 60, poll=1.0), f"screenshot vs kc-render: {match}"
        assert match["same"] > match["other"] + 0.2, match
    finally:
        driver.quit()
        stop.set()
        thread.join(10)
        viewer.stop()


def test_kc_viewer_camera_path_export_is_read_back(finished_run):
    """The camera-path editor's export: nerfstudio's JSON, its first camera the first keyframe's pose."""
    from kc_splatfacto.cli.viewer import open_viewer
    from kc_splatfacto.viewer.cameras import pose_of

    viewer = open_viewer(finished_run, port=0)
    try:
        with pytest.raises(ValueError, match="no keyframes"):
            viewer.export_camera_path()

        class Pose:  # what a browser's camera handle exposes
            def __init__(self, camera):
                wxyz, position, fov = pose_of(camera)
                self.wxyz, self.position, self.fov = wxyz[0], position[0], float(fov[0])

        for i in (0, 2, 4):
            viewer.add_keyframe(Pose(viewer.train_cameras[i]))
        path = viewer.export_camera_path("tour")
        data = json.loads(path.read_text())
        assert path == viewer.run_dir / "camera_paths" / "tour.json"
        assert len(data["camera_path"]) == round(data["fps"] * data["seconds"]) and len(data["keyframes"]) == 3
        first = np.array(data["camera_path"][0]["camera_to_world"]).reshape(4, 4) @ np.diag([1, -1, -1, 1])
        np.testing.assert_allclose(first, torch.linalg.inv(viewer.train_cameras.viewmats[0].double()).numpy(), atol=1e-5)
        with pytest.raises(ValueError, match="not a file name"):
            viewer.export_camera_path("../escape")
    finally:
        viewer.stop()


def test_live_viewer_streams_training_to_the_browser(tmp_path):
    """kc-train's viewer attached to a run with a browser connected: frames arrive while it trains, the
    statistics panel follows the steps, pause holds the step count, and the render budget is kept."""
    from kc_splatfacto.cli.train import attach_viewer

    config = tiny_demo_config("splatfacto", tmp_path, iterations=200, steps_scale=0.05)
    config.viewer.enabled, config.viewer.port = True, 0
    trainer = config.setup()
    viewer = attach_viewer(trainer)
    driver = headless_chromium()
    paused_at, step_times = {}, {}

    def pause_once(step: int) -> None:
        step_times[step] = time.perf_counter()
        if step == 100 and not paused_at:
            viewer.toggle_pause()
            paused_at["step"] = step
            threading.Timer(2.0, viewer.toggle_pause).start()  # what a second click does

    trainer.add_callbacks([TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], pause_once)])
    try:
        driver.get(viewer.url)
        assert wait_for(lambda: len(viewer.server.get_clients()) > 0, 60)
        start = time.perf_counter()
        trainer.train()
        wall = time.perf_counter() - start
        assert viewer.frames_sent >= 2, viewer.frames_sent
        assert viewer.step == 200 and "**step**" in viewer._stats.content and "Gaussians" in viewer._stats.content
        assert step_times[101] - step_times[100] >= 1.9  # the pause held the step after the click
        # renders are charged to the budget: at most render_share of the time, plus the one frame that crossed it
        assert viewer.render_s <= config.viewer.render_share * wall + 0.5, (viewer.render_s, wall)
        assert paused_at == {"step": 100}
    finally:
        driver.quit()
        viewer.stop()


def test_a_run_with_viewer_renders_trains_bit_identically(tmp_path):
    """The viewer's render between every two steps leaves the training untouched: same Gaussians, same optimizer
    state as a run without it."""
    from kc_splatfacto.viewer.viewer import render_rgb

    def run(folder, with_renders: bool):
        config = tiny_demo_config("kc-splatfacto", folder, iterations=40)
        trainer = config.setup()
        if with_renders:
            trainer.setup()
            camera = trainer.datamanager.eval_dataset.cameras[0]
            trainer.add_callbacks([TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION],
                                                    lambda step: render_rgb(trainer.model, camera))])
        run_dir = trainer.train()
        return torch.load(next((run_dir / CHECKPOINT_DIR).glob("*.ckpt")), weights_only=False)

    plain, watched = run(tmp_path / "a", False), run(tmp_path / "b", True)
    for name, value in plain["model"].items():
        assert torch.equal(value, watched["model"][name]), name
    assert plain["rng"]["torch"].equal(watched["rng"]["torch"])


def test_missing_viser_is_one_line_with_the_install_command(monkeypatch):
    import sys

    from kc_splatfacto.viewer.viewer import import_viser

    monkeypatch.setitem(sys.modules, "viser", None)
    with pytest.raises(UserError, match=r"pip install 'kc-splatfacto\[viewer\]'"):
        import_viser()


def test_kc_viewer_missing_config_is_one_line(tmp_path, capsys):
    from kc_splatfacto.cli.viewer import entrypoint

    assert entrypoint(["--load-config", str(tmp_path / "nope" / "config.yml")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("kc-viewer: error:") and "nope" in err
