"""Hooks into the training loop: nerfstudio's ``TrainingCallback``, plus record sinks.

The trainer knows nothing of viewers or logging services. What watches a run registers with
:meth:`Trainer.add_callbacks`:

- a :class:`TrainingCallback` runs ``func(step, *args, **kwargs)`` at its locations (before or after a training
  iteration, every ``update_every_num_iters`` steps or at ``iters``), as nerfstudio's does; ``step`` after an
  iteration is the number of steps completed;
- a :class:`RecordSink` receives every record the trainer writes to ``metrics.jsonl`` (the record stays the run's
  one source of truth; tensorboard and wandb mirror it) and is closed when training ends.

A callback must leave the training state alone (parameters, optimizer state, RNG streams): a run with a viewer or a
logger attached trains bit-identically to one without.
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any


class TrainingCallbackLocation(enum.Enum):
    """Where in the loop a :class:`TrainingCallback` runs (nerfstudio's names)."""

    BEFORE_TRAIN_ITERATION = enum.auto()
    AFTER_TRAIN_ITERATION = enum.auto()


@dataclass
class TrainingCallback:
    """``func(step, *args, **kwargs)`` at ``where_to_run``, every ``update_every_num_iters`` steps, or at ``iters``
    (at most one of the two; neither: every step)."""

    where_to_run: Sequence[TrainingCallbackLocation]
    func: Callable[..., Any]
    update_every_num_iters: int | None = None
    iters: tuple[int, ...] | None = None
    args: tuple[Any, ...] = ()
    kwargs: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.update_every_num_iters is not None and self.iters is not None:
            raise ValueError("TrainingCallback: give update_every_num_iters or iters, not both")
        if self.update_every_num_iters is not None and self.update_every_num_iters < 1:
            raise ValueError(f"TrainingCallback: update_every_num_iters must be >= 1, got {self.update_every_num_iters}")

    def run_callback(self, step: int) -> None:
        if self.update_every_num_iters is not None and step % self.update_every_num_iters != 0:
            return
        if self.iters is not None and step not in self.iters:
            return
        self.func(step, *self.args, **self.kwargs)

    def run_callback_at_location(self, step: int, location: TrainingCallbackLocation) -> None:
        if location in self.where_to_run:
            self.run_callback(step)


class RecordSink:
    """Receives each ``metrics.jsonl`` record as it is written; ``close`` at the end of training."""

    def write(self, record: dict[str, Any]) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def close(self) -> None:
        pass


def run_callbacks(callbacks: Iterable[TrainingCallback], step: int, location: TrainingCallbackLocation) -> None:
    for callback in callbacks:
        callback.run_callback_at_location(step, location)
