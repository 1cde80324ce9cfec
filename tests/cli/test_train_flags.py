"""kc-train's bare boolean options (``--viewer``, ``--logging.tensorboard``, ``--logging.wandb``)."""

from __future__ import annotations

import pytest

from kc_splatfacto.cli.train import expand_bare_flags, parse_config


@pytest.mark.parametrize("argv, viewer, tensorboard, wandb", [
    (["splatfacto", "--data", "demo", "--viewer"], True, False, False),
    (["splatfacto", "--viewer", "--logging.tensorboard", "--data", "demo"], True, True, False),
    (["splatfacto", "--data", "demo", "--viewer", "False", "--logging.wandb", "True"], False, False, True),
    (["splatfacto", "--data", "demo", "--viewer.enabled", "True", "--viewer.port", "7010"], True, False, False),
])
def test_bare_flags_parse_to_the_config(argv, viewer, tensorboard, wandb):
    config = parse_config(expand_bare_flags(argv))
    assert (config.viewer.enabled, config.logging.tensorboard, config.logging.wandb) == (viewer, tensorboard, wandb)


def test_other_arguments_pass_through_unchanged():
    argv = ["kc-splatfacto", "--data", "demo", "--max-num-iterations", "10", "colmap", "--downscale-factor", "4"]
    assert expand_bare_flags(argv) == argv
