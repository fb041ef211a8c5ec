"""The process executor: results in order, and workers that never outlive their driver."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from sara.execute import ProcessExecutor, SerialExecutor, for_device, make_executor


def _square(x: int) -> int:
    return x * x


def test_executors_give_results_in_item_order() -> None:
    items = list(range(17))
    pool = ProcessExecutor(2)
    try:
        assert list(pool.map(_square, items)) == [x * x for x in items]
    finally:
        pool.close()
    assert list(SerialExecutor().map(_square, items)) == [x * x for x in items]
    assert make_executor("auto", 1).workers == 1


class _Remote:
    name = "ray"
    workers = 8


def test_a_network_on_an_accelerator_runs_in_the_driver_not_in_each_local_worker() -> None:
    pool = ProcessExecutor(4)
    for device in ("cuda", "cuda:1", "mps"):
        assert isinstance(for_device(pool, device), SerialExecutor)
    assert for_device(pool, "cpu") is pool  # on the CPU the workers are the parallelism
    assert for_device(None, "cuda") is None
    remote = _Remote()
    assert for_device(remote, "cuda") is remote  # remote workers have their own devices

    class Device:  # as torch.device: its kind in `type`
        type = "cuda"

    assert isinstance(for_device(pool, Device()), SerialExecutor)
    pool.close()


DRIVER = """
import os, sys, time
from sara.execute import ProcessExecutor

def slow(x):
    with open(os.path.join(sys.argv[1], f"worker-{os.getpid()}"), "w"):
        pass
    time.sleep(60)
    return x

if __name__ == "__main__":
    pool = ProcessExecutor(2)
    list(pool.map(slow, range(2)))
"""


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie (exited, not yet reaped by init) counts as gone
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except OSError:
        return False


def test_workers_exit_when_the_driver_is_killed(tmp_path: Path) -> None:
    script = tmp_path / "driver.py"
    script.write_text(DRIVER)
    driver = subprocess.Popen([sys.executable, str(script), str(tmp_path)])
    deadline = time.monotonic() + 60
    while len(list(tmp_path.glob("worker-*"))) < 2 and time.monotonic() < deadline:
        time.sleep(0.1)
    workers = [int(p.name.split("-")[1]) for p in tmp_path.glob("worker-*")]
    assert len(workers) == 2 and all(_alive(pid) for pid in workers)
    driver.send_signal(signal.SIGKILL)  # the pool cannot be shut down: the workers must notice
    driver.wait()
    deadline = time.monotonic() + 10
    while any(_alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(pid) for pid in workers)
