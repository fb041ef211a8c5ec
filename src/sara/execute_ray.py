"""The Ray executor (`--executor ray`, the `sara[cluster]` extra): shards of work run as Ray tasks on
a cluster, results come back in order; the driver alone writes the output files.

Work items carry paths, so every node must see the image folder and the output folder at the same
paths (a shared file system; see README "Scale and clusters"). A task whose worker process dies is
run again (`max_retries`); a killed driver resumes like any run, from its stage records.

`ray_address`: "" starts a local Ray instance with `workers` CPUs for this run (and stops it at the
end); "auto" joins the cluster this machine belongs to (`ray start` was run here); "HOST:PORT" joins
that cluster.
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from .weights import MissingExtraError

logger = logging.getLogger(__name__)

#: runs of a task whose worker died before the run fails
TASK_RETRIES = 3
#: tasks in flight per CPU of the cluster: enough to keep it busy, few enough to bound memory
IN_FLIGHT_PER_CPU = 2


def _import_ray() -> Any:
    try:
        import ray
    except ImportError as exc:
        raise MissingExtraError(
            "--executor ray needs Ray, which is not installed: pip install 'sara[cluster]'") from exc
    return ray


def _call(fn: Callable[[Any], Any], item: Any) -> Any:
    from .execute import single_threaded_torch_in_worker

    single_threaded_torch_in_worker()
    return fn(item)


class RayExecutor:
    name = "ray"

    def __init__(self, workers: int, address: str = "") -> None:
        ray = self._ray = _import_ray()
        self._started_here = not ray.is_initialized()
        if self._started_here:
            kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False,
                                      "configure_logging": False}
            if address:
                ray.init(address=address, **kwargs)
            else:
                ray.init(num_cpus=workers, **kwargs)
        self.workers = max(1, int(ray.cluster_resources().get("CPU", workers)))
        self._task = ray.remote(max_retries=TASK_RETRIES, num_cpus=1)(_call)
        logger.info("ray: %d CPUs on %d node(s)", self.workers, len(ray.nodes()))

    def map(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[Any]:
        """Results in item order; at most IN_FLIGHT_PER_CPU tasks per CPU are pending at once."""
        ray = self._ray
        window = max(1, IN_FLIGHT_PER_CPU * self.workers)
        fn_ref = ray.put(fn)
        pending: list[Any] = []
        items = list(items)
        submitted = 0
        while submitted < len(items) or pending:
            while submitted < len(items) and len(pending) < window:
                pending.append(self._task.remote(fn_ref, items[submitted]))
                submitted += 1
            yield ray.get(pending.pop(0))

    def close(self) -> None:
        if self._started_here and self._ray.is_initialized():
            self._ray.shutdown()
            self._started_here = False


def make(workers: int, address: str) -> RayExecutor:
    return RayExecutor(workers, address)


@contextlib.contextmanager
def local_cluster(nodes: int, cpus_per_node: int, temp_dir: Path) -> Iterator[str]:
    """`nodes` Ray nodes on this machine (a head, then nodes joined to it), stopped on leaving the
    block, also when a start failed; yields the head's address for `ray_address`. For tests and
    measurements: nodes on one machine share its cores. Each node is a `ray start --block` process
    of its own, ended with SIGTERM (its reaper then stops the node's processes): `ray stop` would
    stop every Ray node of the machine, a user's too."""
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0"}
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    address = f"127.0.0.1:{port}"
    each = [f"--num-cpus={cpus_per_node}", "--disable-usage-stats", "--node-ip-address=127.0.0.1"]
    temp_dir = Path(temp_dir)
    temp_dir.mkdir(parents=True, exist_ok=True)
    with contextlib.ExitStack() as stack:
        stack.enter_context(_ray_node(temp_dir / "node-0.log", "--head", f"--port={port}", "--include-dashboard=false",
                                      f"--temp-dir={temp_dir}", *each, env=env))
        for i in range(1, nodes):
            stack.enter_context(_ray_node(temp_dir / f"node-{i}.log", f"--address={address}", *each, env=env))
        yield address


@contextlib.contextmanager
def _ray_node(log: Path, *args: str, env: dict[str, str], timeout_s: float = 180.0) -> Iterator[None]:
    """One node, `ray start ARGS --block` (the cluster extra's `ray` beside this Python), its output
    in `log`; up once it says so, ended on leaving the block. A start that fails or hangs raises
    CalledProcessError / TimeoutExpired with the end of its output as `stderr`."""
    command = [str(Path(sys.executable).with_name("ray")), "start", *args, "--block"]
    with open(log, "wb") as out:
        # a session of its own: the node's reaper ends its whole process group, which must not be ours
        proc = subprocess.Popen(command, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.monotonic() + timeout_s
        while b"Ray runtime started" not in log.read_bytes():
            if proc.poll() is not None:
                raise subprocess.CalledProcessError(proc.returncode, command, stderr=log.read_bytes()[-2000:])
            if time.monotonic() > deadline:
                raise subprocess.TimeoutExpired(command, timeout_s, stderr=log.read_bytes()[-2000:])
            time.sleep(0.2)
        yield
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
