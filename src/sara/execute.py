"""Executors: where chunks of work run. A leaf (standard library only, plus the registry).

An executor maps a picklable, module-level function over a sequence of work items (shards of
image names or of pairs, with paths) and yields the results in the order of the items, so
results never depend on the executor or on the number of workers. The driver process alone
writes output files.

    serial      in this process
    processes   a pool of worker processes on this machine (`spawn`: no state leaks from the
                driver, safe with pycolmap and torch)
    ray         a Ray cluster (`sara.execute_ray`, the `sara[cluster]` extra), imported only when chosen
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any, Protocol, TypeVar, runtime_checkable

from .registry import Registry

logger = logging.getLogger(__name__)

T = TypeVar("T")
R = TypeVar("R")


@runtime_checkable
class Executor(Protocol):
    """Runs `fn` over `items`, yielding results in item order. `workers` says how many run at once."""

    name: str
    workers: int

    def map(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[Any]: ...

    def close(self) -> None: ...


class SerialExecutor:
    name = "serial"
    workers = 1

    def map(self, fn: Callable[[T], R], items: Sequence[T]) -> Iterator[R]:
        return map(fn, items)

    def close(self) -> None:
        pass


class ProcessExecutor:
    """A pool of `workers` processes, started on first use and reused until `close`."""

    name = "processes"

    def __init__(self, workers: int) -> None:
        self.workers = max(1, workers)
        self._pool: ProcessPoolExecutor | None = None

    def map(self, fn: Callable[[T], R], items: Sequence[T]) -> Iterator[R]:
        if self._pool is None:
            self._pool = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"),
                                             initializer=_ignore_interrupts)
        return self._pool.map(fn, items)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None

    def __del__(self) -> None:
        self.close()


def _ignore_interrupts() -> None:
    """Workers leave Ctrl-C to the driver, which stops them: no traceback from every worker. And
    they never outlive it: a driver killed outright (SIGKILL, or SIGTERM to it alone) cannot stop
    its pool, so each worker exits by itself within a second of its parent's end."""
    import signal
    import threading

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    parent = os.getppid()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_POLL_S)
        os._exit(1)

    threading.Thread(target=watch, name="sara-parent-watch", daemon=True).start()


#: how often a worker checks that its driver is still there (seconds)
PARENT_POLL_S = 0.5


def single_threaded_torch_in_worker() -> None:
    """In a worker process of ours (never the user's process), give torch one thread: workers are
    the parallelism, and torch's own threads then only contend (measured: 5x slower on 2 cores)."""
    if multiprocessing.parent_process() is None:
        return
    try:
        import torch
    except ImportError:
        return
    torch.set_num_threads(1)


#: executors whose workers run on other machines, each with its own devices
REMOTE_EXECUTORS = ("ray",)


def for_device(executor: Executor | None, device: Any) -> Executor | None:
    """The executor for a network that runs on `device` (a torch.device, or its name).

    On an accelerator (cuda, mps, ...) a network runs in this process, where it is loaded already:
    each worker process of a local pool would hold its own copy of the network and its own device
    context (16 workers held 14.5 GiB of an H200's memory; a laptop GPU has 4-8), and the device
    runs their calls one after another anyway. A remote executor's workers have their own devices
    and are kept; on the CPU the workers are the parallelism and are kept too.
    """
    kind = getattr(device, "type", None) or str(device or "cpu").split(":")[0]
    if executor is None or kind == "cpu" or getattr(executor, "name", "") in REMOTE_EXECUTORS:
        return executor
    if executor.workers > 1:
        logger.info("the network runs on %s in this process, not in %d workers", device, executor.workers)
    return SerialExecutor()


def available_cores() -> int:
    """Cores this process may use (the affinity mask, not the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def resolve_workers(workers: int) -> int:
    """0: one worker per available core; a negative number is an error."""
    if workers < 0:
        raise ValueError(f"execute.workers must be >= 0 (0: one per core), got {workers}")
    return workers or available_cores()


def _make_serial(workers: int, address: str) -> Executor:
    return SerialExecutor()


def _make_processes(workers: int, address: str) -> Executor:
    return ProcessExecutor(workers)


def _make_auto(workers: int, address: str) -> Executor:
    return SerialExecutor() if workers == 1 else ProcessExecutor(workers)


#: name -> factory(workers, address) -> Executor
EXECUTORS: Registry[Callable[[int, str], Executor]] = Registry("executor", {
    "auto": _make_auto,
    "serial": _make_serial,
    "processes": _make_processes,
    "ray": "sara.execute_ray:make",
})


def make_executor(name: str = "auto", workers: int = 0, address: str = "") -> Executor:
    """The executor `name` with `workers` workers (0: one per core)."""
    return EXECUTORS.get(name)(resolve_workers(workers), address)


class Beside:
    """Runs `step` again and again on a thread of the lowest priority while this process waits on
    another that keeps every core busy (COLMAP's extraction): `poke` asks for one more run (raising
    what the last one raised), leaving the block waits for the one under way. The thread gets only
    the CPU time the other process leaves (its reader idling at the start, one image left at the
    end), so it adds little to the wait."""

    def __init__(self, step: Callable[[], None]) -> None:
        self.step, self.error = step, None
        self._wake, self._stop = threading.Event(), False
        self._thread = threading.Thread(target=self._run, daemon=True, name="sara-beside")

    def _run(self) -> None:
        with contextlib.suppress(OSError, AttributeError):  # Linux: a thread's own niceness
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)
        while True:
            self._wake.wait()
            self._wake.clear()
            if self._stop:
                return
            try:
                self.step()
            except BaseException as exc:  # noqa: BLE001 - raised in the caller's thread by poke / exit
                self.error = exc
                return

    def poke(self) -> None:
        if self.error is not None:
            raise self.error
        self._wake.set()

    def __enter__(self) -> Beside:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop = True
        self._wake.set()
        self._thread.join()
        if self.error is not None and exc[0] is None:
            raise self.error
