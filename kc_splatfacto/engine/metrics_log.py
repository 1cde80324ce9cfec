"""Training records: ``metrics.jsonl`` (one JSON object a line) and a one-line progress bar.

Record schema (shared with kc-eval / kc-bench): every record has ``step`` (int), ``elapsed_s`` (wall clock since the
start of training, resumed runs continue the count), ``train_s`` (time in training steps only, evaluation and
checkpointing excluded), on train and eval records ``train_cpu_s`` (the CPU seconds of those steps,
all threads: other processes on the machine barely move it, where they stretch ``train_s``) and ``kind``:
- ``"train"``: the loss terms (``main_loss``, ``wavelet_loss``, ... and ``loss``, their sum), ``psnr`` of the training
  view, ``gaussian_count``, ``lr_means``, and on logging steps ``kurtosis_render`` / ``kurtosis_gt`` (per band).
- ``"eval"``: ``psnr``, ``ssim``, ``lpips`` and ``lpips_net`` (null with ``lpips_unavailable``), ``num_images``,
  ``split``, ``per_image`` (each view's ``psnr``, ``ssim``, ``lpips``), and at the last step ``lpips_vgg`` (the
  ``final_lpips_nets``; per view too).
- ``"gradient_shares"``: per loss term ``norm`` / ``share`` / ``top`` of its image gradient (engine/gradient_shares.py).
- ``"bad_step"``: a skipped step and ``reason``; ``"densify"``: what density control did; ``"checkpoint"``: ``path``.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path
from typing import Any, TextIO


def _jsonable(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None if math.isnan(value) else (1e308 if value > 0 else -1e308)
    if hasattr(value, "item") and getattr(value, "ndim", 1) == 0:
        return _jsonable(value.item())
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    return value


class MetricsWriter:
    """Appends records to ``metrics.jsonl``, flushed line by line (a crash loses at most the line being written)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = self.path.open("a")

    def write(self, record: dict[str, Any]) -> None:
        self._file.write(json.dumps(_jsonable(record), allow_nan=False) + "\n")
        self._file.flush()

    def close(self) -> None:
        self._file.close()


def read_metrics(path: str | Path) -> list[dict[str, Any]]:
    """Every record of a run's ``metrics.jsonl`` (one JSON object a line; blank lines ignored)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"metrics log {path} does not exist (a run folder holds metrics.jsonl once it trained)")
    records = []
    with path.open() as handle:
        for number, line in enumerate(handle, 1):
            if not line.strip():
                continue
            try:
                records.append(json.loads(line))
            except json.JSONDecodeError as exc:
                raise ValueError(f"{path}:{number}: not a JSON object ({exc}); the log may be truncated") from exc
    return records


class ProgressBar:
    """``[#####.....] 120/300 40% | 5.1 it/s | ETA 0:35 | loss 0.0812 | 12,034 GS`` on one rewritten stderr line."""

    WIDTH = 24

    def __init__(self, total: int, start: int = 0, enabled: bool = True, stream: TextIO | None = None):
        self.total, self.start = total, start
        self.enabled = enabled
        self.stream = stream or sys.stderr
        self._t0 = time.perf_counter()
        self._last_draw = 0.0

    def update(self, step: int, loss: float | None, gaussian_count: int, force: bool = False) -> None:
        if not self.enabled:
            return
        now = time.perf_counter()
        if not force and now - self._last_draw < 0.2:
            return
        self._last_draw = now
        done = step - self.start
        rate = done / max(now - self._t0, 1e-9)
        remaining = (self.total - step) / rate if rate > 0 else float("inf")
        frac = step / max(self.total, 1)
        filled = int(self.WIDTH * frac)
        eta = f"{int(remaining // 60)}:{int(remaining % 60):02d}" if math.isfinite(remaining) else "?"
        loss_text = f"{loss:.4f}" if loss is not None and math.isfinite(loss) else "nan"
        line = (
            f"\r[{'#' * filled}{'.' * (self.WIDTH - filled)}] {step}/{self.total} {100 * frac:3.0f}% | "
            f"{rate:.1f} it/s | ETA {eta} | loss {loss_text} | {gaussian_count:,} GS"
        )
        self.stream.write(line)
        self.stream.flush()

    def close(self) -> None:
        if self.enabled:
            self.stream.write("\n")
            self.stream.flush()
