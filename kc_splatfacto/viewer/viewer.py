"""The scene in the browser through viser (nerfstudio's viewer library): ``kc-train --viewer`` and ``kc-viewer``.

Each connected browser gets the project's own render of its camera as the scene's background image, rendered by the
rasterizer the model trains with, at most ``max_render_pixels`` (the browser scales it to the canvas). Rendering
happens in the thread that owns the model (the training loop between steps, or ``kc-viewer``'s serve loop), never
beside a training step, and as the evaluation renders (eval mode, no gradients): a run trains bit-identically with
a viewer attached. While training, renders take at most ``render_share`` of the wall-clock time (nerfstudio's
'train util'), and the scene is re-rendered at most every ``REFRESH_S`` while the camera stands still.

The panel: training statistics (step, loss, Gaussians, steps/s, the last evaluation) and pause/resume while
training; the training views as camera frustums; for a finished run, the Gaussians as WebGL splats in the browser
(what the PLY export holds); a camera-path editor whose JSON (nerfstudio's format) ``kc-render`` reads.
"""

from __future__ import annotations

import json
import math
import socket
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from kc_splatfacto.atomic import atomic_write_text
from kc_splatfacto.data.outputs import Cameras
from kc_splatfacto.engine.base_config import ViewerConfig
from kc_splatfacto.engine.callbacks import RecordSink, TrainingCallback, TrainingCallbackLocation
from kc_splatfacto.errors import UserError, import_optional
from kc_splatfacto.viewer.cameras import (
    FRUSTUM_FALLBACK_SCALE,
    camera_from_pose,
    camera_path_json,
    frustum_scale,
    pinhole_K,
    pose_of,
    render_size,
    splat_arrays,
    world_up,
)

INSTALL_HINT = "pip install 'kc-splatfacto[viewer]'"
#: seconds between re-renders of a still camera while the scene trains
REFRESH_S = 1.0
#: seconds between updates of the statistics panel
STATS_EVERY_S = 0.5
#: JPEG quality of the frames sent to the browser
JPEG_QUALITY = 85
#: training views shown as frustums with a thumbnail (beyond this, frustums only); thumbnails' longer side
MAX_THUMBNAILS, THUMBNAIL_SIZE = 100, 64
CAMERA_PATH_DIR = "camera_paths"


SERVER_START_TIMEOUT_S = 30.0
"""how long the viewer waits for viser's server to listen (it binds in a thread of its own, and when that thread dies,
on a bad port or host, viser's constructor waits for ever)"""


def start_server(viser, host: str, port: int, timeout: float = SERVER_START_TIMEOUT_S):
    """A ``viser.ViserServer`` listening on ``host``:``port`` (the next free port when taken), or a one-line
    :class:`UserError` within ``timeout`` seconds: a port outside 0-65535, a host this machine cannot bind, a server
    that does not come up."""
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
        raise UserError(f"the viewer's port {port!r} is not a port number (0-65535; 0 picks a free one): pass another "
                        "--port / --viewer.port")
    try:  # viser takes a host it cannot bind for a taken port and tries the next ones: ask the system first
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as probe:
            probe.bind((host, 0))
    except OSError as exc:
        raise UserError(f"the viewer cannot listen on host {host!r} ({exc.strerror or exc}): pass an address of this "
                        "machine with --host / --viewer.host (127.0.0.1, or 0.0.0.0 for every interface)") from exc
    built: dict[str, Any] = {}

    def build() -> None:
        try:
            built["server"] = viser.ViserServer(host=host, port=port, verbose=False)
        except Exception as exc:  # noqa: BLE001  (reported below as the user's bad host or port)
            built["error"] = exc

    def keep_thread_error(args) -> None:  # viser's serving thread dying on bind: its error, not its traceback
        built.setdefault("error", args.exc_value)

    previous_hook, threading.excepthook = threading.excepthook, keep_thread_error
    try:
        thread = threading.Thread(target=build, name="viser-start", daemon=True)
        thread.start()
        deadline = time.monotonic() + timeout
        while thread.is_alive() and "error" not in built and time.monotonic() < deadline:
            thread.join(0.1)
    finally:
        threading.excepthook = previous_hook
    if "server" in built:
        return built["server"]
    error = built.get("error")
    why = f"{type(error).__name__}: {error}" if error is not None else f"no answer within {timeout:.0f} s"
    raise UserError(f"the viewer could not serve on {host}:{port} ({why}): check --host/--port "
                    "(--viewer.host/--viewer.port in kc-train)")


def import_viser():
    return import_optional("viser", "viser", "the viewer", INSTALL_HINT)


def render_rgb(model, camera: Cameras) -> np.ndarray:
    """[H, W, 3] uint8 render of one camera, as the evaluation renders (eval mode, no gradients; mode restored)."""
    was_training = model.training
    model.eval()
    try:
        with torch.no_grad():
            rgb = model.get_outputs(camera.to(model.device))["rgb"]
    finally:
        model.train(was_training)
    return (rgb.clamp(0, 1) * 255.0 + 0.5).to(torch.uint8).cpu().numpy()


def _thumbnail(image: torch.Tensor) -> np.ndarray:
    """[h, w, 3] uint8, longer side ``THUMBNAIL_SIZE``, of an [H, W, C] uint8 image."""
    height, width = image.shape[:2]
    step = max(1, math.ceil(max(height, width) / THUMBNAIL_SIZE))
    return np.ascontiguousarray(image[::step, ::step, :3].cpu().numpy())


class Viewer(RecordSink):
    """A viser server showing ``model``.

    Args:
        config: host, port, render budget.
        model: the SplatfactoModel (trained or training).
        train_dataset: its training views (frustums, the initial camera when ``initial_camera`` is None).
        run_dir: the run folder (camera paths are written into ``run_dir/camera_paths``).
        training: a live run (pause button, statistics, render budget) rather than a finished one (browser splats).
        initial_camera: the camera a new browser starts at (default: the first training view).
    """

    def __init__(self, config: ViewerConfig, model, train_dataset, run_dir: Path, *, training: bool,
                 initial_camera: Cameras | None = None, max_render_pixels: int | None = None):
        viser = import_viser()
        self.config, self.model, self.run_dir, self.training = config, model, Path(run_dir), training
        self.max_render_pixels = max_render_pixels or config.max_render_pixels
        self.train_cameras = train_dataset.cameras if train_dataset is not None else None
        if initial_camera is None and self.train_cameras is not None and len(self.train_cameras):
            initial_camera = self.train_cameras[0]
        self.initial_camera = initial_camera
        self.server = start_server(viser, config.host, config.port)
        self.url = f"http://{config.host}:{self.server.get_port()}"
        self._lock = threading.Lock()
        self._dirty: set[int] = set()
        self._last_frame: dict[int, float] = {}
        self.frames_sent = 0
        self.render_s = 0.0
        self.paused = False
        self.step = 0
        self._t0: float | None = None  # the render budget's clock: from the first training step on
        self._stats_at = (0.0, 0)  # (time, step) of the last statistics update
        self._last_eval: dict[str, Any] | None = None
        self._last_losses: dict[str, float] = {}
        self.keyframes: list[Cameras] = []
        self._splats = None
        self._build_panel()
        self._add_training_frustums(train_dataset)
        self.server.on_client_connect(self._on_connect)

    # ------------------------------------------------------------------------------------------------ the panel
    def _build_panel(self) -> None:
        gui = self.server.gui
        gui.configure_theme(show_logo=False, show_share_button=False)
        self._stats = gui.add_markdown("starting" if self.training else
                                       f"**run** `{self.run_dir}`  \n**Gaussians** {self.model.num_points:,}")
        if self.training:
            self._pause = gui.add_button("Pause training")
            self._pause.on_click(lambda _: self.toggle_pause())
        else:
            self._splat_box = gui.add_checkbox("Splats in the browser (WebGL)", initial_value=False)
            self._splat_box.on_update(lambda _: self._show_splats(self._splat_box.value))
        self._frustum_box = gui.add_checkbox("Training cameras", initial_value=True)
        self._frustum_box.on_update(lambda _: self._set_frustums_visible(self._frustum_box.value))
        width, height = self._path_size()
        with gui.add_folder("Camera path"):
            add = gui.add_button("Add keyframe (this view)")
            add.on_click(lambda event: self.add_keyframe(event.client.camera))
            clear = gui.add_button("Clear keyframes")
            clear.on_click(lambda _: self.clear_keyframes())
            self._path_width = gui.add_number("Width", initial_value=width, min=16, step=1)
            self._path_height = gui.add_number("Height", initial_value=height, min=16, step=1)
            self._path_fps = gui.add_number("FPS", initial_value=24.0, min=1.0)
            self._path_seconds = gui.add_number("Seconds", initial_value=4.0, min=0.1)
            self._path_loop = gui.add_checkbox("Loop", initial_value=False)
            self._path_name = gui.add_text("File name", initial_value="camera_path")
            export = gui.add_button("Export camera path")
            export.on_click(lambda event: self._export_clicked(event.client))
            self._path_status = gui.add_markdown("no keyframes")

    def _path_size(self) -> tuple[int, int]:
        if self.train_cameras is not None and len(self.train_cameras):
            return int(self.train_cameras.widths[0]), int(self.train_cameras.heights[0])
        return 640, 480

    def _add_training_frustums(self, dataset) -> None:
        self._frustums = []
        self._frustum_scale = FRUSTUM_FALLBACK_SCALE
        if self.train_cameras is None or len(self.train_cameras) == 0:
            return
        wxyz, position, fov = pose_of(self.train_cameras)
        scale = self._frustum_scale = frustum_scale(position)
        thumbnails = len(self.train_cameras) <= MAX_THUMBNAILS
        for i in range(len(self.train_cameras)):
            aspect = float(self.train_cameras.widths[i]) / float(self.train_cameras.heights[i])
            image = _thumbnail(dataset.image_uint8(i)) if thumbnails else None
            self._frustums.append(self.server.scene.add_camera_frustum(
                f"/training_cameras/{i:04d}", fov=float(fov[i]), aspect=aspect, scale=scale, image=image,
                wxyz=wxyz[i], position=position[i], color=(60, 90, 200), thickness=2.0, thickness_units="screen"))

    def _set_frustums_visible(self, visible: bool) -> None:
        for frustum in self._frustums:
            frustum.visible = visible

    def _show_splats(self, show: bool) -> None:
        if show and self._splats is None:
            self._splats = self.server.scene.add_gaussian_splats("/splats", **splat_arrays(self.model))
        if self._splats is not None:
            self._splats.visible = show
        if show:
            self.server.scene.set_background_image(None)
        with self._lock:
            self._dirty.update(self.server.get_clients().keys())

    # ------------------------------------------------------------------------------------------------ clients
    def _on_connect(self, client) -> None:
        if self.initial_camera is not None:
            wxyz, position, fov = pose_of(self.initial_camera)
            client.camera.up_direction = world_up(self.train_cameras) if self.train_cameras is not None else (0, 0, 1)
            client.camera.position = position[0]
            client.camera.wxyz = wxyz[0]
            client.camera.fov = float(fov[0])
        client.camera.on_update(lambda camera: self._mark_dirty(camera.client.client_id))
        self._mark_dirty(client.client_id)

    def _mark_dirty(self, client_id: int) -> None:
        with self._lock:
            self._dirty.add(client_id)

    def render_client(self, client) -> bool:
        """Render ``client``'s camera and send it as the background; False when its camera is not known yet."""
        camera_state = client.camera
        try:
            width, height = render_size(camera_state.image_width, camera_state.image_height, self.max_render_pixels)
            camera = camera_from_pose(camera_state.wxyz, camera_state.position, camera_state.fov, width, height)
        except AssertionError:  # the browser has not reported its camera yet
            return False
        image = render_rgb(self.model, camera)
        client.scene.set_background_image(image, format="jpeg", jpeg_quality=JPEG_QUALITY)
        self.frames_sent += 1
        return True

    def render_pending(self, refresh_s: float | None = None) -> int:
        """Render every client whose camera moved (and, with ``refresh_s``, whose frame is older than that);
        returns the number of frames sent. Charged to ``render_s``."""
        if not self.training and self._splats is not None and self._splats.visible:
            return 0
        start = time.perf_counter()
        sent = 0
        for client_id, client in self.server.get_clients().items():
            with self._lock:
                due = client_id in self._dirty or (
                    refresh_s is not None and start - self._last_frame.get(client_id, 0.0) > refresh_s)
                self._dirty.discard(client_id)
            if due:
                if self.render_client(client):
                    self._last_frame[client_id] = time.perf_counter()
                    sent += 1
                else:
                    self._mark_dirty(client_id)
        self.render_s += time.perf_counter() - start
        return sent

    # ------------------------------------------------------------------------------------------------ training
    def toggle_pause(self) -> None:
        self.paused = not self.paused
        if self.training:
            self._pause.label = "Resume training" if self.paused else "Pause training"

    def training_callbacks(self, trainer) -> list[TrainingCallback]:
        """The callback the trainer runs after every step (statistics, pause, renders within the budget)."""
        return [TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], self.after_step, args=(trainer,))]

    def after_step(self, step: int, trainer) -> None:
        self.step = step
        self._last_losses = trainer.last_losses or self._last_losses
        now = time.perf_counter()
        if self._t0 is None:
            self._t0, self.render_s = now, 0.0
        if now - self._stats_at[0] >= STATS_EVERY_S:
            self._update_stats(step, trainer.model.num_points, trainer.config.max_num_iterations, now)
        if self.paused:  # held here, between two steps; renders go on, outside the training budget
            pause_start, render_s = time.perf_counter(), self.render_s
            while self.paused and not trainer.stop_requested:
                self.render_pending()
                time.sleep(0.05)
            self._t0 += time.perf_counter() - pause_start
            self.render_s = render_s
        if self.render_s <= self.config.render_share * (time.perf_counter() - self._t0):
            self.render_pending(refresh_s=REFRESH_S)

    def _update_stats(self, step: int, gaussians: int, total: int, now: float) -> None:
        last_time, last_step = self._stats_at
        rate = (step - last_step) / (now - last_time) if last_time and now > last_time else float("nan")
        self._stats_at = (now, step)
        lines = [f"**step** {step:,} / {total:,}" + (" (paused)" if self.paused else ""),
                 f"**Gaussians** {gaussians:,}"]
        if math.isfinite(rate):
            lines.append(f"**steps/s** {rate:.2f}")
        if "loss" in self._last_losses:
            lines.append(f"**loss** {self._last_losses['loss']:.4f}")
        if self._last_eval is not None:
            lines.append(f"**eval** step {self._last_eval['step']}: PSNR {self._last_eval.get('psnr', float('nan')):.2f} dB,"
                         f" SSIM {self._last_eval.get('ssim', float('nan')):.3f}")
        self._stats.content = "  \n".join(lines)

    def write(self, record: dict[str, Any]) -> None:  # RecordSink: the last evaluation for the panel
        if record.get("kind") == "eval":
            self._last_eval = record

    def close(self) -> None:  # the server outlives training (kc-train serves the result until Ctrl-C)
        pass

    def stop(self) -> None:
        self.server.stop()

    # ------------------------------------------------------------------------------------------------ camera path
    def add_keyframe(self, camera_state) -> Cameras:
        width, height = int(self._path_width.value), int(self._path_height.value)
        camera = camera_from_pose(camera_state.wxyz, camera_state.position, camera_state.fov, width, height)
        self.keyframes.append(camera)
        wxyz, position, fov = pose_of(camera)
        self.server.scene.add_camera_frustum(f"/camera_path/key_{len(self.keyframes) - 1:03d}", fov=float(fov[0]),
                                             aspect=width / height, scale=self._frustum_scale, wxyz=wxyz[0], position=position[0],
                                             color=(220, 120, 20), thickness=2.0, thickness_units="screen")
        self._path_status.content = f"{len(self.keyframes)} keyframes"
        return camera

    def clear_keyframes(self) -> None:
        for i in range(len(self.keyframes)):
            self.server.scene.remove_by_name(f"/camera_path/key_{i:03d}")
        self.keyframes = []
        self._path_status.content = "no keyframes"

    def export_camera_path(self, name: str | None = None) -> Path:
        """Write the keyframes' path as nerfstudio's camera-path JSON into ``run_dir/camera_paths/NAME.json``."""
        if not self.keyframes:
            raise ValueError("no keyframes: add the views the path should pass through first")
        name = (name or str(self._path_name.value) or "camera_path").strip()
        if not name or "/" in name or "\\" in name or name.startswith("."):
            raise ValueError(f"'{name}' is not a file name (no folders, not hidden)")
        keys = Cameras(
            viewmats=torch.cat([k.viewmats for k in self.keyframes]),
            Ks=torch.cat([pinhole_K(2 * math.atan(0.5 * float(k.heights[0]) / float(k.Ks[0, 1, 1])),
                                    int(self._path_width.value), int(self._path_height.value))[None]
                          for k in self.keyframes]),
            widths=torch.full((len(self.keyframes),), int(self._path_width.value)),
            heights=torch.full((len(self.keyframes),), int(self._path_height.value)),
        )
        data = camera_path_json(keys, float(self._path_fps.value), float(self._path_seconds.value),
                                loop=bool(self._path_loop.value))
        path = self.run_dir / CAMERA_PATH_DIR / f"{name.removesuffix('.json')}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(path, json.dumps(data, indent=1))
        return path

    def _export_clicked(self, client) -> None:
        try:
            path = self.export_camera_path()
        except (ValueError, OSError) as exc:
            self._path_status.content = f"not written: {exc}"
            return
        self._path_status.content = f"wrote `{path}`  \nrender it: `kc-render --load-config {self.run_dir} --camera-path {path}`"
        if client is not None:
            client.add_notification("Camera path written", str(path), auto_close_seconds=8.0)

    # ------------------------------------------------------------------------------------------------ kc-viewer
    def serve_forever(self, stop: threading.Event | None = None, poll_s: float = 0.02) -> None:
        """Render moved cameras until ``stop`` is set (or Ctrl-C)."""
        stop = stop or threading.Event()
        while not stop.is_set():
            if self.render_pending() == 0:
                time.sleep(poll_s)
