"""kc-bench's scene-plan arms (``METHOD+plan``, ``METHOD+fixed``) on a tiny demo-scene study: the planned run trains
the plan's choices into its own folder and ends where its plan.json says; ``plans.md`` shows those choices; a
resumed study reuses a run that stopped at the plan's end instead of training it on to the budget."""

import json

import pytest

from kc_splatfacto.analysis import report
from kc_splatfacto.cli import bench
from kc_splatfacto.engine.config import load_config
from kc_splatfacto.engine.metrics_log import read_metrics

BUDGET = 120
# --steps-scale auto scales every schedule by BUDGET / 30000, the plan's end with it (the demo's 13000 -> ~52 steps)
ARGS = ["--data", "demo", "--methods", "kc-splatfacto+fixed", "kc-splatfacto+plan", "splatfacto", "splatfacto+fixed",
        "--seeds", "0", "--max-num-iterations", str(BUDGET), "--steps-scale", "auto", "--num-evals", "3",
        "--steps-per-save", "60"]


def _evals(run_dir):
    return [(r["step"], r["psnr"]) for r in read_metrics(run_dir / "metrics.jsonl") if r["kind"] == "eval"]


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    out = tmp_path_factory.mktemp("plan-arm")
    assert bench.entrypoint([*ARGS, "--output-dir", str(out)]) == 0
    return out


def test_a_plan_arm_trains_its_plan_and_ends_at_its_planned_step(study):
    runs = study / "runs" / "demo"
    planned = runs / "kc-splatfacto" / "seed0+plan"
    plan = json.loads((planned / "plan.json").read_text())
    choices = {d["field"]: d for d in plan["decisions"] if d["source"] == "plan"}
    end = choices["max_num_iterations"]["chosen"]
    assert choices["max_num_iterations"]["asked"] == BUDGET and 1 <= end < BUDGET
    assert _evals(planned)[-1][0] == end  # no step past the plan's end was trained or evaluated
    config = load_config(planned / "config.yml")
    changed = {f: d["chosen"] for f, d in choices.items() if d["chosen"] != d["asked"]}
    assert "pipeline.model.num_downscales" in changed  # the demo's 40x30 first stage holds 2 of 3 db3 levels
    for dotted, chosen in changed.items():  # config.yml records what the run trained
        value = config
        for part in dotted.split("."):
            value = getattr(value, part)
        assert value == chosen, dotted
    fixed = load_config(runs / "kc-splatfacto" / "seed0+fixed" / "config.yml")
    assert fixed.pipeline.model.num_downscales == choices["pipeline.model.num_downscales"]["asked"] == 2
    assert fixed.pipeline.model.plan == "off" and not (runs / "kc-splatfacto" / "seed0+fixed" / "plan.json").exists()
    # the report's final row of the plan arm is its planned end; the fixed arms' are the budget
    finals = {(r["method"], r["step"]) for r in report.final_rows(report.read_rows_csv(study / "evals.csv"))}
    assert ("kc-splatfacto+fixed", BUDGET) in finals and ("kc-splatfacto+plan", end) in finals
    assert ("splatfacto+fixed", BUDGET) in finals


def test_a_plain_arm_is_the_registered_method_and_a_fixed_arm_the_method_with_the_plan_off(study):
    runs = study / "runs" / "demo" / "splatfacto"
    registered = bench.discover_methods()["splatfacto"].config.pipeline.model.plan
    assert load_config(runs / "seed0" / "config.yml").pipeline.model.plan == registered
    assert (runs / "seed0" / "plan.json").exists() == (registered == "on")
    assert load_config(runs / "seed0+fixed" / "config.yml").pipeline.model.plan == "off"
    assert not (runs / "seed0+fixed" / "plan.json").exists()
    if registered == "off":
        assert _evals(runs / "seed0+fixed") == _evals(runs / "seed0")  # the same run, number for number


def _section(text: str, heading: str) -> list[str]:
    return text.split(heading, 1)[1].split("\n## ", 1)[0].splitlines()


def test_plans_md_shows_each_planned_arms_choices(study):
    text = (study / "plans.md").read_text()
    assert "kc-splatfacto+fixed" not in text and "splatfacto+fixed" not in text
    for method, folder in (("kc-splatfacto+plan", "kc-splatfacto/seed0+plan"), ("splatfacto", "splatfacto/seed0")):
        path = study / "runs" / "demo" / folder / "plan.json"
        if not path.exists():  # the registered splatfacto with the plan off
            assert f"## demo, {method} (" not in text
            continue
        rows = _section(text, f"## demo, {method} (")
        for d in json.loads(path.read_text())["decisions"]:
            row = next(line for line in rows if line.startswith(f"| {d['name']} |"))
            if d["source"] == "plan" and d["chosen"] != d["asked"]:
                assert f"**{d['chosen']}** (asked {d['asked']})" in row
            else:
                assert f"{d['chosen']} (" in row and "**" not in row


def test_resume_reuses_a_run_that_stopped_at_its_plans_end(study, capsys):
    planned = study / "runs" / "demo" / "kc-splatfacto" / "seed0+plan"
    log = (planned / "metrics.jsonl").read_text()
    capsys.readouterr()
    assert bench.entrypoint([*ARGS, "--output-dir", str(study), "--resume"]) == 0
    statuses = {r["method"]: r["status"] for r in json.loads((study / "runs.json").read_text())}
    assert statuses == dict.fromkeys(["kc-splatfacto+fixed", "kc-splatfacto+plan", "splatfacto", "splatfacto+fixed"],
                                     "reused")
    assert (planned / "metrics.jsonl").read_text() == log


@pytest.mark.parametrize("arm", ["kc-splatfacto+bogus", "no-such-method+plan"])
def test_an_unknown_arm_is_refused_naming_the_variants(tmp_path, capsys, arm):
    assert bench.entrypoint(["--data", "demo", "--methods", arm, "--output-dir", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert arm in err and "METHOD+plan" in err and "METHOD+fixed" in err


def test_resume_of_a_run_with_the_plan_the_other_way_names_the_switch(tmp_path, capsys):
    # a study of before the plan was on by default: its runs, resumed by a command that plans, are refused with the
    # --set that asks for them, never reused as planned runs
    registered = bench.discover_methods()["splatfacto"].config.pipeline.model.plan
    other = "off" if registered == "on" else "on"
    args = ["--data", "demo", "--methods", "splatfacto", "--seeds", "0", "--max-num-iterations", "8", "--num-evals", "2",
            "--output-dir", str(tmp_path / "study")]
    assert bench.entrypoint([*args, "--set", f"pipeline.model.plan={other}"]) == 0
    capsys.readouterr()
    assert bench.entrypoint([*args, "--resume"]) == 2
    err = capsys.readouterr().err
    assert f"--set pipeline.model.plan={other}" in err and "seed0" in err
    assert bench.entrypoint([*args, "--set", f"pipeline.model.plan={other}", "--resume"]) == 0
