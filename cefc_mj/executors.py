"""Where independent jobs run: in this process, on a local process pool, or as Ray tasks on a cluster.

`map_unordered(fn, items, executor)` calls the picklable, module-level `fn` on every item and yields
(item, result) as each finishes. Table VIII grids (`cefc_mj.eval.table8.run_grid`) and multi-seed
training sweeps (`cefc_mj.train.sweep`) use it, so both run the same way on either executor:

    local   a process pool of `workers` processes on this machine (1: one after another, in this process),
            started with "spawn": fresh interpreters, never a fork of a process whose threads (torch's,
            numba's, ZeroMQ's, tqdm's monitor) may hold a lock the child would then wait on forever;
            a pool whose workers use no CPU for `STALL_TIMEOUT_S` while jobs are pending ends the
            map with `WorkersStalled` (one line), not a hang
    ray     one Ray task per item: on the cluster whose head is at `address`, or, without an address,
            on a Ray instance started here (bound to 127.0.0.1, `workers` CPUs, no dashboard, no usage
            statistics) and shut down when the map ends, also on Ctrl-C or an error

Ray is an optional dependency (`pip install cefc-mj[ray]`), imported only when a Ray map starts.
docs/scaling.md explains clusters.
"""

from __future__ import annotations

import importlib.util
import logging
import multiprocessing
import os
import re
import socket
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

from cefc_mj.errors import CefcError, ConfigError

EXECUTORS = ("local", "ray")
"""The executor kinds."""
RAY_MISSING = "--executor ray needs the ray extra: pip install cefc-mj[ray]"
"""The one-line error when Ray is asked for but not installed."""
LOCAL_HOST = "127.0.0.1"
"""The only address a Ray instance started here listens on."""
FORWARDED_ENV = ("MKL_CBWR",)
"""Variables of this process that Ray workers on other machines get too: they change the numbers
(docs/reproduce.md). A Ray instance started here passes its whole environment on anyway."""

CONNECT_TIMEOUT_S = 10.0
"""How long to wait for the head's port to accept a connection before giving up on --address."""

POOL_START_METHOD = "spawn"
"""How the local pool starts its workers. A fork after the parent has started threads (a torch
module run, a numba kernel, a ZeroMQ context, a progress bar's monitor) can copy a lock held by a
thread that does not exist in the child, which then waits on it forever; a spawned worker is a
fresh interpreter (it loads the compiled kernels from the disk cache, about a second)."""
STALL_TIMEOUT_S = 300.0
"""A local pool whose worker processes together use no CPU time for this long while jobs are pending
is stalled (a deadlock, a stopped process): the map ends with `WorkersStalled`."""
STALL_POLL_S = 5.0
"""How often the local pool's progress is checked."""


class WorkersStalled(CefcError, RuntimeError):
    """The local pool's workers made no progress (no CPU time) for `STALL_TIMEOUT_S` with jobs pending."""


_ADDRESS = re.compile(r"^(?P<host>[A-Za-z0-9_.-]+):(?P<port>[0-9]{1,5})$")


def parse_address(text: str) -> tuple[str, int]:
    """(host, port) of a Ray head address 'HOST:PORT' (a host name or IPv4 address); ConfigError otherwise."""
    match = _ADDRESS.match(text.strip()) if isinstance(text, str) else None
    if match is None or not 1 <= int(match["port"]) <= 65535:
        raise ConfigError(f"--address {text}: expected HOST:PORT of a Ray head, e.g. 10.0.0.1:6379")
    return match["host"], int(match["port"])


def ray_available() -> bool:
    """Whether Ray is installed (without importing it, which takes about a second)."""
    try:
        return importlib.util.find_spec("ray") is not None
    except (ImportError, ValueError):  # a broken or stubbed-out installation
        return False


def usable_cpus() -> int:
    """The CPUs this process may run on (its affinity mask where the OS has one, else the machine's)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return os.cpu_count() or 1


@dataclass(frozen=True)
class ExecutorConfig:
    """How `map_unordered` runs its jobs."""

    kind: str = "local"
    """"local" (this machine's processes) or "ray" (Ray tasks)."""
    workers: int = 1
    """local: processes of the pool (1: the jobs run one after another in this process). ray without
    `address`: CPUs of the Ray instance started here. Unused with an address: the cluster's CPUs
    decide how many jobs run at once."""
    address: str | None = None
    """ray: HOST:PORT of a running cluster's head (`ray start --head --port ...`); None starts a
    local Ray instance for the map and shuts it down afterwards."""

    def validate(self) -> None:
        """One-line ConfigError naming the flag, before any work: unknown kind, bad worker count, an
        address without Ray or a malformed one, Ray not installed."""
        if self.kind not in EXECUTORS:
            raise ConfigError(f"--executor {self.kind}: must be one of {', '.join(EXECUTORS)}")
        if not isinstance(self.workers, int) or isinstance(self.workers, bool) or self.workers < 1:
            raise ConfigError(f"--workers {self.workers}: must be an integer >= 1")
        if self.address is not None:
            if self.kind != "ray":
                raise ConfigError(f"--address {self.address}: connects to a Ray cluster; add --executor ray")
            parse_address(self.address)
        if self.kind == "ray" and not ray_available():
            raise ConfigError(RAY_MISSING)

    def describe(self) -> str:
        """Where the jobs run, for a status line."""
        if self.kind == "local":
            return "in this process" if self.workers == 1 else f"on {self.workers} local processes"
        if self.address is not None:
            return f"on the Ray cluster at {self.address}"
        return f"on a local Ray instance with {self.workers} CPU(s)"


def check_reachable(address: str, timeout_s: float = CONNECT_TIMEOUT_S) -> None:
    """ConfigError unless something accepts TCP connections at HOST:PORT: Ray itself retries an
    address where nothing listens for minutes."""
    host, port = parse_address(address)
    try:
        socket.create_connection((host, port), timeout=timeout_s).close()
    except OSError as e:
        raise ConfigError(
            f"--address {address}: no Ray head answers there ({e.strerror or e}); "
            "is `ray start --head` running on that machine and port?"
        ) from None


def import_ray():
    """The ray module, or ConfigError(RAY_MISSING)."""
    try:
        import ray
    except ImportError:
        raise ConfigError(RAY_MISSING) from None
    return ray


@contextmanager
def ray_session(executor: ExecutorConfig):
    """Ray, connected for the duration of the block. Connects to `executor.address`, or starts a
    local instance bound to 127.0.0.1 and shuts it down when the block ends (normally, on an error
    or on Ctrl-C), so no Ray process outlives the command. A connection made by the caller before
    (ray.is_initialized()) is used as it is and left open."""
    ray = import_ray()
    if ray.is_initialized():
        yield ray
        return
    env = {name: os.environ[name] for name in FORWARDED_ENV if name in os.environ}
    quiet = {"logging_level": logging.WARNING, "runtime_env": {"env_vars": env} if env else None}
    if executor.address is None:
        os.environ["RAY_USAGE_STATS_ENABLED"] = "0"  # no usage statistics leave the machine
    else:
        check_reachable(executor.address)
    try:
        if executor.address is not None:
            ray.init(address=executor.address, **quiet)
        else:
            ray.init(
                address="local",
                num_cpus=executor.workers,
                include_dashboard=False,
                _node_ip_address=LOCAL_HOST,
                **quiet,
            )
    except BaseException as e:  # Ctrl-C or a failure half-way: stop what has started, disconnect
        ray.shutdown()
        if isinstance(e, ConnectionError):
            raise ConfigError(
                f"--address {executor.address}: no Ray cluster answers there, or it asks for a token "
                "this machine lacks (RAY_AUTH_MODE=token and the token: docs/scaling.md)"
            ) from None
        raise
    try:
        yield ray
    finally:
        ray.shutdown()  # a local instance: its GCS, raylet and workers end here


def map_unordered(
    fn: Callable[[Any], Any],
    items: Sequence,
    executor: ExecutorConfig | None = None,
    mp_context=None,
    ray_options: dict | None = None,
    stall_timeout_s: float | None = STALL_TIMEOUT_S,
) -> Iterator[tuple[Any, Any]]:
    """Yield (item, fn(item)) for every item, in completion order.

    `fn` must be a module-level function (the local pool also takes a functools.partial of one), and
    the items and results must pickle. An exception of `fn` is raised here as it was raised there (Ray's
    wrapper removed), after the jobs not yet finished are cancelled. Closing the generator early (a
    break, an error or Ctrl-C in the caller) cancels the rest too: the local pool waits for the jobs
    already running; Ray stops its running tasks, and a Ray instance started here is shut down.
    `mp_context`: the multiprocessing context of the local pool (default: POOL_START_METHOD).
    `ray_options`: `ray.remote` options of each task (default one CPU each).
    `stall_timeout_s`: the local pool's stall limit (default STALL_TIMEOUT_S; None: no limit).
    """
    executor = executor or ExecutorConfig()
    items = list(items)
    if executor.kind == "ray":
        yield from _map_ray(fn, items, executor, ray_options or {"num_cpus": 1})
    elif executor.workers <= 1 or len(items) <= 1:
        for item in items:
            yield item, fn(item)
    else:
        context = mp_context or multiprocessing.get_context(POOL_START_METHOD)
        tracker_was_running = resource_tracker_running()
        pool = ProcessPoolExecutor(
            max_workers=min(executor.workers, len(items)), mp_context=context, initializer=_one_thread_per_worker
        )
        try:
            futures = {pool.submit(fn, item): item for item in items}
            pending = set(futures)
            watch = _ProgressWatch(pool, stall_timeout_s)
            while pending:
                done, pending = wait(pending, timeout=STALL_POLL_S, return_when=FIRST_COMPLETED)
                for future in done:
                    yield futures[future], future.result()
                if done:
                    watch.progressed()
                else:
                    watch.check(len(pending))
        except WorkersStalled:
            _kill_workers(pool)
            raise
        finally:
            pool.shutdown(wait=True, cancel_futures=True)
            if not tracker_was_running:
                stop_resource_tracker()


WORKER_THREAD_VARIABLES = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")
"""Set to 1 in each local pool worker (unless the user set them): W workers that each start a thread
per core (torch's OpenMP pool) oversubscribe the cores and spin against each other. Measured with
Table V's 98 jobs on 2 cores: 122 s with 2 workers against 38 s with 1, and 27 s with 2 workers of
one thread each."""


def _one_thread_per_worker() -> None:
    """The local pool's initializer, in each worker before its first job. A spawned worker has often
    imported torch already (it re-imports the command's main module), so torch is told directly."""
    for name in WORKER_THREAD_VARIABLES:
        os.environ.setdefault(name, "1")
    if "torch" in sys.modules and os.environ["OMP_NUM_THREADS"] == "1":
        sys.modules["torch"].set_num_threads(1)


def resource_tracker_running() -> bool:
    from multiprocessing import resource_tracker

    return getattr(resource_tracker._resource_tracker, "_fd", None) is not None


def stop_resource_tracker() -> None:
    """Stop the resource-tracker process a spawned pool starts (it watches the pool's semaphores, which
    are gone once the pool is shut down), so that the map leaves no process of its own behind; the
    next pool starts a new one."""
    from multiprocessing import resource_tracker

    try:
        resource_tracker._resource_tracker._stop()  # (private, in CPython since 3.8)
    except (AttributeError, OSError, ChildProcessError):
        pass


class _ProgressWatch:
    """Whether a local pool's workers still use CPU time (Linux /proc; elsewhere psutil if installed,
    otherwise no watch): a deadlocked or stopped worker uses none."""

    def __init__(self, pool: ProcessPoolExecutor, timeout_s: float | None):
        self.pool, self.timeout_s = pool, timeout_s
        self.cpu_s = self._cpu_seconds()
        self.since = time.monotonic()

    def _cpu_seconds(self) -> float | None:
        processes = getattr(self.pool, "_processes", None) or {}  # (no public accessor)
        total = 0.0
        for pid in list(processes):
            seconds = _process_cpu_seconds(pid)
            if seconds is None:
                return None
            total += seconds
        return total

    def progressed(self) -> None:
        self.cpu_s, self.since = self._cpu_seconds(), time.monotonic()

    def check(self, pending: int) -> None:
        if self.timeout_s is None:
            return
        cpu_s = self._cpu_seconds()
        if cpu_s is None or self.cpu_s is None or cpu_s - self.cpu_s > 0.05:
            self.cpu_s, self.since = cpu_s, time.monotonic()
            return
        idle = time.monotonic() - self.since
        if idle >= self.timeout_s:
            raise WorkersStalled(
                f"the {len(getattr(self.pool, '_processes', None) or {})} worker processes used no CPU for "
                f"{idle:.0f} s with {pending} job(s) pending: stalled (deadlocked or stopped); rerun with --workers 1"
            )


def _process_cpu_seconds(pid: int) -> float | None:
    """User + system CPU seconds of process `pid` and its reaped children; None when unknown."""
    if sys.platform.startswith("linux"):
        try:
            stat = open(f"/proc/{pid}/stat").read()
            fields = stat[stat.rindex(")") + 2 :].split()
            return sum(int(f) for f in fields[11:15]) / os.sysconf("SC_CLK_TCK")  # utime stime cutime cstime
        except (OSError, ValueError, IndexError):
            return None
    try:
        import psutil
    except ImportError:
        return None
    try:
        times = psutil.Process(pid).cpu_times()
    except psutil.Error:
        return None
    return times.user + times.system + times.children_user + times.children_system


def _kill_workers(pool: ProcessPoolExecutor) -> None:
    """SIGKILL a stalled pool's workers, so that shutting it down does not wait on them."""
    for process in list((getattr(pool, "_processes", None) or {}).values()):
        try:
            process.kill()
        except (OSError, AttributeError):
            pass


def _map_ray(fn, items: list, executor: ExecutorConfig, ray_options: dict) -> Iterator[tuple[Any, Any]]:
    if not items:
        return
    with ray_session(executor) as ray:
        remote = ray.remote(**ray_options)(fn)
        pending = {remote.remote(item): item for item in items}
        try:
            while pending:
                (ref,), _ = ray.wait(list(pending), num_returns=1)
                item = pending.pop(ref)
                try:
                    result = ray.get(ref)
                except ray.exceptions.RayTaskError as e:
                    # the job's own exception (e.g. a ConfigError), not Ray's wrapper with its remote traceback
                    cause = getattr(e, "cause", None)
                    if isinstance(cause, BaseException):
                        raise cause from None
                    raise
                yield item, result
        finally:
            for ref in pending:  # what has not finished: never started, or stopped now
                ray.cancel(ref, force=True)
