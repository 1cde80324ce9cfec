"""``kc-process-data images --data PHOTOS --output-dir SCENE``: camera poses for a folder of photos (nerfstudio's
``ns-process-data images``, on pycolmap and the CPU).

Writes the COLMAP layout ``kc-train ... --data SCENE`` reads (see :mod:`kc_splatfacto.data.sfm`); with
``--num-train 12`` a SPARS3R-style sparse split whose seed points come from the train views alone::

    kc-process-data images --data photos/ --output-dir scenes/garden
    kc-process-data images --data frames/ --output-dir scenes/walk --matching-method sequential
    kc-process-data images --data photos/ --output-dir scenes/garden-12 --num-train 12
    kc-train kc-splatfacto --data scenes/garden

Progress is one line per stage on stdout; a failure the photos cause (too few, too little overlap, photos that do
not register) is one line ``kc-process-data: error: ...`` and exit code 2.
"""

from __future__ import annotations

import sys
import time
import typing
from pathlib import Path

from kc_splatfacto.cli.main import ArgumentParser, run_cli
from kc_splatfacto.data.sfm import (
    SEED_MAX,
    TEST_EVERY,
    CameraModel,
    MatchingMethod,
    ProcessImagesConfig,
    process_images,
)

PROG = "kc-process-data"


def entrypoint(argv: list[str] | None = None) -> int:
    """``kc-process-data``: user errors are one line and exit code 2 (``--debug`` shows the traceback)."""
    return run_cli(PROG, main, argv)


def build_parser() -> ArgumentParser:
    parser = ArgumentParser(prog=PROG, description="Turn a folder of photos into a scene kc-train reads (COLMAP SfM).")
    commands = parser.add_subparsers(dest="command", required=True, metavar="images")
    images = commands.add_parser("images", help="a folder of photos -> camera poses, seed points, undistorted images",
                                 description=ProcessImagesConfig.__doc__)
    images.add_argument("--data", type=Path, required=True, help="folder of photos (jpg, png, tif, bmp, webp)")
    images.add_argument("--output-dir", type=Path, required=True, help="scene folder to write")
    images.add_argument("--matching-method", choices=typing.get_args(MatchingMethod), default="auto",
                        help="exhaustive (every pair), sequential (neighbours in name order: video frames), spatial "
                             "(GPS in EXIF); auto: exhaustive up to 100 photos, sequential beyond (default: auto)")
    images.add_argument("--camera-model", choices=typing.get_args(CameraModel), default="SIMPLE_RADIAL",
                        help="COLMAP camera model; models with distortion are undistorted to PINHOLE "
                             "(default: SIMPLE_RADIAL)")
    images.add_argument("--num-train", type=int, default=None,
                        help=f"a SPARS3R-style split: this many train views, every {TEST_EVERY}th view for test, "
                             "seed points from the train views only")
    images.add_argument("--max-image-size", type=int, default=3200,
                        help="longer side SIFT sees; larger photos are downscaled for extraction (default: 3200)")
    images.add_argument("--seed", type=int, default=0,
                        help=f"random seed of COLMAP's RANSAC and mapper, 0..{SEED_MAX} (default: 0)")
    images.add_argument("--overwrite", action="store_true", help="replace images/, sparse/, colmap/ of --output-dir")
    images.add_argument("--verbose", action="store_true", help="show COLMAP's own log")
    return parser


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    config = ProcessImagesConfig(data=args.data, output_dir=args.output_dir, matching_method=args.matching_method,
                                 camera_model=args.camera_model, num_train=args.num_train,
                                 max_image_size=args.max_image_size, seed=args.seed, overwrite=args.overwrite,
                                 verbose=args.verbose)
    start = time.perf_counter()
    result = process_images(config, progress=lambda line: print(line, flush=True))
    total = time.perf_counter() - start
    print(f"registered {len(result.registered)} of {len(result.registered) + len(result.unregistered)} photos, "
          f"{result.num_points} points, {result.camera_model} camera(s), in {total:.0f} s")
    if result.train:
        print(f"split: {len(result.train)} train views (train_list.txt), {len(result.test)} test views (test_list.txt)")
    print(f"scene written to {result.scene}; train it with: kc-train kc-splatfacto --data {result.scene}")
    return 0


if __name__ == "__main__":
    sys.exit(entrypoint())
