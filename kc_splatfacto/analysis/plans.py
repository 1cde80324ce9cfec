"""``plans.md``: the scene plan's choices in a study, per scene and arm (each run's ``plan.json``), so a report of a
planned arm says what the plan left out and what it kept (docs/plan.md)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Sequence

from kc_splatfacto.atomic import atomic_write_text
from kc_splatfacto.plan.scene_plan import PLAN_FILE, Decision


def plan_rows(runs: Sequence[dict]) -> list[dict[str, Any]]:
    """Per (scene, method) whose runs hold a ``plan.json``: its lowest seed's decisions, and the seeds whose plan
    differs from that one's choices (the plan reads the training split, so it should not depend on the seed)."""
    groups: dict[tuple[str, str], list[tuple[int, dict]]] = {}
    for run in runs:
        path = Path(run["run_dir"]) / PLAN_FILE
        if path.is_file():
            groups.setdefault((run["scene"], run["method"]), []).append((int(run["seed"]), json.loads(path.read_text())))
    rows = []
    for (scene, method), plans in groups.items():
        plans.sort(key=lambda item: item[0])
        first = plans[0][1]

        def choices(plan: dict) -> list:
            return [(d.get("field"), d.get("chosen")) for d in plan.get("decisions", []) if d.get("source") == "plan"]

        rows.append({"scene": scene, "method": method, "seeds": [s for s, _ in plans], "plan": first,
                     "differs": [s for s, p in plans[1:] if choices(p) != choices(first)]})
    return rows


def write_plan_table(runs: Sequence[dict], out_dir: Path) -> dict[str, Path]:
    """``plans.md`` of the runs that made a scene plan (nothing when none did)."""
    rows = plan_rows(runs)
    if not rows:
        return {}
    lines = ["# The scene plan's choices", "",
             "Per scene and arm, from the lowest seed's `plan.json` (bold: changed from what the study asked).", ""]
    for row in rows:
        plan = row["plan"]
        seeds = ", ".join(str(s) for s in row["seeds"])
        agree = "the same choices in every seed" if not row["differs"] else \
            f"other choices in seeds {', '.join(str(s) for s in row['differs'])}"
        lines += [f"## {row['scene']}, {row['method']} ({plan.get('views')} training views, {plan.get('size')}; "
                  f"seeds {seeds}: {agree})", "",
                  "| decision | measured | rule | choice |", "|---|---|---|---|"]
        decisions = [Decision(**d) for d in plan.get("decisions", [])]
        lines += [f"| {d.name} | {d.measured} | {d.rule} | {d.choice('**', yours='set by the study')} |"
                  for d in decisions]
        lines.append("")
    path = Path(out_dir) / "plans.md"
    atomic_write_text(path, "\n".join(lines))
    return {"plans": path}
