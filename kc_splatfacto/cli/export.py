"""``kc-export --load-config outputs/.../config.yml --output-path splat.ply``: the Gaussians as an Inria-style PLY."""

from __future__ import annotations

import sys
from pathlib import Path

from kc_splatfacto.cli.main import ArgumentParser, add_run_arguments, check_output_path, existing_run_config, run_cli
from kc_splatfacto.engine.run_io import load_run
from kc_splatfacto.errors import UserError
from kc_splatfacto.model.ply import export_ply

DEFAULT_OUTPUT_PATH = Path("splat.ply")


def run_export(load_config: Path, output_path: Path, step: int | None = None):
    """Load a run and write its Gaussians; returns :class:`kc_splatfacto.model.ply.PlyExportResult`."""
    load_config = existing_run_config("kc-export", load_config)
    check_output_path(output_path, "--output-path", DEFAULT_OUTPUT_PATH)
    loaded = load_run(load_config, step=step, device="cpu")
    params = loaded.model.gaussian_state()
    try:
        return export_ply(output_path, params)
    except ValueError as exc:  # e.g. every Gaussian non-finite: the run, not the code, is the problem
        raise UserError(f"kc-export: cannot export the Gaussians of {load_config.parent}: {exc}") from exc


def entrypoint(argv: list[str] | None = None) -> int:
    """``kc-export``: user errors are one line and exit code 2 (``--debug`` shows the traceback)."""
    return run_cli("kc-export", main, argv)


def main(argv: list[str]) -> int:
    parser = ArgumentParser(prog="kc-export", description="Export a run's Gaussians as a 3DGS PLY (SuperSplat, Inria viewers).")
    add_run_arguments(parser)
    parser.add_argument("--output-path", type=Path, default=DEFAULT_OUTPUT_PATH, help="the .ply file to write")
    args = parser.parse_args(argv)
    result = run_export(args.load_config, args.output_path, args.step)
    note = f", dropped {result.num_dropped} non-finite" if result.num_dropped else ""
    print(f"wrote {result.num_written} Gaussians (SH rest {result.sh_rest_coeffs}/channel{note}) -> {result.path}")
    return 0


if __name__ == "__main__":
    sys.exit(entrypoint())
