"""``kc-render --load-config outputs/.../config.yml --output-dir renders``: images and a video of a trained run.

Writes:
- ``views/<index>_<name>.png``: each test view's render next to its ground truth (render left, GT right);
- ``path.mp4``: a video along a smooth path through the test cameras (slerped orientations, lerped centres),
  written through OpenCV's VideoWriter and read back to check it really opens and holds every frame;
- with ``--diagnostics``: ``diagnostics/view_<i>_wavelets.png`` (signed coarse subband differences and the
  wavelet-vs-pixel error ratio) and ``diagnostics/kurtosis_history.png`` from the run's ``metrics.jsonl``.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

from kc_splatfacto.cli.main import ArgumentParser, add_run_arguments, existing_run_config, run_cli
from kc_splatfacto.engine.run_guard import check_writable_folder
from kc_splatfacto.errors import UserError

#: OpenCV FourCC of the mp4 writer; 'mp4v' (MPEG-4 part 2) ships with every opencv-python wheel.
MP4_FOURCC = "mp4v"


def to_uint8_bgr(rgb):
    """[H,W,3] float tensor in [0,1] -> contiguous uint8 BGR numpy array for OpenCV."""
    import numpy as np

    array = (rgb.detach().cpu().clamp(0, 1).numpy() * 255.0 + 0.5).astype(np.uint8)
    return np.ascontiguousarray(array[..., ::-1])


def write_side_by_side(model, dataset, out_dir: Path) -> list[Path]:
    """One PNG per view of ``dataset``: [render | ground truth]."""
    import cv2
    import numpy as np

    from kc_splatfacto.cli.eval import render_view
    from kc_splatfacto.model.splatfacto import composite_with_background

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


def write_video(frames_bgr, path: Path, fps: float) -> int:
    """Write uint8 BGR frames [H,W,3] to an mp4 and read it back; returns the number of frames read.

    Raises RuntimeError when OpenCV cannot open a writer or the written file does not decode to every frame.
    """
    import cv2

    frames_bgr = list(frames_bgr)
    if not frames_bgr:
        raise ValueError("kc-render: no frames to write")
    height, width = frames_bgr[0].shape[:2]
    path.parent.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*MP4_FOURCC), float(fps), (width, height))
    if not writer.isOpened():
        raise RuntimeError(f"kc-render: OpenCV cannot open an '{MP4_FOURCC}' writer for {path} (codec missing?)")
    for frame in frames_bgr:
        writer.write(frame)
    writer.release()
    capture = cv2.VideoCapture(str(path))
    try:
        if not capture.isOpened():
            raise RuntimeError(f"kc-render: the written video {path} does not open")
        count = 0
        while True:
            ok, frame = capture.read()
            if not ok:
                break
            if frame.shape[:2] != (height, width):
                raise RuntimeError(f"kc-render: {path} frame {count} is {frame.shape[:2]}, expected {(height, width)}")
            count += 1
    finally:
        capture.release()
    if count != len(frames_bgr):
        raise RuntimeError(f"kc-render: {path} holds {count} readable frames, {len(frames_bgr)} were written")
    return count


def render_path_video(model, keyframes, path: Path, num_frames: int, fps: float, loop: bool = False) -> int:
    """Render ``num_frames`` cameras interpolated through ``keyframes`` into an mp4; returns the frames checked."""
    from kc_splatfacto.cli.eval import render_view
    from kc_splatfacto.analysis.camera_path import interpolate_camera_path

    cameras = interpolate_camera_path(keyframes, num_frames, loop=loop)
    return write_video((to_uint8_bgr(render_view(model, cameras, i)[0]) for i in range(len(cameras))), path, fps)


def write_diagnostics(loaded, out_dir: Path, views: list[int]) -> list[Path]:
    """Wavelet diagnostics PNGs for the given test views, and the kurtosis history when the log has it."""
    from kc_splatfacto.cli.eval import render_view
    from kc_splatfacto.analysis.diagnostics import plot_kurtosis_history, save_view_diagnostics
    from kc_splatfacto.engine.metrics_log import read_metrics
    from kc_splatfacto.model.splatfacto import composite_with_background

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
    output_dir: Path,
    step: int | None = None,
    num_frames: int = 60,
    fps: float = 24.0,
    video: bool = True,
    diagnostics: bool = False,
    diagnostic_views: tuple[int, ...] = (0,),
) -> dict:
    from kc_splatfacto.engine.run_io import load_run

    load_config = existing_run_config("kc-render", load_config)
    if video and not (math.isfinite(fps) and fps > 0):
        raise UserError(f"kc-render: --fps must be a positive number, got {fps}")
    if video and num_frames < 1:
        raise UserError(f"kc-render: --num-frames must be at least 1, got {num_frames}")
    check_writable_folder(Path(output_dir), "--output-dir")
    loaded = load_run(load_config, step=step, device="cpu")
    if hasattr(loaded.model, "eval"):
        loaded.model.eval()
    dataset = loaded.test_dataset
    if dataset is None or len(dataset) == 0:
        raise UserError(f"kc-render: the test split of {loaded.run_dir} is empty; nothing to render")
    output_dir = Path(output_dir)
    result = {"views": write_side_by_side(loaded.model, dataset, output_dir / "views")}
    if video:
        video_path = output_dir / "path.mp4"
        result["video_frames"] = render_path_video(loaded.model, dataset.cameras, video_path, num_frames, fps)
        result["video"] = video_path
    if diagnostics:
        result["diagnostics"] = write_diagnostics(loaded, output_dir / "diagnostics", list(diagnostic_views))
    return result


def entrypoint(argv: list[str] | None = None) -> int:
    """``kc-render``: user errors are one line and exit code 2 (``--debug`` shows the traceback)."""
    return run_cli("kc-render", main, argv)


def main(argv: list[str]) -> int:
    parser = ArgumentParser(prog="kc-render", description="Render test views next to GT, and a camera-path video.")
    add_run_arguments(parser)
    parser.add_argument("--output-dir", type=Path, default=Path("renders"))
    parser.add_argument("--num-frames", type=int, default=60, help="frames of the path video")
    parser.add_argument("--fps", type=float, default=24.0)
    parser.add_argument("--no-video", action="store_true", help="only the side-by-side PNGs")
    parser.add_argument("--diagnostics", action="store_true", help="also the wavelet diagnostics PNGs")
    parser.add_argument("--diagnostic-views", type=int, nargs="+", default=[0], help="test view indices for diagnostics")
    args = parser.parse_args(argv)
    result = run_render(args.load_config, args.output_dir, args.step, args.num_frames, args.fps,
                        not args.no_video, args.diagnostics, tuple(args.diagnostic_views))
    print(f"wrote {len(result['views'])} side-by-side views to {args.output_dir / 'views'}")
    if "video" in result:
        print(f"wrote {result['video']} ({result['video_frames']} frames, checked by reading it back)")
    for path in result.get("diagnostics", []):
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(entrypoint())
