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
    """`nodes` Ray nodes on this machine (`ray start --head`, then nodes joined to it), stopped on
    leaving the block, also when a start failed; yields the head's address for `ray_address`. For
    tests and measurements: nodes on one machine share its cores."""
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0"}
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    address = f"127.0.0.1:{port}"
    each = [f"--num-cpus={cpus_per_node}", "--disable-usage-stats"]
    try:
        _ray_cli("start", "--head", f"--port={port}", "--node-ip-address=127.0.0.1", "--include-dashboard=false",
                 f"--temp-dir={temp_dir}", *each, env=env)
        for _ in range(nodes - 1):
            _ray_cli("start", f"--address={address}", "--node-ip-address=127.0.0.1", *each, env=env)
        yield address
    finally:
        _ray_cli("stop", "--force", env=env)


def _ray_cli(*args: str, env: dict[str, str]) -> None:
    """The `ray` command beside this Python (the cluster extra installs it)."""
    subprocess.run([str(Path(sys.executable).with_name("ray")), *args], check=True, env=env, capture_output=True,
                   timeout=180)
