"""Method discovery: the built-in methods, a throwaway installed distribution's entry point, the environment variable,
and the dotted command-line overrides of ``kc-train``."""

import dataclasses
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from kc_splatfacto.cli.train import parse_config
from kc_splatfacto.registry import discover_methods

PROJECT_ROOT = Path(__file__).resolve().parents[2]
BUILT_IN = ["splatfacto", "kc-splatfacto", "kc-splatfacto-fine", "kc-ablation-l1-wavelet", "kc-ablation-wavelet",
            "kc-ablation-unscaled-wavelet", "kc-ablation-heavy-wavelet", "kc-ablation-scaled-cbc", "kc-splatfacto-corr"]


def run_help(extra_path: Path | None = None, env_extra: dict | None = None) -> str:
    env = dict(os.environ, COLUMNS="200")
    if extra_path is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(extra_path), env.get("PYTHONPATH", "")])
    env.update(env_extra or {})
    code = "import sys; from kc_splatfacto.cli.train import entrypoint; sys.exit(entrypoint(['--help']))"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120,
                          cwd=PROJECT_ROOT)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


def test_builtin_methods_are_registered_with_the_papers_weights():
    methods = discover_methods()
    assert set(BUILT_IN) <= set(methods)
    kc = methods["kc-splatfacto"].config.pipeline.model.frequency
    assert (kc.wavelet_weight, kc.kc_weight, kc.cbc_weight, kc.wave, kc.wavelet_levels) == (1e-3, 1e-5, 1e-2, "db3", 3)
    assert kc.kc_supervised and kc.cbc_supervised and kc.wavelet_weighting == "paper"
    base = methods["splatfacto"].config.pipeline.model
    assert (base.frequency.wavelet_weight, base.frequency.kc_weight, base.frequency.cbc_weight,
            base.ssim_lambda) == (0.0, 0.0, 0.0, 0.2)
    assert methods["kc-splatfacto-fine"].config.pipeline.model.frequency.wavelet_weighting == "fine"
    assert methods["kc-ablation-l1-wavelet"].config.pipeline.model.ssim_lambda == 0.0
    assert methods["kc-ablation-unscaled-wavelet"].config.pipeline.model.frequency.wavelet_weighting == "uniform"
    assert methods["kc-ablation-scaled-cbc"].config.pipeline.model.frequency.cbc_correlation
    # the tuned method is the paper's settings with one change: the CBC on correlations
    corr = methods["kc-splatfacto-corr"].config.pipeline.model
    kc_model = methods["kc-splatfacto"].config.pipeline.model
    assert corr == dataclasses.replace(kc_model, frequency=dataclasses.replace(kc, cbc_correlation=True))
    for name in BUILT_IN:
        assert methods[name].config.method_name == name


def test_throwaway_distribution_registers_a_method_seen_by_kc_train_help(tmp_path):
    (tmp_path / "kc_dummy_plugin.py").write_text(textwrap.dedent("""
        from kc_splatfacto.engine.trainer import TrainerConfig
        from kc_splatfacto.registry import MethodSpecification

        dummy = MethodSpecification(config=TrainerConfig(method_name="dummy-splats"),
                                    description="a dummy method from a throwaway plugin")
    """))
    dist_info = tmp_path / "kc_dummy_plugin-0.0.1.dist-info"
    dist_info.mkdir()
    (dist_info / "METADATA").write_text("Metadata-Version: 2.1\nName: kc-dummy-plugin\nVersion: 0.0.1\n")
    (dist_info / "entry_points.txt").write_text(
        "[kc_splatfacto.method_configs]\ndummy-splats = kc_dummy_plugin:dummy\n"
    )
    output = run_help(tmp_path)
    assert "dummy-splats" in output and "a dummy method from a throwaway plugin" in output
    for name in BUILT_IN:
        assert name in output
    assert "dummy-splats" not in run_help()  # nothing leaks into this process's environment


def test_environment_variable_adds_a_method(tmp_path):
    (tmp_path / "kc_env_plugin.py").write_text(
        "from kc_splatfacto.engine.trainer import TrainerConfig\n"
        "from kc_splatfacto.registry import MethodSpecification\n"
        "spec = MethodSpecification(TrainerConfig(method_name='env-splats'), 'named by KC_SPLATFACTO_METHOD_CONFIGS')\n"
    )
    output = run_help(tmp_path, {"KC_SPLATFACTO_METHOD_CONFIGS": "env-splats=kc_env_plugin:spec"})
    assert "env-splats" in output and "named by KC_SPLATFACTO_METHOD_CONFIGS" in output


def test_dotted_overrides_reach_the_config():
    config = parse_config([
        "kc-splatfacto", "--data", "demo", "--max-num-iterations", "300", "--pipeline.model.frequency.kc-weight", "1e-3",
        "--pipeline.model.frequency.wavelet-weighting", "fine",
        "--eval-at-steps", "0", "10", "100", "--machine.seed", "3", "--optimizers.means.optimizer.lr", "2e-4",
        "auto", "--downscale-factor", "4",
    ])
    assert config.method_name == "kc-splatfacto"
    assert config.max_num_iterations == 300
    assert config.pipeline.model.frequency.kc_weight == 1e-3
    assert config.pipeline.model.frequency.cbc_weight == 1e-2  # untouched defaults stay the method's
    assert config.pipeline.model.frequency.wavelet_weighting == "fine"
    assert config.pipeline.datamanager.dataparser.downscale_factor == 4
    assert config.eval_at_steps == (0, 10, 100)
    assert config.machine.seed == 3 and config.optimizers.means.optimizer.lr == 2e-4
    assert str(config.pipeline.datamanager.dataparser.data) == "demo"  # --data: the dataparser's field
    # the registered defaults were not mutated by parsing
    assert discover_methods()["kc-splatfacto"].config.max_num_iterations == 30000


def test_dataparser_is_a_subcommand_with_its_own_options(castle_p30):
    from kc_splatfacto.data.colmap import ColmapDataParserConfig
    from kc_splatfacto.data.spars3r import Spars3rDataParserConfig

    config = parse_config(["kc-splatfacto", "--data", str(castle_p30), "--pipeline.model.frequency.kc-weight", "1e-4",
                           "colmap", "--downscale-factor", "4", "--eval-mode", "all"])
    parser = config.pipeline.datamanager.dataparser
    assert type(parser) is ColmapDataParserConfig and parser.downscale_factor == 4 and parser.eval_mode == "all"
    assert config.pipeline.model.frequency.kc_weight == 1e-4
    resolved = config.pipeline.datamanager.resolve_dataparser()
    assert resolved.data == castle_p30 and resolved.eval_mode == "all"
    assert resolved is not parser  # a copy: the user's config is left as given
    # no subcommand: detected, with the common options of `auto` handed on
    auto = parse_config(["kc-splatfacto", "--data", str(castle_p30), "auto", "--downscale-factor", "2"])
    detected = auto.pipeline.datamanager.resolve_dataparser()
    assert type(detected) is Spars3rDataParserConfig and detected.downscale_factor == 2
    with pytest.raises(SystemExit):  # a Literal choice field refuses other values
        parse_config(["kc-splatfacto", "--data", str(castle_p30), "colmap", "--eval-mode", "sometimes"])


def test_every_user_settable_field_has_a_help_line():
    import dataclasses

    from kc_splatfacto.registry import discover_dataparsers

    def fields_without_help(cls, seen):
        missing = []
        if cls in seen:
            return missing
        seen.add(cls)
        docs = _field_docs(cls)
        for f in dataclasses.fields(cls):
            default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
            if dataclasses.is_dataclass(default) and f.name != "dataparser":  # a group of fields, not a field
                continue
            if f.name not in docs:
                missing.append(f"{cls.__name__}.{f.name}")
        return missing

    config = discover_methods()["kc-splatfacto"].config
    classes = [type(config), type(config.machine), type(config.logging), type(config.pipeline),
               type(config.pipeline.datamanager), type(config.pipeline.model)]
    classes += [type(spec.config) for spec in discover_dataparsers().values()]
    seen: set = set()
    missing = [m for cls in classes for m in fields_without_help(cls, seen)]
    assert not missing, missing


def _field_docs(cls) -> set[str]:
    """Names of the fields of ``cls`` (and its dataclass bases) followed by a docstring line, as tyro reads them."""
    import ast
    import inspect

    documented = set()
    for klass in cls.__mro__:
        try:
            tree = ast.parse(inspect.getsource(klass))
        except (OSError, TypeError):
            continue
        body = tree.body[0].body
        for node, after in zip(body, body[1:]):
            if isinstance(node, ast.AnnAssign) and isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant):
                documented.add(node.target.id)
    return documented


def test_unknown_option_is_rejected():
    with pytest.raises(SystemExit):
        parse_config(["kc-splatfacto", "--pipeline.model.no-such-weight", "1"])


def test_kc_bench_set_goes_through_kc_trains_parser():
    from pathlib import Path

    from kc_splatfacto.cli.bench import build_run_config

    spec = discover_methods()["kc-splatfacto"].config
    common = dict(method="kc-splatfacto", data=Path("demo"), seed=1, max_steps=10, eval_steps=(1, 10),
                  runs_dir=Path("runs"), experiment="e", downscale_factor=2, steps_scale=0.1, device="cpu")
    config = build_run_config(spec, **common, overrides=[
        "pipeline.model.num_downscales=0", "pipeline.model.frequency.wavelet_weighting=fine", "eval_at_steps=0 5"])
    assert config.pipeline.model.num_downscales == 0 and config.pipeline.model.frequency.wavelet_weighting == "fine"
    assert config.eval_at_steps == (0, 5) and config.pipeline.datamanager.dataparser.downscale_factor == 2
    assert spec.pipeline.model.frequency.wavelet_weighting == "paper"  # the registered config is untouched
    for bad in ("pipeline.model.frequency.wavelet_weighting=coarse", "pipeline.model.no_such_field=1", "missing-equals"):
        with pytest.raises(ValueError, match="--set"):
            build_run_config(spec, **common, overrides=[bad])
