"""A run's memory: what it may use (its budget), what its Gaussians will cost, and growth stopped at the budget.

Nothing else bounds a run's memory but ``max_num_gaussians``: a scene at a higher resolution grows until the
operating system kills the process (no checkpoint since the last periodic one, no message). So:

- at start (:meth:`MemoryGuard.start`), the run's budget is ``machine.memory_budget_gb``, or
  :data:`BUDGET_FRACTION` of what the process may use (its RSS plus the memory available to it: the smaller of the
  system's ``MemAvailable`` and its cgroup's limit; on CUDA the GPU's free memory plus what torch holds); when the cap
  ``max_num_gaussians`` at :func:`bytes_per_gaussian` would not fit in it, one warning line names the numbers and the
  remedies;
- after each density-control step that changed the count (:meth:`MemoryGuard.after_density_control`), the peak memory
  since the previous check plus what the new Gaussians will cost is compared with the budget; past it, the model's
  growth is capped at its current count (the training state's ``cap_gaussians``) and one line says so, with the numbers and the
  remedies. The run then trains on at that count and ends with its checkpoint, instead of being killed.

:func:`bytes_per_gaussian` and :data:`STEP_BYTES_PER_PIXEL` come from ``benchmarks/bench_memory.py`` (the table in
docs/performance.md): the slope of a CPU training's peak RSS against the number of Gaussians at two image sizes, and
the rise of its intercept with the pixel count.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import torch

BUDGET_FRACTION = 0.85
"""the share of the memory a process may use that a run takes as its budget when ``memory_budget_gb`` is 0 (the
rest is headroom for evaluation, LPIPS networks and the estimate's error)"""

#: peak bytes per Gaussian of a CPU training step (kc-splatfacto, benchmarks/bench_memory.py, docs/performance.md):
#: the slope of the peak RSS against the number of Gaussians, 1,246 at 320x240 and 1,184 at 960x720 (the same within
#: the measurement's noise: a Gaussian's parameters, gradients, Adam moments and projection buffers do not depend on
#: the image), rounded up
BYTES_PER_GAUSSIAN = 1_300
#: a training step's buffers per pixel of its image (render, loss maps, wavelet bands and their gradients): the rise of
#: the peak at N = 0 from 320x240 to 960x720 (626 MB to 1,044 MB over 614,400 more pixels), rounded up
STEP_BYTES_PER_PIXEL = 700
REMEDIES = ("lower --pipeline.model.max-num-gaussians to what fits, use --pipeline.model.strategy mcmc (a fixed "
            "count), or a larger --downscale-factor (fewer bytes per Gaussian)")


def bytes_per_gaussian(pixels: int) -> float:  # noqa: ARG001  (measured alike at both image sizes)
    """Peak bytes one Gaussian costs a training step on images of ``pixels`` pixels."""
    return float(BYTES_PER_GAUSSIAN)


def current_rss_bytes() -> int:
    """This process's resident memory now (Linux: /proc/self/statm; elsewhere its peak so far)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return _peak_rss_bytes()


def _peak_rss_bytes() -> int:
    try:
        import resource  # POSIX only
    except ImportError:
        return 0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(peak if sys.platform == "darwin" else peak * 1024)  # bytes on macOS, kilobytes on Linux


def _proc_bytes(path: str, key: str) -> int | None:
    """The ``key: <n> kB`` line of a /proc file in bytes, or None where the file or the line is missing."""
    try:
        for line in Path(path).read_text().splitlines():
            if line.startswith(f"{key}:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def peak_rss_since_reset() -> int:
    """The resident peak since :func:`reset_peak_rss` (Linux: VmHWM; elsewhere the process's peak)."""
    peak = _proc_bytes("/proc/self/status", "VmHWM")
    return peak if peak is not None else _peak_rss_bytes()


def reset_peak_rss() -> None:
    """Start a new resident peak (Linux: ``5`` to /proc/self/clear_refs); where that fails the peak stays the
    process's, which only makes the guard earlier."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass


def _meminfo_available() -> int | None:
    return _proc_bytes("/proc/meminfo", "MemAvailable")


def _cgroup_room() -> int | None:
    """What the process's cgroup (v2, else v1) still allows: its limit minus its usage; None without a limit."""
    for limit_file, usage_file in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                                   ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
                                    "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        try:
            limit_text = Path(limit_file).read_text().strip()
            if limit_text == "max" or int(limit_text) >= 1 << 60:
                return None
            return max(int(limit_text) - int(Path(usage_file).read_text().strip()), 0)
        except (OSError, ValueError):
            continue
    return None


def cpu_memory_it_may_use() -> int | None:
    """The process's RSS plus the memory still available to it (system and cgroup); None when unknown."""
    rooms = [room for room in (_meminfo_available(), _cgroup_room()) if room is not None]
    return current_rss_bytes() + min(rooms) if rooms else None


@dataclass
class MemoryGuard:
    """The budget of a run on ``device`` and the count its growth is capped at (None: not capped)."""

    device: torch.device
    budget: int | None
    pixels: int
    cap: int | None = None
    last_count: int = 0
    announce: Callable[[str], Any] = print

    @classmethod
    def start(cls, device: torch.device, budget_gb: float, max_gaussians: int | None, count: int, pixels: int,
              announce: Callable[[str], Any] = print) -> MemoryGuard:
        """The guard of a run whose model holds ``count`` Gaussians, capped at ``max_gaussians``, on training images
        of ``pixels`` pixels (the largest); one warning line when the cap would not fit in the budget."""
        if budget_gb > 0:
            budget: int | None = int(budget_gb * 1e9)
            source = f"--machine.memory-budget-gb {budget_gb:g}"
        else:
            total = _device_memory_it_may_use(device)
            budget = int(total * BUDGET_FRACTION) if total is not None else None
            source = f"{BUDGET_FRACTION:.0%} of the {_gb(total)} GB this process may use" if total else ""
        guard = cls(device=device, budget=budget, pixels=pixels, last_count=count, announce=announce)
        if budget is not None and max_gaussians is not None:
            start = guard.usage() + STEP_BYTES_PER_PIXEL * pixels  # what the run holds, and a step's image buffers
            need = start + bytes_per_gaussian(pixels) * max(max_gaussians - count, 0)
            if need > budget:
                room = budget - start
                fits = (f"about {count + int(room / bytes_per_gaussian(pixels)):,} fit" if room > 0 else
                        f"the run needs {_gb(start)} GB before it adds any, so none are added")
                announce(f"--pipeline.model.max-num-gaussians {max_gaussians:,} would need about "
                         f"{_gb(need)} GB on {_where(device)} at {pixels:,} pixels per image, more than the memory "
                         f"budget of {_gb(budget)} GB ({source}); {fits}: growth will stop at the budget. "
                         f"To choose where it stops: {REMEDIES}")
        reset_peak(device)
        return guard

    def usage(self) -> int:
        """Memory the run holds now (RSS, or what torch holds on the GPU)."""
        if self.device.type == "cuda":
            return int(torch.cuda.memory_reserved(self.device))
        return current_rss_bytes()

    def peak(self) -> int:
        if self.device.type == "cuda":
            return int(torch.cuda.max_memory_reserved(self.device))
        return max(peak_rss_since_reset(), current_rss_bytes())

    def after_density_control(self, step: int, count: int, cap_gaussians: Callable[[int], None]) -> str | None:
        """After a density-control step left ``count`` Gaussians: when the peak since the last check plus what the
        new ones add passes the budget, cap growth at ``count`` (``cap_gaussians``) and return the line said."""
        grew = count - self.last_count
        self.last_count = count
        if self.budget is None or self.cap is not None or grew <= 0:
            return None
        projected = self.peak() + bytes_per_gaussian(self.pixels) * grew
        reset_peak(self.device)
        if projected <= self.budget:
            return None
        self.cap = count
        cap_gaussians(count)
        line = (f"memory budget reached at step {step}: {count:,} Gaussians need about {_gb(projected)} GB on "
                f"{_where(self.device)} of a budget of {_gb(self.budget)} GB; density control adds no more Gaussians "
                f"(training goes on at this count). Next time: {REMEDIES}; or give the run more memory "
                "(--machine.memory-budget-gb)")
        self.announce(line)
        return line


def reset_peak(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    else:
        reset_peak_rss()


def _device_memory_it_may_use(device: torch.device) -> int | None:
    if device.type == "cuda":
        free, _total = torch.cuda.mem_get_info(device)
        return int(free + torch.cuda.memory_reserved(device))
    return cpu_memory_it_may_use()


def _where(device: torch.device) -> str:
    return "the GPU" if device.type == "cuda" else "the CPU (RAM)"


def _gb(value: float | None) -> str:
    return "?" if value is None else f"{value / 1e9:.2f}"


__all__ = ["BUDGET_FRACTION", "BYTES_PER_GAUSSIAN", "STEP_BYTES_PER_PIXEL", "MemoryGuard", "bytes_per_gaussian", "cpu_memory_it_may_use", "current_rss_bytes",
           "peak_rss_since_reset", "reset_peak_rss"]
