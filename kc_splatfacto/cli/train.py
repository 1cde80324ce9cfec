"""``kc-train METHOD --data SCENE [--dotted.config.fields VALUE ...]``: train a registered method.

Methods come from the ``kc_splatfacto.method_configs`` entry points and ``KC_SPLATFACTO_METHOD_CONFIGS``
(see :mod:`kc_splatfacto.registry`); ``kc-train --help`` lists them with their descriptions, and
``kc-train METHOD --help`` every field of its config. Examples::

    kc-train kc-splatfacto --data demo
    kc-train kc-splatfacto --data ../shared/data/castle-P30 --max-num-iterations 3000 \\
        --pipeline.model.steps-scale 0.1 --pipeline.model.kc-weight 1e-3 spars3r --downscale-factor 4
    kc-train kc-splatfacto --data SCENE colmap --downscale-factor 4 --eval-mode interval

The dataparser is a subcommand after the method's options (``auto``, the default, detects the format from
``--data``); ``kc-train METHOD DATAPARSER --help`` lists its options.
    kc-train kc-splatfacto --data demo --load-dir outputs/demo/kc-splatfacto/<timestamp>/nerfstudio_models

A mistake in the input (scene, flags, checkpoint, config) prints one line ``kc-train: error: ...`` and exits 2;
``--debug`` or ``KC_DEBUG=1`` shows its traceback. SIGTERM, like Ctrl-C, saves a checkpoint and exits 0.
"""

from __future__ import annotations

import copy
import sys
from typing import Any


from kc_splatfacto.registry import discover_methods

DESCRIPTION = "Train a Gaussian-splatting method (KC-3DGS or Splatfacto) on a scene."


def parse_config(argv: list[str]):
    """The TrainerConfig a command line describes (tyro subcommands, one per discovered method)."""
    import tyro

    methods = discover_methods()
    if not methods:
        raise SystemExit("kc-train: no methods registered (is kc-splatfacto installed? `pip install -e .`)")
    defaults = {name: copy.deepcopy(spec.config) for name, spec in methods.items()}
    descriptions = {name: spec.description for name, spec in methods.items()}
    union = _markers(tyro.extras.subcommand_type_from_defaults(defaults, descriptions))
    return tyro.cli(union, args=argv, description=DESCRIPTION)


def _markers(config_type: Any) -> Any:
    """The tyro conventions of every kc-train command line (fixed fields hidden, booleans take a value)."""
    import tyro

    return tyro.conf.SuppressFixed[tyro.conf.FlagConversionOff[config_type]]


def override_config(config: Any, args: list[str]) -> Any:
    """A copy of ``config`` with kc-train's dotted flags applied (``["--pipeline.model.kc-weight", "1e-4"]``):
    the one override path, shared by kc-bench's ``--set``."""
    import tyro

    return tyro.cli(_markers(type(config)), default=copy.deepcopy(config), args=list(args),
                    description=DESCRIPTION)


def entrypoint(argv: list[str] | None = None) -> int:
    """``kc-train``: user errors are one line and exit code 2 (``--debug`` shows the traceback)."""
    from kc_splatfacto.cli.main import run_cli

    return run_cli("kc-train", main, argv)


def main(argv: list[str]) -> int:
    if not argv:
        argv = ["--help"]
    config = parse_config(argv)

    from kc_splatfacto.engine.trainer import TrainingDivergedError
    from kc_splatfacto.engine.validation import validate_config
    from kc_splatfacto.errors import UserError
    from kc_splatfacto.model.strategy import NoGaussiansLeftError

    validate_config(config)  # every value, with its dotted name, before the device, the scene or the run folder
    try:
        config.machine.resolve_device()
    except RuntimeError as exc:  # e.g. --machine.device cuda on a machine without CUDA: the flag, not a bug
        raise UserError(str(exc)) from exc
    trainer = config.setup()
    try:
        run_dir = trainer.train()
    except (TrainingDivergedError, NoGaussiansLeftError) as exc:
        print(f"kc-train: {exc}", file=sys.stderr)
        return 1
    final = trainer.last_eval
    if final is not None:
        lpips = final.get("lpips")
        lpips_text = f"{lpips:.4f}" if lpips is not None else f"n/a ({final.get('lpips_unavailable')})"
        print(
            f"final {final.get('split', 'test')} metrics at step {final['step']} over {final['num_images']} images: "
            f"PSNR {final['psnr']:.3f} dB, SSIM {final['ssim']:.4f}, LPIPS({final.get('lpips_net', 'alex')}) {lpips_text}"
        )
    print(f"gaussians: {trainer.model.num_points}, training time: {trainer._train_s:.1f} s")
    print(f"output folder: {run_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(entrypoint())
