"""Training records: ``metrics.jsonl`` (one JSON object a line) and the progress bar.

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
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TextIO

from tqdm import tqdm

from kc_splatfacto.errors import UserError

POSTFIX_EVERY = 10
"""steps between two updates of the terminal bar's text (rate, ETA, loss)"""


def _value(loss: float | Callable[[], float | None] | None) -> float | None:
    return loss() if callable(loss) else loss


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


class LoggingFailedError(UserError, OSError):
    """Writing the run's records failed (``metrics.jsonl`` or a logging backend): the run stopped with a checkpoint."""


class MetricsWriter:
    """Appends records to ``metrics.jsonl``, flushed line by line (a crash loses at most the line being written),
    then hands each to the ``sinks`` (tensorboard, wandb, a viewer: objects with ``write(record)`` and ``close()``)
    as the JSON holds it.

    A failure to write (the file made unwritable, a disk full, a backend raising) does not raise in the middle of a
    training step: the first one is kept in ``failure`` and writing stops; the trainer checks it after each step,
    saves a checkpoint and stops with one line (``LoggingFailedError``)."""

    def __init__(self, path: Path, sinks: Sequence[Any] = ()):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._file = self.path.open("a")
        except OSError as exc:  # before the first step: nothing to save yet, a line naming the file is enough
            raise UserError(f"cannot append to the run's log {self.path} ({exc.strerror or exc}): make it a writable "
                            "file and run the command again") from exc
        self.sinks = list(sinks)
        self.failure: str | None = None

    def write(self, record: dict[str, Any]) -> None:
        if self.failure is not None:
            return
        record = _jsonable(record)
        try:
            self._file.write(json.dumps(record, allow_nan=False) + "\n")
            self._file.flush()
        except OSError as exc:
            self.failure = f"writing {self.path} failed ({exc.strerror or exc})"
            return
        for sink in self.sinks:
            try:
                sink.write(record)
            except Exception as exc:  # any backend's error: the run must stop with its state saved, not crash
                self.failure = f"the logging backend {type(sink).__name__} failed ({type(exc).__name__}: {exc})"
                return

    def close(self) -> None:
        for closing in (self._file, *self.sinks):
            try:
                closing.close()
            except Exception as exc:  # after a failure, or a backend failing at its end: said, never masking
                self.failure = self.failure or f"closing {type(closing).__name__} failed ({type(exc).__name__}: {exc})"


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


#: steps whose time the ETA leaves out: the first steps compile the numba kernels (seconds each, then milliseconds)
ETA_WARMUP_STEPS = 5


def format_duration(seconds: float) -> str:
    """``1:02:03`` / ``2:03`` for finite ``seconds``, ``?`` otherwise."""
    if not math.isfinite(seconds):
        return "?"
    seconds = int(round(seconds))
    hours, rest = divmod(seconds, 3600)
    return f"{hours}:{rest // 60:02d}:{rest % 60:02d}" if hours else f"{rest // 60}:{rest % 60:02d}"


class ProgressBar:
    """Training progress on ``stream`` (stderr): a tqdm bar when it is a terminal, otherwise one plain line every
    ``line_every`` steps (a log file or CI gets no carriage-return redraws).

    The rate and ETA are measured from the ``ETA_WARMUP_STEPS``-th step of this session on, so the compilation of
    the first steps does not inflate the estimate; before then the ETA is ``?``.
    """

    def __init__(self, total: int, start: int = 0, enabled: bool = True, stream: TextIO | None = None,
                 line_every: int = 100, interactive: bool | None = None):
        self.total, self.start = total, start
        self.enabled = enabled
        self.stream = stream or sys.stderr
        self.line_every = max(int(line_every), 1)
        if interactive is None:
            isatty = getattr(self.stream, "isatty", None)
            interactive = bool(isatty and isatty())
        self.interactive = interactive
        self._warm: tuple[int, float] | None = None  # (step, time) once the warm-up steps are done
        self._last_line_step = self._last_postfix_step = start
        self._bar = None
        if enabled and interactive:

            self._bar = tqdm(total=total, initial=start, file=self.stream, dynamic_ncols=True, mininterval=0.2,
                             bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} [{elapsed}{postfix}]")

    def rate_and_eta(self, step: int, now: float | None = None) -> tuple[float, float]:
        """(steps per second, seconds left) measured since the warm-up steps; NaN and inf before then."""
        now = time.perf_counter() if now is None else now
        if self._warm is None:
            if step - self.start >= ETA_WARMUP_STEPS:
                self._warm = (step, now)
            return math.nan, math.inf
        steps, seconds = step - self._warm[0], now - self._warm[1]
        if steps <= 0 or seconds <= 0:
            return math.nan, math.inf
        rate = steps / seconds
        return rate, (self.total - step) / rate

    def describe(self, step: int, loss: float | None, gaussian_count: int) -> str:
        rate, eta = self.rate_and_eta(step)
        rate_text = f"{rate:.2f} it/s" if math.isfinite(rate) else "? it/s"
        loss_text = f"{loss:.4f}" if loss is not None and math.isfinite(loss) else "nan"
        return f"{rate_text}, ETA {format_duration(eta)}, loss {loss_text}, {gaussian_count:,} GS"

    def update(self, step: int, loss: float | Callable[[], float | None] | None, gaussian_count: int,
               force: bool = False) -> None:
        """``loss``: the value, or a function giving it, called only when the bar shows it (every
        ``POSTFIX_EVERY`` steps on a terminal, on each line otherwise): reading a loss from a GPU is a host
        synchronisation, which a training step should not pay for a display."""
        if not self.enabled:
            return
        if self._bar is not None:
            if force or step - self._last_postfix_step >= POSTFIX_EVERY:
                self._last_postfix_step = step
                self._bar.set_postfix_str(self.describe(step, _value(loss), gaussian_count), refresh=False)
            else:
                self.rate_and_eta(step)  # the ETA's warm-up point is taken at its step all the same
            self._bar.update(step - self._bar.n)
            if force:
                self._bar.refresh()
            return
        if step == self._last_line_step:  # the closing update of a step already reported
            return
        if force or step - self._last_line_step >= self.line_every or step == self.total:
            self._last_line_step = step
            text = self.describe(step, _value(loss), gaussian_count)
            self.stream.write(f"step {step}/{self.total} ({100 * step / max(self.total, 1):.0f}%): {text}\n")
            self.stream.flush()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None
