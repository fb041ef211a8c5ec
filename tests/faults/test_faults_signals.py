"""Class 6 of the fault suite: signals during a run (real signals to a real `sara` process, sent
once the stage's half-built output appears). One clean line, exit 128 + signal, the half-built
output removed, the previous outputs kept, and the same command then finishes. The slow cases
(during extraction, to a process group, while matching) are in test_faults_slow.py."""

from __future__ import annotations

import shutil
import signal

import pytest

from harness import assert_error, assert_kept, assert_ok, registered, signal_when, snapshot

SIGNALS = {
    "SIGTERM during pair selection": (signal.SIGTERM, 143, "pairs"),
    "SIGINT during pair selection": (signal.SIGINT, 130, "pairs"),
    "SIGTERM twice during pair selection": (signal.SIGTERM, 143, "pairs"),
    "SIGHUP during mapping": (signal.SIGHUP, 129, "map"),
    "SIGTERM during mapping": (signal.SIGTERM, 143, "map"),
}


# each signal and each stage stays in the default suite; two repeats of a pair of them are slow
SLOW = {"SIGTERM during pair selection", "SIGHUP during mapping"}


@pytest.mark.parametrize("case", [pytest.param(c, marks=pytest.mark.slow) if c in SLOW else c for c in SIGNALS])
def test_signal_is_one_clean_line_and_resumes(case, finished_run, images, finished_run_template, run_cli):
    signum, code, stage = SIGNALS[case]
    if stage == "pairs":
        (finished_run / "pairs.txt").unlink()
        # without the finished run's scores the selection scores its candidates again: it lasts
        # long enough for the signal to come during it (with them it took a fraction of a second
        # and, with the suite on every core, often ended before the test saw its marker)
        shutil.rmtree(finished_run / ".sara" / "score-journal")
        marker = finished_run / ".sara" / "pairs.next"
    else:
        shutil.rmtree(finished_run / "sparse")
        marker = finished_run / ".sara" / "sparse.partial"
    before = snapshot(finished_run)
    result = signal_when(["run", images, finished_run, "-q"], marker, signum, times=2 if "twice" in case else 1)
    if result.code == 0:
        pytest.skip("the run finished before the signal arrived (machine too fast for this case)")
    assert_error(result, code, f"interrupted by {signal.Signals(signum).name}", "run the same command again")
    assert not marker.exists()  # its half-built output is removed
    assert_kept(before, finished_run, ("database.db", "features-sift.h5", "run.json", "report.md"))
    result = run_cli("run", images, finished_run, "-q")  # the signalled process is gone: the same command, here
    assert_ok(result)
    assert registered(finished_run) == registered(finished_run_template)
