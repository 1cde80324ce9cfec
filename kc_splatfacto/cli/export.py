"""``kc-export --load-config outputs/.../config.yml --output-path splat.ply``: the Gaussians as an Inria-style PLY."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def run_export(load_config: Path, output_path: Path, step: int | None = None):
    """Load a run and write its Gaussians; returns :class:`kc_splatfacto.model.ply.PlyExportResult`."""
    from kc_splatfacto.engine.run_io import load_run
    from kc_splatfacto.model.ply import export_ply

    load_config = Path(load_config)
    if not load_config.is_file():
        raise FileNotFoundError(f"kc-export: --load-config {load_config} does not exist (pass a run's config.yml)")
    loaded = load_run(load_config, step=step, device="cpu")
    params = {name: value.detach() for name, value in loaded.model.gauss_params.items()}
    return export_ply(output_path, params)


def entrypoint(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="kc-export", description="Export a run's Gaussians as a 3DGS PLY (SuperSplat, Inria viewers).")
    parser.add_argument("--load-config", type=Path, required=True, help="the run's config.yml")
    parser.add_argument("--output-path", type=Path, default=Path("splat.ply"), help="the .ply file to write")
    parser.add_argument("--step", type=int, default=None, help="checkpoint step (default: the latest)")
    args = parser.parse_args(argv)
    try:
        result = run_export(args.load_config, args.output_path, args.step)
    except (FileNotFoundError, ValueError, KeyError) as exc:
        print(f"kc-export: error: {exc}", file=sys.stderr)
        return 2
    note = f", dropped {result.num_dropped} non-finite" if result.num_dropped else ""
    print(f"wrote {result.num_written} Gaussians (SH rest {result.sh_rest_coeffs}/channel{note}) -> {result.path}")
    return 0


if __name__ == "__main__":
    sys.exit(entrypoint())
