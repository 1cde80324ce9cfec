"""``kc-train METHOD --data SCENE [--dotted.config.fields VALUE ...]``: train a registered method.

Methods come from the ``kc_splatfacto.method_configs`` entry points and ``KC_SPLATFACTO_METHOD_CONFIGS``
(see :mod:`kc_splatfacto.registry`); ``kc-train --help`` lists them with their descriptions, and
``kc-train METHOD --help`` every field of its config. Examples::

    kc-train kc-splatfacto --data demo
    kc-train kc-splatfacto --data ../shared/data/castle-P30 --max-num-iterations 3000 \\
        --pipeline.model.steps-scale 0.1 --pipeline.model.frequency.kc-weight 1e-3 spars3r --downscale-factor 4
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

import tyro

from kc_splatfacto.cli.flags import (
    SCENE_FLAG,
    check_no_moved_flags,
    config_flags,
    dataparser_flags,
    move_scene_flag,
    short_help,
    subcommand_index,
    tyro_errors_as_one_line,
)
from kc_splatfacto.cli.main import did_you_mean, run_cli
from kc_splatfacto.engine.datamanager import install_dataparser_subcommands
from kc_splatfacto.engine.trainer import TrainingDivergedError
from kc_splatfacto.errors import UserError
from kc_splatfacto.model.strategy import NoGaussiansLeftError
from kc_splatfacto.registry import discover_methods
from kc_splatfacto.viewer.viewer import Viewer, import_viser

DESCRIPTION = "Train a Gaussian-splatting method (KC-3DGS or Splatfacto) on a scene."


def parse_config(argv: list[str]):
    """The TrainerConfig a command line describes (tyro subcommands, one per discovered method; ``--data SCENE``
    among the method's options is the dataparser's ``data``)."""
    methods = discover_methods()
    if not methods:
        raise SystemExit("kc-train: no methods registered (is kc-splatfacto installed? `pip install -e .`)")
    install_dataparser_subcommands()
    argv = move_scene_flag(argv, dataparser_flags())
    defaults = {name: copy.deepcopy(spec.config) for name, spec in methods.items()}
    descriptions = {name: spec.description for name, spec in methods.items()}
    union = _markers(tyro.extras.subcommand_type_from_defaults(defaults, descriptions))
    return tyro.cli(union, args=argv, description=DESCRIPTION)


def _markers(config_type: Any) -> Any:
    """The tyro conventions of every kc-train command line (fixed fields hidden, booleans take a value)."""
    return tyro.conf.SuppressFixed[tyro.conf.FlagConversionOff[config_type]]  # type: ignore[misc]  # built at run time


def override_config(config: Any, args: list[str]) -> Any:
    """A copy of ``config`` with kc-train's dotted flags applied (``["--pipeline.model.frequency.kc-weight", "1e-4"]``):
    the one override path, shared by kc-bench's ``--set``."""
    check_no_moved_flags(list(args))
    install_dataparser_subcommands()
    return tyro.cli(_markers(type(config)), default=copy.deepcopy(config), args=list(args),
                    description=DESCRIPTION)


def entrypoint(argv: list[str] | None = None) -> int:
    """``kc-train``: user errors are one line and exit code 2 (``--debug`` shows the traceback)."""
    return run_cli("kc-train", main, argv)


HELP_FLAGS = ("-h", "--help")
HELP_ALL_FLAG = "--help-all"


def parse_command_line(argv: list[str]):
    """:func:`parse_config` as a person meets it: a misspelt method, flag or dataparser is one line naming the
    closest valid names (a :class:`UserError`, exit 2); ``METHOD --help`` is one screen, ``--help-all`` tyro's."""
    methods = discover_methods()
    method = argv[0] if argv and not argv[0].startswith("-") else None
    if method is not None and method not in methods:
        raise UserError(f"unknown method '{method}'{did_you_mean(method, methods)} (kc-train --help lists them)")
    if method is None and argv and argv[0] not in HELP_FLAGS:
        raise UserError(f"the method comes first: kc-train METHOD --data SCENE [OPTIONS], METHOD one of "
                        f"{', '.join(sorted(methods))}")
    check_no_moved_flags(argv)
    parsers = dataparser_flags()
    before_dataparser = argv[1:subcommand_index(argv, parsers)]
    if method is not None and any(a in HELP_FLAGS for a in before_dataparser):
        print(short_help(method, methods[method].description, methods[method].config))
        raise SystemExit(0)
    argv = ["--help" if a == HELP_ALL_FLAG else a for a in argv]
    method_flags = [f.name for f in config_flags(methods[method].config)] if method else []
    check_method_flags_come_first(argv, method_flags, parsers)
    valid = [SCENE_FLAG] + method_flags
    valid += [f.name for flags in parsers.values() for f in flags] + list(HELP_FLAGS)
    with tyro_errors_as_one_line(valid, [*methods, *parsers], "kc-train"):
        return parse_config(argv)
def check_method_flags_come_first(argv: list[str], method_flags: list[str], parsers: dict[str, list]) -> None:
    """A method's option after the dataparser subcommand is tyro's "unrecognized option" (with itself as the closest
    name): a :class:`UserError` saying where it goes instead."""
    at = subcommand_index(argv, parsers)
    if at >= len(argv):
        return
    subcommand = argv[at]
    own = {flag.name for flag in parsers[subcommand]}
    for arg in argv[at + 1:]:
        name = arg.split("=", 1)[0]
        if name in method_flags and name not in own:
            raise UserError(f"{name} is an option of the method, not of the dataparser '{subcommand}': put it before "
                            f"'{subcommand}' (kc-train METHOD --data SCENE [OPTIONS] [DATAPARSER [DATAPARSER OPTIONS]])")


#: boolean options that also work bare (``--viewer`` for ``--viewer.enabled True``), as nerfstudio users type them
BARE_FLAGS = {"--viewer": "--viewer.enabled", "--logging.tensorboard": "--logging.tensorboard",
              "--logging.wandb": "--logging.wandb"}
BOOL_VALUES = ("True", "False")  # what tyro accepts


def expand_bare_flags(argv: list[str]) -> list[str]:
    """``--viewer`` -> ``--viewer.enabled True`` (and the other ``BARE_FLAGS``) where no boolean value follows."""
    expanded: list[str] = []
    for i, token in enumerate(argv):
        if token in BARE_FLAGS:
            following = argv[i + 1] if i + 1 < len(argv) else None
            expanded.append(BARE_FLAGS[token])
            if following not in BOOL_VALUES:
                expanded.append("True")
        else:
            expanded.append(token)
    return expanded


def main(argv: list[str]) -> int:
    if not argv:
        argv = ["--help"]
    config = parse_command_line(expand_bare_flags(argv))
    if not any(a == SCENE_FLAG or a.startswith(SCENE_FLAG + "=") for a in argv):
        raise UserError("no scene given: pass --data PATH (a scene folder, or 'demo' for the demo scene)")

    trainer = config.setup()  # every value checked, with its dotted name, before the device, scene or run folder
    viewer = attach_viewer(trainer) if config.viewer.enabled else None
    try:
        run_dir = trainer.train()
    except BaseException as exc:
        if viewer is not None:
            viewer.stop()
        if isinstance(exc, (TrainingDivergedError, NoGaussiansLeftError)):
            print(f"kc-train: {exc}", file=sys.stderr)
            return 1
        raise
    final = trainer.last_eval
    if final is not None:
        lpips = final.get("lpips")
        lpips_text = f"{lpips:.4f}" if lpips is not None else f"n/a ({final.get('lpips_unavailable')})"
        print(
            f"final {final.get('split', 'test')} metrics at step {final['step']} over {final['num_images']} images: "
            f"PSNR {final['psnr']:.3f} dB, SSIM {final['ssim']:.4f}, LPIPS({final.get('lpips_net', 'alex')}) {lpips_text}"
        )
    print(f"gaussians: {trainer.model.num_points}, training time: {trainer.train_seconds:.1f} s")
    print(f"output folder: {run_dir}")
    if viewer is not None and config.viewer.quit_on_train_completion:
        viewer.stop()
    elif viewer is not None:
        print(f"training finished; the viewer still serves the scene at {viewer.url} (Ctrl-C to stop)", flush=True)
        try:
            viewer.serve_forever()
        except KeyboardInterrupt:
            pass
        finally:
            viewer.stop()
    return 0


def attach_viewer(trainer):
    """Set the trainer up and attach a live viewer to it (its callbacks and record sink); returns the viewer."""
    import_viser()  # the install hint before the scene loads
    trainer.setup()
    datamanager = trainer.datamanager
    eval_cameras = datamanager.eval_dataset.cameras if datamanager.eval_dataset is not None else None
    viewer = Viewer(trainer.config.viewer, trainer.model, datamanager.train_dataset, trainer.run_dir, training=True,
                    initial_camera=eval_cameras[0] if eval_cameras is not None and len(eval_cameras) else None)
    trainer.add_callbacks(viewer.training_callbacks(trainer), sinks=[viewer])
    print(f"viewer: {viewer.url}", flush=True)
    return viewer


if __name__ == "__main__":
    sys.exit(entrypoint())
