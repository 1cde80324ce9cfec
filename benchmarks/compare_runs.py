"""Are two training runs bit-identical? Compares the final checkpoints (every tensor with ``torch.equal``, every other
value with ``==``) and ``metrics.jsonl`` (every record; wall-clock fields, render speed and paths left out).

Used to show that a refactor changes no numerics::

    python benchmarks/compare_runs.py RUN_DIR_BEFORE RUN_DIR_AFTER

Prints one line per difference (at most 20) and a summary; exit status 0 when identical, 1 otherwise.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import torch

#: fields that measure time or name a place, not the numerics
VOLATILE = {"elapsed_s", "train_s", "render_fps", "path"}


def _differences(a: Any, b: Any, where: str) -> Iterator[str]:
    if isinstance(a, torch.Tensor) or isinstance(b, torch.Tensor):
        if not (isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor)):
            yield f"{where}: tensor against {type(b if isinstance(a, torch.Tensor) else a).__name__}"
        elif a.shape != b.shape or a.dtype != b.dtype:
            yield f"{where}: {tuple(a.shape)} {a.dtype} against {tuple(b.shape)} {b.dtype}"
        elif not torch.equal(a, b):
            diff = (a.double() - b.double()).abs()
            yield f"{where}: values differ (max |diff| {float(diff[diff == diff].max()) if diff.numel() else 0:.3g})"
    elif isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        if not np.array_equal(np.asarray(a), np.asarray(b)):
            yield f"{where}: arrays differ"
    elif isinstance(a, dict) and isinstance(b, dict):
        for key in sorted(set(a) | set(b), key=str):
            if key in VOLATILE:
                continue
            if key not in a or key not in b:
                yield f"{where}.{key}: only in {'after' if key not in a else 'before'}"
            else:
                yield from _differences(a[key], b[key], f"{where}.{key}")
    elif isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        if len(a) != len(b):
            yield f"{where}: length {len(a)} against {len(b)}"
        for i, (x, y) in enumerate(zip(a, b)):
            yield from _differences(x, y, f"{where}[{i}]")
    elif a != b and not (isinstance(a, float) and isinstance(b, float) and a != a and b != b):
        yield f"{where}: {a!r} against {b!r}"


def _final_checkpoint(run_dir: Path) -> Path:
    checkpoints = sorted((run_dir / "nerfstudio_models").glob("step-*.ckpt"))
    if not checkpoints:
        raise SystemExit(f"{run_dir}: no nerfstudio_models/step-*.ckpt (pass a finished run folder)")
    return checkpoints[-1]


def _records(run_dir: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines() if line.strip()]


def compare_runs(before: Path, after: Path) -> list[str]:
    """Every difference between two run folders' final checkpoints and metrics logs (empty: bit-identical)."""
    ckpt_a = torch.load(_final_checkpoint(before), map_location="cpu", weights_only=False)
    ckpt_b = torch.load(_final_checkpoint(after), map_location="cpu", weights_only=False)
    found = list(_differences(ckpt_a, ckpt_b, "checkpoint"))
    found += list(_differences(_records(before), _records(after), "metrics.jsonl"))
    return found


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    before, after = (Path(p) for p in argv)
    found = compare_runs(before, after)
    for line in found[:20]:
        print(line)
    n_params = sum(v.numel() for v in torch.load(_final_checkpoint(before), map_location="cpu",
                                                 weights_only=False)["model"].values())
    n_records = len(_records(before))
    if found:
        print(f"DIFFERENT: {len(found)} differences ({n_params} Gaussian parameter values, {n_records} records)")
        return 1
    print(f"IDENTICAL: {n_params} Gaussian parameter values, optimizer/strategy/RNG state and {n_records} "
          "metrics records (wall-clock fields left out)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
