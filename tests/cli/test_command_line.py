"""The command line as a person meets it (issue 25): a misspelt method, flag or dataparser is one line naming the
closest valid names, exit 2, from the installed scripts; a method's --help fits on a screen with one --data."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from kc_splatfacto.cli.flags import config_flags, dataparser_flags
from kc_splatfacto.cli.main import did_you_mean
from kc_splatfacto.registry import discover_methods

BIN = Path(sys.executable).parent
#: a screen: lines and columns of the method's help
SCREEN_LINES = 50
SCREEN_COLUMNS = 120


def run(*args: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "KC_DEBUG"}
    env["COLUMNS"] = "100"
    return subprocess.run([str(BIN / args[0]), *args[1:]], capture_output=True, text=True, env=env, timeout=300)


@pytest.mark.parametrize("args, expected", [
    (("kc-train", "kc-splatfaco", "--data", "demo"), "unknown method 'kc-splatfaco'; did you mean kc-splatfacto?"),
    (("kc-train", "--data", "demo"), "the method comes first: kc-train METHOD --data SCENE"),
    (("kc-train", "kc-splatfacto", "--max-num-iteration", "5"),
     "unrecognized option --max-num-iteration; did you mean --max-num-iterations?"),
    (("kc-train", "kc-splatfacto", "--kc-weigth", "1"),
     "unrecognized option --kc-weigth; did you mean --pipeline.model.frequency.kc-weight?"),
    (("kc-train", "kc-splatfacto", "--data", "demo", "colmp"), "unrecognized option colmp; did you mean colmap?"),
    (("kc-train", "kc-splatfacto", "--data", "demo", "colmap", "--downscale-factr", "2"),
     "unrecognized option --downscale-factr; did you mean --downscale-factor?"),
    (("kc-train", "splatfacto", "--max-num-iterations", "abc"), "--max-num-iterations"),
    (("kc-train", "splatfacto", "--data", "demo", "demo", "--width", "32", "--max-num-iterations", "2"),
     "--max-num-iterations is an option of the method, not of the dataparser 'demo': put it before 'demo'"),
    (("kc-train", "splatfacto", "--pipeline.model.kc-weight", "1"),
     "--pipeline.model.kc-weight is now --pipeline.model.frequency.kc-weight"),
    (("kc-render", "--load-config", "x.yml", "--camera-path-filname", "p.json"),
     "did you mean --camera-path-filename?"),
    (("kc-eval", "--load-config", "x.yml", "--splt", "test"), "did you mean --split?"),
    (("kc-export", "--load-config", "x.yml", "--output-pth", "a.ply"), "did you mean --output-path?"),
    (("kc-process-data", "imgs", "--data", "x"), "did you mean images?"),
])
def test_mistakes_are_one_line_with_the_closest_names_and_exit_2(args, expected, capsys):
    module = {"kc-train": "train", "kc-render": "render", "kc-eval": "eval", "kc-export": "export",
              "kc-process-data": "process_data"}[args[0]]
    import importlib

    entrypoint = importlib.import_module(f"kc_splatfacto.cli.{module}").entrypoint
    assert entrypoint(list(args[1:])) == 2
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"{args[0]}: error: "), err
    assert expected in lines[0], lines[0]
    assert "Traceback" not in err and "╭" not in err


def test_installed_script_prints_one_line_and_exits_2():
    proc = run("kc-train", "kc-splatfacto", "--max-num-iteration", "5")
    assert proc.returncode == 2
    assert proc.stderr.strip() == ("kc-train: error: unrecognized option --max-num-iteration; did you mean "
                                   "--max-num-iterations? (see kc-train --help)")


def test_method_help_fits_on_a_screen_with_one_data_flag(capsys):
    from kc_splatfacto.cli import train as kc_train

    with pytest.raises(SystemExit) as exit_:
        kc_train.entrypoint(["kc-splatfacto", "--help"])
    assert exit_.value.code == 0
    stdout = capsys.readouterr().out
    lines = stdout.rstrip().splitlines()
    assert len(lines) <= SCREEN_LINES and max(len(line) for line in lines) <= SCREEN_COLUMNS
    assert len([line for line in lines if re.match(r"\s*--data\b", line)]) == 1
    assert "scheduler" not in stdout.replace("--optimizers.GROUP.{optimizer.lr, scheduler.lr-final", "")
    # the scene plan's switch (the paper's fixed settings one flag away), its skips and --plan-only, one line each
    plan_section = stdout.split("scene plan options:\n", 1)[1].split("\n\n", 1)[0].splitlines()
    assert [line.split()[0] for line in plan_section] == ["--pipeline.model.plan", "--pipeline.model.plan-skip",
                                                          "--plan-only"]
    assert "{on,off}" in plan_section[0] and "(default: on)" in plan_section[0]  # the registered methods plan
    # every flag of the method is named somewhere on the screen (featured, or in a group's brace list)
    flags = [f.name for f in config_flags(discover_methods()["kc-splatfacto"].config)
             if not f.name.startswith(("--optimizers.", "--method-name", "--timestamp"))]
    for name in flags:
        head, _, tail = name[2:].rpartition(".")
        assert name in stdout or re.search(rf"--{re.escape(head + '.' if head else '')}\{{[^}}]*\b{re.escape(tail)}\b",
                                           stdout, re.S), name
    with pytest.raises(SystemExit) as exit_:
        kc_train.entrypoint(["kc-splatfacto", "--help-all"])
    assert exit_.value.code == 0 and "--optimizers.means.optimizer.lr" in capsys.readouterr().out


def _value(default) -> list[str]:
    if isinstance(default, tuple):
        return [str(v) for v in default]
    return ["None" if default is None else str(default)]


def test_the_flags_listed_are_the_flags_tyro_accepts():
    """Every name config_flags derives parses through kc-train's real tyro parser, at its default value, so the
    suggestions and the help name real flags (one parse for the method's flags, one per dataparser)."""
    from kc_splatfacto.cli.train import parse_config

    config = discover_methods()["splatfacto"].config
    flags = [f for f in config_flags(config) if ".scheduler." not in f.name]  # scheduler flags need its subcommand
    assert len(flags) > 50
    args = [word for f in flags if not isinstance(f.default, tuple) for word in (f.name, *_value(f.default))]
    parsed = parse_config(["splatfacto", *args])
    assert parsed.max_num_iterations == config.max_num_iterations
    for parser, parser_flags in dataparser_flags().items():
        args = [word for f in parser_flags if f.name != "--data" and not isinstance(f.default, tuple)
                for word in (f.name, *_value(f.default))]
        parse_config(["splatfacto", "--data", "demo", parser, *args])


def test_did_you_mean_offers_nothing_far_off():
    assert did_you_mean("--zzzz", ["--data", "--fps"]) == ""
    assert did_you_mean("colmap2", ["colmap", "spars3r"]) == "; did you mean colmap?"
