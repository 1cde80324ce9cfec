"""``kc-export --load-config outputs/.../config.yml --output-path scene.spz``: the Gaussians as a splat file.

Without ``--output-path`` the file goes into the run's own folder: ``RUN/exports/splat.<ending>`` (as kc-render's
``RUN/renders``), whatever the current folder.

Formats (``--format``, or the output file's ending): ``ply`` (Inria's 3DGS PLY, ``.ply``), ``splat`` (antimatter15's,
``.splat``), ``ply-compressed`` (SuperSplat's compressed PLY, ``.compressed.ply``) and ``spz`` (Niantic's, ``.spz``).
"""

from __future__ import annotations

import sys
from pathlib import Path

from kc_splatfacto.cli.main import (
    ArgumentParser,
    add_run_arguments,
    check_folder_can_hold,
    check_output_path,
    existing_run_config,
    path_flag,
    run_cli,
)
from kc_splatfacto.engine.run_io import load_run
from kc_splatfacto.errors import UserError
from kc_splatfacto.model.export import EXTENSIONS, FORMATS, ExportResult, export_gaussians, format_from_path

DEFAULT_STEM = "splat"
DEFAULT_FOLDER = "exports"
"""without --output-path: RUN/exports/splat.<the format's ending>, RUN the run's folder"""
_ENDING = {fmt: ending for ending, fmt in EXTENSIONS.items()}  # the file ending each format gets by default


def resolve_format(output_path: Path | None, fmt: str | None, run_dir: Path = Path(".")) -> tuple[Path, str]:
    """The output path and format from what the user passed: ``--format`` and the file's ending must agree where
    both say something (a compressed PLY may end in plain ``.ply``); with neither, the default
    ``run_dir/exports/splat.ply``."""
    if output_path is None:
        fmt = fmt or "ply"
        return run_dir / DEFAULT_FOLDER / (DEFAULT_STEM + _ENDING[fmt]), fmt
    implied = format_from_path(output_path)
    if fmt is None:
        if implied is None:
            raise UserError(f"kc-export: cannot tell the format of --output-path {output_path} from its name: pass "
                            f"--format ({'|'.join(FORMATS)}) or end the name in {', '.join(EXTENSIONS)}")
        return output_path, implied
    if implied is not None and implied != fmt and not (fmt == "ply-compressed" and implied == "ply"):
        raise UserError(f"kc-export: --format {fmt} but --output-path {output_path} names a {implied} file: end the "
                        f"name in {_ENDING[fmt]}, or drop --format")
    return output_path, fmt


def run_export(load_config: Path, output_path: Path | None = None, step: int | None = None, fmt: str | None = None,
               overwrite: bool = False) -> ExportResult:
    """Load a run and write its Gaussians; returns :class:`kc_splatfacto.model.export.ExportResult`."""
    passed = None if output_path is None else Path(output_path)
    load_config = existing_run_config("kc-export", load_config)
    if passed is not None:  # a folder or an unwritable place is said as such, before the name's format
        check_output_path(passed, "--output-path")
    output_path, fmt = resolve_format(passed, fmt, load_config.parent)
    default = output_path if passed is None else None  # messages say "--output-path's default" for a path not typed
    if passed is None:  # checked, not created: the writer makes RUN/exports once the run has loaded
        check_folder_can_hold(output_path.parent, f"the run's {DEFAULT_FOLDER} folder {output_path.parent}",
                              "--output-path")
    if output_path.exists() and not overwrite:
        raise UserError(f"kc-export: {path_flag('--output-path', output_path, default)} exists: pass --overwrite to "
                        "replace it, or another --output-path")
    loaded = load_run(load_config, step=step, device="cpu")
    params = loaded.model.gaussian_state()
    antialiased = getattr(loaded.model.config, "rasterize_mode", "classic") == "antialiased"
    try:
        return export_gaussians(output_path, params, fmt, antialiased=antialiased)
    except ValueError as exc:  # e.g. every Gaussian non-finite: the run, not the code, is the problem
        raise UserError(f"kc-export: cannot export the Gaussians of {load_config.parent} as {fmt}: {exc}") from exc
    except OSError as exc:  # the folder was writable a moment ago: a full disk, a permission changed meanwhile
        raise UserError(f"kc-export: cannot write --output-path {output_path} ({exc.strerror or exc}): free space "
                        "or choose another --output-path") from exc


def entrypoint(argv: list[str] | None = None) -> int:
    """``kc-export``: user errors are one line and exit code 2 (``--debug`` shows the traceback)."""
    return run_cli("kc-export", main, argv)


def main(argv: list[str]) -> int:
    parser = ArgumentParser(prog="kc-export", description="Export a run's Gaussians as a splat file: ply (Inria "
                            "3DGS, most tools), splat (antimatter15), ply-compressed (SuperSplat), spz (Niantic).")
    add_run_arguments(parser)
    parser.add_argument("--output-path", type=Path, default=None,
                        help=f"the file to write (default: RUN/{DEFAULT_FOLDER}/{DEFAULT_STEM}{_ENDING['ply']}, "
                             "or with --format " + ", ".join(DEFAULT_STEM + _ENDING[f] for f in FORMATS if f != "ply")
                             + "; RUN is the run's folder, that of --load-config)")
    parser.add_argument("--format", choices=FORMATS, default=None,
                        help="the file format (default: from the --output-path ending; ply without one)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --output-path")
    args = parser.parse_args(argv)
    result = run_export(args.load_config, args.output_path, args.step, args.format, args.overwrite)
    notes = [f"dropped {result.num_dropped} non-finite"] if result.num_dropped else []
    if result.num_transparent:
        notes.append(f"left out {result.num_transparent} with opacity <= 1/255")
    sh = "no SH rest: splat stores base colours" if result.format == "splat" else f"SH rest {result.sh_rest_coeffs}/channel"
    note = "".join(f", {n}" for n in notes)
    print(f"wrote {result.num_written} Gaussians as {result.format} ({sh}{note}, {result.num_bytes:,} bytes) "
          f"-> {result.path}")
    return 0


if __name__ == "__main__":
    sys.exit(entrypoint())
