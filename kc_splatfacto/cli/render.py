"""``kc-render --load-config RUN/config.yml``: images and a video of a trained run, into ``RUN/renders`` by default.

Writes:
- ``views/<index>_<name>.png``: each test view's render next to its ground truth (render left, GT right);
- a video along a camera path, H.264 in an mp4 (what browsers play), read back to check every frame decodes:
  ``--camera-path-filename PATH.json`` renders nerfstudio's camera-path JSON (the viewer's export; see
  :mod:`kc_splatfacto.analysis.camera_path`) into ``<its stem>.mp4``; otherwise ``--path interpolate`` (through the
  training views, slerped orientations) or ``--path spiral`` (LLFF's spiral around the mean training camera) into
  ``<path>.mp4``, and that path as ``<path>_camera_path.json`` (the same format, to edit and render again);
- with ``--diagnostics``: ``diagnostics/view_<i>_wavelets.png`` (signed coarse subband differences and the
  wavelet-vs-pixel error ratio) and ``diagnostics/kurtosis_history.png`` from the run's ``metrics.jsonl``.

H.264 comes from the ffmpeg executable the imageio-ffmpeg wheel ships (libx264); without it the video is OpenCV's
MPEG-4 part 2 (``mp4v``), which the command names as a fallback (most browsers do not play it).
"""

from __future__ import annotations

import itertools
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from kc_splatfacto.analysis.camera_path import (
    camera_path_dict,
    interpolate_camera_path,
    read_camera_path,
    spiral_camera_path,
)
from kc_splatfacto.analysis.diagnostics import plot_kurtosis_history, save_view_diagnostics
from kc_splatfacto.atomic import atomic_write_text
from kc_splatfacto.cli.eval import render_view
from kc_splatfacto.cli.main import ArgumentParser, add_run_arguments, existing_run_config, run_cli
from kc_splatfacto.engine.metrics_log import read_metrics
from kc_splatfacto.engine.run_guard import check_writable_folder
from kc_splatfacto.engine.run_io import load_run
from kc_splatfacto.errors import UserError
from kc_splatfacto.losses.layout import composite_with_background

#: OpenCV FourCC of the fallback writer; 'mp4v' (MPEG-4 part 2) ships with every opencv-python wheel.
MP4_FOURCC = "mp4v"
#: codecs of --codec: H.264 through imageio-ffmpeg's ffmpeg, or OpenCV's mp4v
CODECS = ("h264", "mp4v")
#: built-in paths of --path
PATHS = ("interpolate", "spiral")
#: x264's constant rate factor (18: visually lossless for renders) and a moov atom up front (a browser starts playing
#: before the whole file has arrived)
H264_OUTPUT_PARAMS = ["-crf", "18", "-preset", "medium", "-movflags", "+faststart"]
#: the render folder inside the run folder when --output-dir is not given
DEFAULT_RENDER_DIR = "renders"


@dataclass
class VideoResult:
    """A written video: its file, frames read back, codec, size (width, height), and why H.264 was not used."""

    path: Path
    frames: int
    codec: str
    size: tuple[int, int]
    fallback_reason: str | None = None


def to_uint8_rgb(rgb):
    """[H,W,3] float tensor in [0,1] -> contiguous uint8 RGB numpy array."""
    return np.ascontiguousarray((rgb.detach().cpu().clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8))


def to_uint8_bgr(rgb):
    """[H,W,3] float tensor in [0,1] -> contiguous uint8 BGR numpy array for OpenCV."""
    return np.ascontiguousarray(to_uint8_rgb(rgb)[..., ::-1])


def write_side_by_side(model, dataset, out_dir: Path) -> list[Path]:
    """One PNG per view of ``dataset``: [render | ground truth]."""
    out_dir.mkdir(parents=True, exist_ok=True)
    filenames = getattr(getattr(dataset, "outputs", None), "image_filenames", None)
    paths = []
    for i in range(len(dataset)):
        rgb, _ = render_view(model, dataset.cameras, i)
        gt = composite_with_background(dataset.image_float(i), model.background_color)  # RGBA as evaluated
        stem = Path(filenames[i]).stem if filenames is not None else "view"
        path = out_dir / f"{i:03d}_{stem}.png"
        if not cv2.imwrite(str(path), np.concatenate([to_uint8_bgr(rgb), to_uint8_bgr(gt)], axis=1)):
            raise OSError(f"kc-render: OpenCV could not write {path}")
        paths.append(path)
    return paths


def even_size(frame):
    """``frame`` [H,W,3] with its last row/column repeated where H or W is odd (H.264's 4:2:0 needs even sides)."""
    pad_h, pad_w = frame.shape[0] % 2, frame.shape[1] % 2
    return np.pad(frame, ((0, pad_h), (0, pad_w), (0, 0)), mode="edge") if pad_h or pad_w else frame


def _write_h264(frames_rgb, path: Path, fps: float) -> tuple[int, int]:
    """Frames through imageio-ffmpeg's ffmpeg (libx264, yuv420p); returns the (width, height) written."""
    import imageio_ffmpeg

    writer, size = None, None
    try:
        for frame in frames_rgb:
            frame = even_size(frame)
            if writer is None:
                size = (frame.shape[1], frame.shape[0])
                writer = imageio_ffmpeg.write_frames(str(path), size, fps=float(fps), codec="libx264", quality=None,
                                                     macro_block_size=1, output_params=H264_OUTPUT_PARAMS)
                writer.send(None)  # start ffmpeg
            writer.send(frame)
    finally:
        if writer is not None:
            writer.close()
    return _written_size(size)


def _write_mp4v(frames_rgb, path: Path, fps: float) -> tuple[int, int]:
    writer, size = None, None
    try:
        for frame in frames_rgb:
            frame = even_size(frame)  # MPEG-4 part 2 is 4:2:0 as well (OpenCV would drop the odd row/column)
            if writer is None:
                size = (frame.shape[1], frame.shape[0])
                writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*MP4_FOURCC), float(fps), size)
                if not writer.isOpened():
                    raise RuntimeError(f"kc-render: OpenCV cannot open an '{MP4_FOURCC}' writer for {path}")
            writer.write(frame[..., ::-1].copy())  # OpenCV takes BGR
    finally:
        if writer is not None:
            writer.release()
    return _written_size(size)


def _written_size(size: tuple[int, int] | None) -> tuple[int, int]:
    if size is None:  # write_video checks for a first frame before a writer starts
        raise ValueError("kc-render: no frames to write")
    return size


def read_video(path: Path) -> tuple[int, tuple[int, int], str]:
    """Decode every frame of ``path``: (frame count, (width, height), codec name), through ffmpeg when installed
    (what a browser's decoder sees), else OpenCV."""
    try:
        import imageio_ffmpeg
    except ImportError:
        imageio_ffmpeg = None
    if imageio_ffmpeg is not None:
        reader = imageio_ffmpeg.read_frames(str(path))
        meta = next(reader)
        count = sum(1 for _ in reader)
        return count, tuple(meta["size"]), str(meta.get("codec", "")).split(" ")[0]

    capture = cv2.VideoCapture(str(path))
    try:
        if not capture.isOpened():
            raise RuntimeError(f"kc-render: the written video {path} does not open")
        size = (int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        count = 0
        while capture.read()[0]:
            count += 1
    finally:
        capture.release()
    return count, size, MP4_FOURCC


def h264_unavailable() -> str | None:
    """Why H.264 cannot be written here (None when it can)."""
    try:
        import imageio_ffmpeg

        imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError) as exc:
        return f"imageio-ffmpeg's ffmpeg is not available ({exc}; pip install imageio-ffmpeg)"
    return None


def write_video(frames_rgb, path: Path, fps: float, codec: str = "h264") -> VideoResult:
    """Write uint8 RGB frames [H,W,3] to an mp4 and decode it back.

    ``codec`` "h264" falls back to "mp4v" (``VideoResult.fallback_reason`` says why) when imageio-ffmpeg is absent.
    Raises RuntimeError when the written file does not decode to every frame at the written size.
    """
    frames_rgb = iter(frames_rgb)
    first = next(frames_rgb, None)
    if first is None:
        raise ValueError("kc-render: no frames to write")
    frames_rgb = itertools.chain([first], frames_rgb)
    count = [0]

    def counted(frames):
        for frame in frames:
            count[0] += 1
            yield frame

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    reason = h264_unavailable() if codec == "h264" else None
    used = "mp4v" if codec == "mp4v" or reason else "h264"
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")  # a video appears whole or not at all
    size = (_write_h264 if used == "h264" else _write_mp4v)(counted(frames_rgb), tmp, fps)
    read, read_size, read_codec = read_video(tmp)
    if read != count[0] or read_size != size or (used == "h264" and read_codec != "h264"):
        raise RuntimeError(f"kc-render: {path} decodes to {read} {read_codec} frames of {read_size}, {count[0]} "
                           f"{used} frames of {size} were written")
    tmp.replace(path)
    return VideoResult(path, read, used, size, reason)


def path_cameras(loaded, path_kind: str, num_frames: int):
    """The built-in path's cameras: through the training views (interpolate) or LLFF's spiral around them."""
    keys = loaded.train_dataset.cameras if loaded.train_dataset is not None and len(loaded.train_dataset) else None
    if keys is None:
        raise UserError(f"kc-render: the train split of {loaded.run_dir} is empty; no path through its views")
    if path_kind == "interpolate":
        return interpolate_camera_path(keys, num_frames)
    means = loaded.model.means.detach().cpu().double().numpy() if hasattr(loaded.model, "means") else np.zeros((0, 3))
    return spiral_camera_path(keys, means, num_frames)


def render_path_video(model, cameras, path: Path, fps: float, codec: str = "h264") -> VideoResult:
    """Render every camera of ``cameras`` into an mp4 (see :func:`write_video`)."""
    return write_video((to_uint8_rgb(render_view(model, cameras, i)[0]) for i in range(len(cameras))), path, fps,
                       codec)


def write_diagnostics(loaded, out_dir: Path, views: list[int]) -> list[Path]:
    """Wavelet diagnostics PNGs for the given test views, and the kurtosis history when the log has it."""
    paths = []
    dataset = loaded.test_dataset
    for i in views:
        if not 0 <= i < len(dataset):
            raise UserError(f"kc-render: --diagnostic-views index {i} is outside the test split (0..{len(dataset) - 1})")
        rgb, _ = render_view(loaded.model, dataset.cameras, i)
        paths.append(
            save_view_diagnostics(rgb, composite_with_background(dataset.image_float(i), loaded.model.background_color),
                                  out_dir / f"view_{i:03d}_wavelets.png",
                                  title=f"test view {i}, step {loaded.step}")
        )
    log = Path(loaded.run_dir) / "metrics.jsonl"
    if log.is_file():
        records = read_metrics(log)
        if any(r.get("kurtosis_render") is not None for r in records):
            paths.append(plot_kurtosis_history(records, out_dir / "kurtosis_history.png", title=str(loaded.run_dir)))
        else:
            print(f"kc-render: {log} has no kurtosis records (logged on logging steps only); no kurtosis plot")
    return paths


def run_render(
    load_config: Path,
    output_dir: Path | None = None,
    step: int | None = None,
    num_frames: int = 120,
    fps: float = 24.0,
    video: bool = True,
    diagnostics: bool = False,
    diagnostic_views: tuple[int, ...] = (0,),
    camera_path_filename: Path | None = None,
    path_kind: str = "interpolate",
    codec: str = "h264",
) -> dict:
    """Render a run (see the module docstring); ``output_dir`` None is ``<run folder>/renders``."""
    load_config = existing_run_config("kc-render", load_config)
    if video and not (math.isfinite(fps) and fps > 0):
        raise UserError(f"kc-render: --fps must be a positive number, got {fps}")
    if video and num_frames < 1:
        raise UserError(f"kc-render: --num-frames must be at least 1, got {num_frames}")
    if path_kind not in PATHS:
        raise UserError(f"kc-render: --path must be one of {', '.join(PATHS)}, got {path_kind}")
    if codec not in CODECS:
        raise UserError(f"kc-render: --codec must be one of {', '.join(CODECS)}, got {codec}")
    camera_path = read_camera_path(camera_path_filename) if video and camera_path_filename is not None else None
    if output_dir is None:
        output_dir = load_config.parent / DEFAULT_RENDER_DIR
        check_writable_folder(output_dir, "--output-dir's default", "pass --output-dir with a folder you can write to")
    else:
        output_dir = Path(output_dir)
        check_writable_folder(output_dir, "--output-dir")
    loaded = load_run(load_config, step=step, device="cpu")
    if hasattr(loaded.model, "eval"):
        loaded.model.eval()
    dataset = loaded.test_dataset
    if dataset is None or len(dataset) == 0:
        raise UserError(f"kc-render: the test split of {loaded.run_dir} is empty; nothing to render")
    result = {"output_dir": output_dir, "views": write_side_by_side(loaded.model, dataset, output_dir / "views")}
    if video:
        if camera_path is not None and camera_path_filename is not None:
            cameras, name = camera_path.cameras, Path(camera_path_filename).stem
            fps = camera_path.fps if camera_path.fps is not None else fps
        else:
            cameras, name = path_cameras(loaded, path_kind, num_frames), path_kind
            json_path = output_dir / f"{name}_camera_path.json"
            atomic_write_text(json_path, json.dumps(camera_path_dict(cameras, fps), indent=1))
            result["camera_path"] = json_path
        result["video"] = render_path_video(loaded.model, cameras, output_dir / f"{name}.mp4", fps, codec)
    if diagnostics:
        result["diagnostics"] = write_diagnostics(loaded, output_dir / "diagnostics", list(diagnostic_views))
    return result


def entrypoint(argv: list[str] | None = None) -> int:
    """``kc-render``: user errors are one line and exit code 2 (``--debug`` shows the traceback)."""
    return run_cli("kc-render", main, argv)


def main(argv: list[str]) -> int:
    parser = ArgumentParser(prog="kc-render", description="Render test views next to GT, and a video along a camera path.")
    add_run_arguments(parser)
    parser.add_argument("--output-dir", type=Path, default=None,
                        help=f"where to write (default: {DEFAULT_RENDER_DIR}/ in the run folder)")
    parser.add_argument("--camera-path-filename", type=Path, default=None,
                        help="nerfstudio camera-path JSON (the viewer's export) to render instead of --path")
    parser.add_argument("--path", choices=PATHS, default="interpolate",
                        help="built-in path: through the training views, or a spiral around them (default: interpolate)")
    parser.add_argument("--num-frames", type=int, default=120, help="frames of a built-in path (default: 120)")
    parser.add_argument("--fps", type=float, default=24.0,
                        help="frame rate of a built-in path, or of a JSON that names none (default: 24)")
    parser.add_argument("--codec", choices=CODECS, default="h264",
                        help="h264 (imageio-ffmpeg's libx264; browsers play it) or mp4v (OpenCV; a fallback)")
    parser.add_argument("--no-video", action="store_true", help="only the side-by-side PNGs")
    parser.add_argument("--diagnostics", action="store_true", help="also the wavelet diagnostics PNGs")
    parser.add_argument("--diagnostic-views", type=int, nargs="+", default=[0], help="test view indices for diagnostics")
    args = parser.parse_args(argv)
    result = run_render(args.load_config, args.output_dir, args.step, args.num_frames, args.fps,
                        not args.no_video, args.diagnostics, tuple(args.diagnostic_views),
                        args.camera_path_filename, args.path, args.codec)
    print(f"wrote {len(result['views'])} side-by-side views to {result['output_dir'] / 'views'}")
    if "camera_path" in result:
        print(f"wrote {result['camera_path']} (nerfstudio's camera-path format; edit it and pass "
              "--camera-path-filename)")
    if "video" in result:
        video = result["video"]
        if video.fallback_reason:
            print(f"kc-render: H.264 unavailable: {video.fallback_reason}; wrote MPEG-4 part 2 ({MP4_FOURCC}) instead, "
                  "which most browsers do not play", file=sys.stderr)
        print(f"wrote {video.path} ({video.codec}, {video.frames} frames of {video.size[0]}x{video.size[1]}, "
              "checked by decoding it)")
    for path in result.get("diagnostics", []):
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(entrypoint())
