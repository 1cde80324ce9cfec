"""Where a study's runs execute: one after another in this process (:class:`SerialRunner`), or as Ray tasks
(:class:`RayRunner`) on an embedded local cluster (``--workers N``) or an existing one (``--ray-address``).

Both call ``on_result(result)`` in this process as each run ends (in completion order; the study reorders for its
report) and print progress: finished / running / queued runs and an ETA. A run's failure is a result with status
``failed``, never an exception: the other runs go on. Ctrl-C stops the study: the serial runner lets the running
trainer save a checkpoint and stop; the Ray runner cancels its tasks (a running trainer is interrupted where it is,
its last periodic checkpoint is what ``--resume`` continues from). SIGTERM (``kill``, ``timeout``, a job scheduler)
stops a study as Ctrl-C does: ``ray.init`` installs a SIGTERM handler of its own that exits the driver at once, so the
Ray runner puts its own back once the cluster is up. Either way the runs already finished are intact and
:class:`StudyInterrupted` is raised after the results so far were handed over.

Threads: a Ray task asks for ``threads`` CPUs (``num_cpus``) and runs with ``OMP_NUM_THREADS`` and
``NUMBA_NUM_THREADS`` set to that number before torch and numba load; ``--device cuda`` tasks also ask for one GPU.
"""

from __future__ import annotations

import os
import socket
import sys
import time
from typing import Any, Callable, Sequence

from kc_splatfacto.engine.signals import current_stop_handlers, install_stop_handlers, restore_handlers
from kc_splatfacto.errors import UserError, import_optional
from kc_splatfacto.study.runs import RunSpec, execute_run, is_finished, write_returned_files

RAY_INSTALL = "pip install 'kc-splatfacto[cluster]'  (or: pip install 'ray>=2.9')"
ResultCallback = Callable[[dict[str, Any]], None]


class StudyInterrupted(KeyboardInterrupt):
    """Ctrl-C or SIGTERM stopped the study; the finished runs' results were handed over before this was raised."""


def _interrupt(signum, frame) -> None:  # noqa: ARG001
    raise KeyboardInterrupt


class RayUnavailableError(UserError, ImportError):
    """A Ray runner was asked for and Ray is not installed."""


def import_ray(why: str):
    """The ``ray`` module, or a one-line :class:`RayUnavailableError` saying how to install it."""
    try:
        return import_optional("ray", "ray", why, RAY_INSTALL)
    except UserError as exc:
        cause = exc.__cause__
        if isinstance(cause, ImportError) and cause.name == "ray":  # absent (a broken install keeps its own message)
            raise RayUnavailableError(f"{why} needs Ray, which is not installed: {RAY_INSTALL}") from cause
        raise


def format_duration(seconds: float | None) -> str:
    if seconds is None:
        return "?"
    seconds = int(round(seconds))
    hours, rest = divmod(seconds, 3600)
    return f"{hours}h{rest // 60:02d}m" if hours else f"{rest // 60}m{rest % 60:02d}s"


def recorded_wall(records: list[dict[str, Any]]) -> float | None:
    """The wall time a finished run's ``metrics.jsonl`` records: its last ``elapsed_s`` (training, evaluations and
    saves, over every resumption), or None when no record has one."""
    return next((float(r["elapsed_s"]) for r in reversed(records) if "elapsed_s" in r), None)


class Progress:
    """Counts and an ETA for a study of ``total`` runs with ``slots`` running at once.

    The ETA is the mean wall time of the runs that trained here times the runs left, divided by the slots; the first
    run's time includes kernel compilation, so the estimate settles after a few. Until a run has trained here (a
    study resumed with ``--resume``), the mean is that of the reused runs' recorded wall times: the same study's
    runs, timed where they trained, which is a better guess than none for the hour the first new run takes.
    ``to_reuse``: the runs already finished in their folders (``--resume``), which take no time, so are not left to do.
    """

    def __init__(self, total: int, slots: int, stream=None, to_reuse: int = 0):
        self.total, self.slots, self.to_reuse = total, max(1, slots), to_reuse
        self.finished = self.failed = self.running = self.reused = 0
        self.trained_walls: list[float] = []
        self.reused_walls: list[float] = []
        self.stream = stream or sys.stderr

    def started(self) -> None:
        self.running += 1

    def ended(self, result: dict[str, Any]) -> None:
        self.running = max(0, self.running - 1)
        self.finished += 1
        self.failed += result["status"] == "failed"
        self.reused += result["status"] == "reused"
        if result["status"] in ("trained", "resumed", "restarted"):
            self.trained_walls.append(result["wall_s"])
        elif result["status"] == "reused" and (wall := recorded_wall(result["records"])) is not None:
            self.reused_walls.append(wall)

    def eta(self) -> float | None:
        left = self.total - self.finished - max(0, self.to_reuse - self.reused)
        if left <= 0:
            return 0.0
        walls = self.trained_walls or self.reused_walls
        if not walls:
            return None
        return sum(walls) / len(walls) * left / self.slots

    def line(self) -> str:
        queued = self.total - self.finished - self.running
        failed = f" ({self.failed} failed)" if self.failed else ""
        eta = self.eta()
        source = " (from the reused runs' recorded times)" if eta and not self.trained_walls else ""
        return (f"[kc-bench] {self.finished}/{self.total} finished{failed}, {self.running} running, {queued} queued; "
                f"ETA {format_duration(eta)}{source}")

    def print(self) -> None:
        print(self.line(), file=self.stream, flush=True)


def count_finished(specs: Sequence[RunSpec]) -> int:
    """How many of ``specs`` already hold their final evaluation (``--resume`` reuses them as they are)."""
    return sum(is_finished(spec.run_dir, spec.max_steps) for spec in specs)


def describe(result: dict[str, Any], spec: RunSpec) -> str:
    """One line on a finished run: its status, time and final metrics, or its error and folder."""
    if result["status"] == "failed":
        return f"[kc-bench] FAILED {spec.name} (run folder {result['run_dir']}): {result['error']}"
    final: dict[str, Any] = next((r for r in reversed(result["records"]) if r.get("kind") == "eval"), {})
    return (f"[kc-bench] {spec.name}: {result['status']} in {result['wall_s']:.0f}s, final step {final.get('step')} "
            f"PSNR {final.get('psnr')} SSIM {final.get('ssim')} train_s {final.get('train_s')}")


class SerialRunner:
    """Every run in this process, one after another (the default: ``--workers 1``)."""

    def __init__(self, stream=None):
        self.stream = stream or sys.stderr

    def run(self, specs: Sequence[RunSpec], on_result: ResultCallback, *, resume: bool) -> None:
        progress = Progress(len(specs), 1, self.stream, to_reuse=count_finished(specs) if resume else 0)
        for spec in specs:
            progress.started()
            progress.print()
            result = execute_run(spec, resume=resume)
            progress.ended(result)
            print(describe(result, spec), flush=True)
            on_result(result)
            if result["status"] == "interrupted":  # Ctrl-C reached the trainer, which saved and stopped
                raise StudyInterrupted()
        progress.print()


def _ray_execute(spec: RunSpec, resume: bool, send_files: bool, progress_actor) -> dict[str, Any]:
    """The Ray task: tell the driver the run started, then run it."""
    if progress_actor is not None:
        progress_actor.started.remote(spec.index)
    return execute_run(spec, resume=resume, send_files=send_files)


RAY_CONNECT_TIMEOUT_S = 5.0
"""how long ``--ray-address`` may take to answer a TCP connection before the study stops (``ray.init`` itself retries
an address where nothing listens for minutes)"""


def check_reachable(address: str, timeout: float = RAY_CONNECT_TIMEOUT_S) -> None:
    """A one-line :class:`UserError` when nothing accepts a TCP connection at ``address`` (``HOST:PORT``, or
    ``ray://HOST:PORT``) within ``timeout`` seconds; other forms (``auto``) are left to Ray."""
    host, sep, port = address.split("://", 1)[-1].rpartition(":")
    if not sep or not port.isdigit():
        return
    try:
        socket.create_connection((host or "127.0.0.1", int(port)), timeout=timeout).close()
    except OSError as exc:
        raise UserError(f"--ray-address {address}: nothing answers there ({exc.strerror or exc}); start the cluster "
                        f"(`ray start --head --port={port}` on {host or 'this machine'}) or fix the address") from exc


def _authenticate_like_ray_start() -> None:
    """Use Ray's token authentication when a token is there (``~/.ray/auth_token``, ``RAY_AUTH_TOKEN``...) and
    ``RAY_AUTH_MODE`` does not decide: ``ray start`` turns it on in that case, but ``ray.init`` with an explicit
    address does not, so without this a driver is refused by a cluster that ``ray start`` began on the same machine
    (any earlier local Ray cluster leaves the token file behind)."""
    if os.environ.get("RAY_AUTH_MODE") is not None:
        return
    try:
        from ray._private.authentication.authentication_token_setup import maybe_enable_token_auth_if_token_available
    except ImportError:  # a Ray without token authentication
        return
    maybe_enable_token_auth_if_token_available(warn_if_disabled=False)


class RayRunner:
    """Every run as a Ray task.

    Args:
        workers: for an embedded local cluster (no ``address``), how many runs at once; it gets
            ``workers * threads`` CPUs.
        threads: CPUs (torch and numba threads) per run.
        address: an existing cluster's address (``ray start --head`` prints it; ``RAY_ADDRESS`` is the default),
            or None for an embedded local cluster.
        gpus_per_run: 1 for ``--device cuda``.
    """

    def __init__(self, *, workers: int, threads: int, address: str | None = None, gpus_per_run: float = 0,
                 stream=None):
        self.workers, self.threads, self.address, self.gpus = workers, threads, address, gpus_per_run
        self.stream = stream or sys.stderr
        self.ray = import_ray(f"--ray-address {address}" if address else f"--workers {workers}")

    def _env(self) -> dict[str, str]:
        env = {"OMP_NUM_THREADS": str(self.threads), "NUMBA_NUM_THREADS": str(self.threads)}
        for name in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT", "PYTHONPATH", "KC_SPLATFACTO_METHOD_CONFIGS",
                     "KC_SPLATFACTO_DATAPARSER_CONFIGS", "KC_SPLATFACTO_CACHE"):
            if os.environ.get(name):
                env[name] = os.environ[name]
        return env

    def _init(self) -> int:
        """Start or join the cluster; returns how many runs fit at once."""
        ray = self.ray
        runtime_env = {"env_vars": self._env()}
        if self.address:
            check_reachable(self.address)
            _authenticate_like_ray_start()
            ray.init(address=self.address, runtime_env=runtime_env, log_to_driver=False)
            cpus = int(ray.cluster_resources().get("CPU", 0))
            print(f"[kc-bench] Ray cluster at {self.address}: {cpus} CPUs, {self.threads} per run", file=self.stream,
                  flush=True)
            if cpus < self.threads:
                raise UserError(f"--ray-address {self.address}: the cluster has {cpus} CPUs, fewer than --threads "
                                f"{self.threads} per run; no run could start")
            return max(1, cpus // self.threads)
        # Ray runs its workers at niceness 15 by default (to keep the raylet responsive): a study's runs are the
        # machine's work, so they run at the driver's priority (a cluster's `ray start` decides for its own nodes)
        os.environ.setdefault("RAY_worker_niceness", "0")
        # address="local": always a new cluster of our own, never one a `ray start` left running on this machine
        ray.init(address="local", num_cpus=self.workers * self.threads, num_gpus=None if self.gpus else 0,
                 include_dashboard=False, runtime_env=runtime_env, log_to_driver=False)
        return self.workers

    def run(self, specs: Sequence[RunSpec], on_result: ResultCallback, *, resume: bool) -> None:
        ray = self.ray
        previous = current_stop_handlers()
        try:
            slots = self._init()
            install_stop_handlers(_interrupt)  # after ray.init, which routes SIGTERM to its own exit
            self._run(ray, specs, on_result, resume=resume, slots=slots)
        finally:
            ray.shutdown()
            restore_handlers(previous)  # the caller's handlers, not the ones ray.init left

    def _run(self, ray, specs: Sequence[RunSpec], on_result: ResultCallback, *, resume: bool, slots: int) -> None:
        @ray.remote
        class ProgressActor:
            def __init__(self):
                self.started_runs: set[int] = set()

            def started(self, index: int) -> None:
                self.started_runs.add(index)

            def count(self) -> int:
                return len(self.started_runs)

        actor = ProgressActor.options(num_cpus=0).remote()  # type: ignore[attr-defined]  # a ray.remote class
        task = ray.remote(_ray_execute).options(num_cpus=self.threads, num_gpus=self.gpus, max_retries=0)
        send_files = self.address is not None  # another machine may have run it
        by_ref = {task.remote(spec, resume, send_files, actor): spec for spec in specs}
        progress = Progress(len(specs), slots, self.stream, to_reuse=count_finished(specs) if resume else 0)
        pending = list(by_ref)
        last_print = 0.0
        try:
            while pending:
                done, pending = ray.wait(pending, num_returns=1, timeout=10.0)
                for ref in done:
                    spec = by_ref[ref]
                    try:
                        result = ray.get(ref)
                    except ray.exceptions.RayError as exc:  # the worker died (out of memory, killed)
                        result = {"index": spec.index, "status": "failed", "run_dir": str(spec.run_dir),
                                  "records": [], "wall_s": 0.0, "error": f"{type(exc).__name__}: {exc}"}
                    if result.get("files") and result["status"] != "failed":
                        write_returned_files(spec.run_dir, result["files"])
                    progress.ended(result)
                    print(describe(result, spec), flush=True)
                    on_result(result)
                started = ray.get(actor.count.remote())
                progress.running = max(0, started - progress.finished)
                if done or time.monotonic() - last_print > 60:
                    progress.print()
                    last_print = time.monotonic()
        except KeyboardInterrupt:
            print(f"[kc-bench] interrupted: cancelling {len(pending)} unfinished runs; the {progress.finished} "
                  f"finished ones are kept (continue with --resume)", file=self.stream, flush=True)
            for ref in pending:
                ray.cancel(ref)
            raise StudyInterrupted() from None
