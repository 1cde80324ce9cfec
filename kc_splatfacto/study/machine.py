"""Which machine a run trained on, recorded in its folder (``machine.json``), so a study can tell when the two runs
of a pair rounded differently.

numba compiles the CPU kernels for the host processor (LLVM's name for it and its vector features), so the same code
and seed give bit-identical training only on the same kind of CPU (``docs/training.md``: three kinds seen here, two
of them named "AMD EPYC"). A run whose training spans sessions may also span machines, so ``machine.json`` holds one
entry per stretch of training, each with the step it started from.
"""

from __future__ import annotations

import json
import platform
import time
from pathlib import Path
from typing import Any

import llvmlite
import llvmlite.binding as llvm
import numba
import torch

from kc_splatfacto.atomic import atomic_write_text

MACHINE_FILE = "machine.json"
#: LLVM feature flags that change the compiled kernels' rounding (vector width, fused multiply-add), widest first
VECTOR_FEATURES = ("avx512f", "avx2", "fma", "neon", "sve")


def cpu_model_name(cpuinfo: str | None = None) -> str:
    """The processor's marketing name: the first ``model name`` of ``/proc/cpuinfo`` (``cpuinfo`` its text, for
    tests), else :func:`platform.processor`, else ``"unknown"``."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            cpuinfo = ""
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "model name" and value.strip():
            return value.strip()
    return platform.processor() or "unknown"


def cpu_kind(llvm_cpu: str, features: dict[str, bool]) -> str:
    """What decides the kernels' rounding, as one comparable string: LLVM's host CPU name and the vector features
    it has, e.g. ``"znver5 avx512f avx2 fma"``. Two runs of one seed and code train bit-identically only when their
    kinds are equal (the converse is not promised: an AVX-512 Xeon and an AVX-512 EPYC gave one Splatfacto hash)."""
    present = [name for name in VECTOR_FEATURES if features.get(name)]
    return " ".join([llvm_cpu or "unknown", *present])


def machine_signature() -> dict[str, Any]:
    """This machine as a run records it: ``kind`` (:func:`cpu_kind`), ``llvm_cpu``, ``cpu_model``, ``arch`` and
    the versions of the compilers and libraries that shape the numbers (numba, llvmlite, torch)."""
    llvm_cpu = llvm.get_host_cpu_name()
    features = {name: bool(value) for name, value in llvm.get_host_cpu_features().items()}
    return {
        "kind": cpu_kind(llvm_cpu, features),
        "llvm_cpu": llvm_cpu,
        "cpu_model": cpu_model_name(),
        "arch": platform.machine(),
        "numba": numba.__version__,
        "llvmlite": llvmlite.__version__,
        "torch": torch.__version__,
    }


def read_machines(run_dir: str | Path) -> list[dict[str, Any]]:
    """The entries of ``run_dir``'s ``machine.json`` (oldest first); empty when the run recorded none (runs made
    before this file existed)."""
    path = Path(run_dir) / MACHINE_FILE
    if not path.is_file():
        return []
    try:
        entries = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not JSON ({exc}); delete it or restore it from git") from exc
    if not isinstance(entries, list) or not all(isinstance(e, dict) and "kind" in e for e in entries):
        raise ValueError(f"{path}: expected a list of entries with a 'kind', got {entries!r:.200}")
    return entries


def record_machine(run_dir: str | Path, from_step: int, threads: int, signature: dict[str, Any] | None = None) -> Path:
    """Add this machine to ``run_dir``'s ``machine.json`` as the one training from ``from_step`` with ``threads``
    threads (atomic). A run trained from step 0 starts a new list: entries of an earlier, abandoned attempt go."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    entries = read_machines(run_dir) if from_step > 0 else []
    entries = [e for e in entries if int(e.get("from_step", 0)) < from_step]  # a stretch redone from a checkpoint
    entry = {"from_step": int(from_step), "threads": int(threads),
             "started_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
             **(signature if signature is not None else machine_signature())}
    path = run_dir / MACHINE_FILE
    atomic_write_text(path, json.dumps(entries + [entry], indent=1) + "\n")
    return path


def machine_kinds(entries: list[dict[str, Any]]) -> str:
    """The distinct CPU kinds of a run's entries, in order, joined by ``" + "`` (``""`` when none is recorded)."""
    return " + ".join(dict.fromkeys(str(e["kind"]) for e in entries))
