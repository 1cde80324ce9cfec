"""``kc-train METHOD --data SCENE [--dotted.config.fields VALUE ...]``: train a registered method;
``kc-train --load-dir RUN [FLAG VALUE ...]``: resume a run from its folder alone.

Methods come from the ``kc_splatfacto.method_configs`` entry points and ``KC_SPLATFACTO_METHOD_CONFIGS``
(see :mod:`kc_splatfacto.registry`); ``kc-train --help`` lists them with their descriptions, and
``kc-train METHOD --help`` every field of its config. Examples::

    kc-train kc-splatfacto --data demo
    kc-train kc-splatfacto --data ../shared/data/castle-P30 --max-num-iterations 3000 \\
        --pipeline.model.steps-scale 0.1 --pipeline.model.frequency.kc-weight 1e-3 spars3r --downscale-factor 4
    kc-train kc-splatfacto --data SCENE colmap --downscale-factor 4 --eval-mode interval

The dataparser is a subcommand after the method's options (``auto``, the default, detects the format from
``--data``); ``kc-train METHOD DATAPARSER --help`` lists its options.

Resume (the newest checkpoint, or ``--load-step N``, continued in the same run folder)::

    kc-train --load-dir outputs/demo/kc-splatfacto/<timestamp>
    kc-train --load-config outputs/demo/kc-splatfacto/<timestamp>/config.yml --max-num-iterations 5000
    kc-train --load-dir RUN --data NEW_PATH
    kc-train kc-splatfacto --data demo --load-dir outputs/demo/kc-splatfacto/<timestamp>/nerfstudio_models

Without METHOD, ``--load-dir RUN`` (the run folder, its nerfstudio_models folder or a checkpoint in it) or
``--load-config RUN/config.yml`` takes the method, scene, dataparser and every setting from the run's ``config.yml``,
as the full command line that started it would give them. A flag beside it overrides the recorded value, one line
each (``kc-train: max_num_iterations 5000 (the run recorded 3000)``); the resume rules decide whether the same run
may go on with it (:mod:`kc_splatfacto.engine.run_guard`). A run whose scene folder moved says so and takes
``--data NEW_PATH``.

A mistake in the input (scene, flags, checkpoint, config) prints one line ``kc-train: error: ...`` and exits 2;
``--debug`` or ``KC_DEBUG=1`` shows its traceback. SIGTERM, like Ctrl-C, saves a checkpoint and exits 0.
"""

from __future__ import annotations

import copy
import dataclasses
import sys
from pathlib import Path
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
from kc_splatfacto.data.detect import DEMO_NAME, AutoDataParserConfig
from kc_splatfacto.engine.checkpoints import CHECKPOINT_DIR
from kc_splatfacto.engine.config_file import read_config_file
from kc_splatfacto.engine.datamanager import install_dataparser_subcommands
from kc_splatfacto.engine.run_guard import scene_of
from kc_splatfacto.engine.scene_planning import plan_only
from kc_splatfacto.engine.trainer import TrainerConfig, TrainingDivergedError
from kc_splatfacto.errors import UserError
from kc_splatfacto.model.strategy import NoGaussiansLeftError
from kc_splatfacto.registry import discover_dataparsers, discover_methods
from kc_splatfacto.viewer.viewer import Viewer, import_viser

DESCRIPTION = "Train a Gaussian-splatting method (KC-3DGS or Splatfacto) on a scene."
#: the second paragraph of ``kc-train --help``
RESUME_HELP = ("Resume a run from its folder alone: kc-train --load-dir RUN [FLAG VALUE ...] (or --load-config "
               "RUN/config.yml): the method, scene and settings come from RUN/config.yml, a flag beside it overrides "
               "the recorded value, --data NEW_PATH names a scene that moved.")


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
    return tyro.cli(union, args=argv, description=f"{DESCRIPTION}\n\n{RESUME_HELP}")


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
    if method is not None and _flag_value(argv, LOAD_CONFIG_FLAG) is not None:
        raise UserError(f"{LOAD_CONFIG_FLAG} resumes a run with the method, scene and settings its config.yml "
                        f"records: leave out the method (kc-train {LOAD_CONFIG_FLAG} RUN/config.yml [FLAG VALUE ...])")
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
    plan_only_asked = PLAN_ONLY_FLAG in argv
    argv = [a for a in argv if a != PLAN_ONLY_FLAG]
    if is_run_folder_resume(argv):
        config = resume_config(expand_bare_flags(argv))
    else:
        config = parse_command_line(expand_bare_flags(argv))
        if _flag_value(argv, SCENE_FLAG) is None:
            hint = (f"; or leave out the method to resume the run with the scene and settings it recorded "
                    f"(kc-train {LOAD_DIR_FLAG} RUN)" if _flag_value(argv, LOAD_DIR_FLAG) is not None else "")
            raise UserError(f"no scene given: pass --data PATH (a scene folder, or 'demo' for the demo scene){hint}")

    if plan_only_asked:
        scene_plan = plan_only(config)
        print(scene_plan.table())
        if config.pipeline.model.plan != "on":
            print(f"kc-train: the plan is off for this run ({PLAN_SWITCH}): these choices are not applied; "
                  "--pipeline.model.plan on applies them")
        return 0
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


PLAN_ONLY_FLAG = "--plan-only"
"""print the scene plan the run would get (seconds: the training split is read, nothing is trained or written)"""
PLAN_SWITCH = "--pipeline.model.plan off"
LOAD_DIR_FLAG = "--load-dir"
LOAD_CONFIG_FLAG = "--load-config"
#: fields that say what a resume continues from, not how the run trains: set from the command line, never reported
#: as overrides of what the run recorded (a run that was itself a resume recorded its own)
RESUME_CONTROL_FIELDS = ("load_dir", "load_step", "resume_from_other_run")
CONFIG_FILE = "config.yml"


def _flag_value(argv: list[str], flag: str) -> str | None:
    """The value of ``flag`` (``--flag VALUE`` or ``--flag=VALUE``) in ``argv``, the last one given; None if absent."""
    found = None
    for i, token in enumerate(argv):
        if token == flag:
            found = argv[i + 1] if i + 1 < len(argv) else ""
        elif token.startswith(flag + "="):
            found = token[len(flag) + 1:]
    return found


def _without_flag(argv: list[str], flag: str) -> list[str]:
    """``argv`` without ``flag`` and its value (either spelling)."""
    kept: list[str] = []
    skip = False
    for token in argv:
        if skip:
            skip = False
        elif token == flag:
            skip = True
        elif not token.startswith(flag + "="):
            kept.append(token)
    return kept


def is_run_folder_resume(argv: list[str]) -> bool:
    """``kc-train --load-dir RUN ...`` / ``kc-train --load-config RUN/config.yml ...``: no method first, a run named."""
    if not argv or not argv[0].startswith("-") or argv[0] in HELP_FLAGS:
        return False
    return any(_flag_value(argv, flag) is not None for flag in (LOAD_DIR_FLAG, LOAD_CONFIG_FLAG))


def run_config_path(load_dir: str | None, load_config: str | None) -> Path:
    """The ``config.yml`` of the run ``--load-config`` (the file, or its run folder) or else ``--load-dir`` (a run
    folder, its nerfstudio_models folder or a checkpoint in it) names; a :class:`UserError` naming the file expected
    when there is none."""
    flag, value = (LOAD_CONFIG_FLAG, load_config) if load_config is not None else (LOAD_DIR_FLAG, load_dir)
    path = Path(value or "")
    if not str(value or "").strip():
        raise UserError(f"{flag} needs a value: a run folder (kc-train {flag} RUN)")
    if not path.exists():
        raise UserError(f"{flag} {value} does not exist: pass a run folder kc-train wrote (outputs/EXPERIMENT/METHOD/"
                        "TIMESTAMP), its nerfstudio_models folder, one of its checkpoints or its config.yml")
    if flag == LOAD_CONFIG_FLAG and path.is_file():
        return path
    folder = path.parent if path.is_file() else path
    if folder.name == CHECKPOINT_DIR:
        folder = folder.parent
    config_path = folder / CONFIG_FILE
    if not config_path.is_file():
        raise UserError(
            f"{flag} {value}: {config_path} does not exist, and a resume without a method reads the run's method, "
            f"scene and settings from it (kc-train writes it into every run folder): pass a run folder kc-train "
            f"wrote, or the full command line (kc-train METHOD --data SCENE [OPTIONS] {LOAD_DIR_FLAG} {value})"
        )
    return config_path


def _dataparser_name(parser: Any) -> str:
    """The subcommand name of the dataparser config ``parser`` (``auto`` for an undetected one)."""
    if isinstance(parser, AutoDataParserConfig):
        return "auto"
    for name, spec in discover_dataparsers().items():
        if type(spec.config) is type(parser):
            return name
    raise UserError(f"the run's dataparser {type(parser).__name__} is not a registered dataparser (is the package "
                    "that provides it installed?)")


def _override_args(args: list[str], recorded: TrainerConfig, parsers: dict[str, list]) -> list[str]:
    """The flags given beside ``--load-dir`` as :func:`override_config` reads them: ``--data NEW_PATH`` and the
    dataparser's own options go behind the dataparser subcommand, the run's own one unless another is named (which
    then reads the run's scene unless ``--data`` names one)."""
    at = subcommand_index(["", *args], parsers) - 1
    head, tail = args[:at], args[at:]
    scene = _flag_value(head, SCENE_FLAG)
    head = _without_flag(head, SCENE_FLAG)
    parser_flags = {flag.name for flags in parsers.values() for flag in flags}
    method_flags = {flag.name for flag in config_flags(recorded)}
    for token in head:
        name = token.split("=", 1)[0]
        if name in parser_flags and name not in method_flags:
            raise UserError(f"{name} is an option of the dataparser: put it after the dataparser's name (kc-train "
                            f"{LOAD_DIR_FLAG} RUN {_dataparser_name(recorded.pipeline.datamanager.dataparser)} {name} "
                            "VALUE)")
    own = _dataparser_name(recorded.pipeline.datamanager.dataparser)
    if not tail and scene is None:
        return head
    subcommand, rest = (tail[0], tail[1:]) if tail else (own, [])
    if scene is None and subcommand != own and _flag_value(rest, SCENE_FLAG) is None:
        scene = str(recorded.pipeline.datamanager.dataparser.data)
    return [*head, subcommand, *([SCENE_FLAG, scene] if scene is not None else []), *rest]


def _settings(value: Any, prefix: str = "") -> dict[str, Any]:
    """{dotted field: value} of a config: every plain field, and for each nested config its class (a dataparser
    subcommand swaps the class)."""
    if not dataclasses.is_dataclass(value) or isinstance(value, type):
        return {prefix.rstrip("."): value}
    found: dict[str, Any] = {prefix.rstrip("."): type(value)} if prefix else {}
    for f in dataclasses.fields(value):
        found.update(_settings(getattr(value, f.name), f"{prefix}{f.name}."))
    return found


def overrides(recorded: Any, config: Any) -> list[str]:
    """One line for each setting in which ``config`` differs from the ``recorded`` one (a nested config whose class
    changed is one line; the resume-control fields are not settings)."""
    before, after = _settings(recorded), _settings(config)
    lines: list[str] = []
    swapped: list[str] = []
    for name, value in after.items():
        if name in RESUME_CONTROL_FIELDS or any(name.startswith(s + ".") for s in swapped):
            continue
        old = before.get(name, "(absent)")
        if isinstance(value, type) or isinstance(old, type):
            if value is not old:
                swapped.append(name)
                lines.append(f"kc-train: {name} {getattr(value, '__name__', value)} (the run recorded "
                             f"{getattr(old, '__name__', old)})")
            continue
        if old != value:
            label = "data" if name == "pipeline.datamanager.dataparser.data" else name
            lines.append(f"kc-train: {label} {value} (the run recorded {old})")
    return lines


def resume_config(argv: list[str]) -> TrainerConfig:
    """The TrainerConfig of ``kc-train --load-dir RUN [FLAG VALUE ...]`` (or ``--load-config RUN/config.yml``): the
    run's ``config.yml`` as the trainer wrote it, resumed from ``RUN`` (its newest checkpoint unless ``--load-step``),
    with the flags given beside it applied by :func:`override_config` and printed, one line each."""
    load_dir, load_config = _flag_value(argv, LOAD_DIR_FLAG), _flag_value(argv, LOAD_CONFIG_FLAG)
    config_path = run_config_path(load_dir, load_config)
    recorded = read_config_file(config_path, TrainerConfig)
    args = _without_flag(_without_flag(argv, LOAD_DIR_FLAG), LOAD_CONFIG_FLAG)
    base = copy.deepcopy(recorded)
    base.load_dir = Path(load_dir) if load_dir is not None else config_path.parent
    base.load_step, base.resume_from_other_run = None, False  # what this command says, not what the run was told
    parsers = dataparser_flags()
    if any(a in HELP_FLAGS for a in args[:subcommand_index(["", *args], parsers) - 1]):
        description = discover_methods().get(base.method_name)
        text = short_help(base.method_name, description.description if description else "", base)
        text = text.replace(f"kc-train {base.method_name} --data SCENE", f"kc-train {LOAD_DIR_FLAG} RUN", 1)
        text = text.replace(f"kc-train {base.method_name} --help-all", f"kc-train {LOAD_DIR_FLAG} RUN --help-all")
        print(text.replace("(default: ", "(the run: "))  # the defaults shown are the run's values
        raise SystemExit(0)
    args = _override_args(["--help" if a == HELP_ALL_FLAG else a for a in args], recorded, parsers)
    config = base
    if args:
        valid = [SCENE_FLAG, LOAD_DIR_FLAG, LOAD_CONFIG_FLAG, *(f.name for f in config_flags(base)),
                 *(f.name for flags in parsers.values() for f in flags), *HELP_FLAGS]
        with tyro_errors_as_one_line(valid, list(parsers), "kc-train"):
            config = override_config(base, args)
    for line in overrides(base, config):
        print(line, flush=True)
    check_scene_exists(config, recorded, config_path)
    return config


def check_scene_exists(config: TrainerConfig, recorded: TrainerConfig, config_path: Path) -> None:
    """The scene a resume from the run folder trains on must exist: the recorded one (a :class:`UserError` naming it
    and ``--data NEW_PATH`` when it moved), or the one ``--data`` names instead."""
    scene, recorded_scene = config.pipeline.datamanager.dataparser.data, recorded.pipeline.datamanager.dataparser.data
    if scene_of(config.pipeline.datamanager.dataparser) == DEMO_NAME or Path(scene).expanduser().exists():
        return
    if scene == recorded_scene:
        raise UserError(
            f"the scene {scene} that {config_path} records does not exist (moved or deleted?): pass --data NEW_PATH "
            f"with the scene where it is now (kc-train {LOAD_DIR_FLAG} {config_path.parent} --data NEW_PATH)"
        )
    raise UserError(f"--data {scene} does not exist: pass the scene folder the run trained on (it recorded "
                    f"{recorded_scene})")


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
