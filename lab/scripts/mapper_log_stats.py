"""What COLMAP's incremental mapper spent its time on, from the log in OUT/logs.

Per mapping run in the log (a run with rounds after mapping holds several): initial pairs tried,
images registered, registration attempts that failed, global bundle adjustments and their
total time, and the run's duration.

    python lab/scripts/mapper_log_stats.py OUT [OUT ...]
"""

from __future__ import annotations

import re
import sys
from datetime import datetime
from pathlib import Path

STAMP = re.compile(r"^[IWEF](\d{8} \d{2}:\d{2}:\d{2}\.\d{6})")


def _time(line: str) -> datetime | None:
    m = STAMP.match(line)
    return datetime.strptime(m.group(1), "%Y%m%d %H:%M:%S.%f") if m else None


def mapping_runs(log: Path) -> list[dict]:
    runs: list[dict] = []
    current: dict | None = None
    last = None
    ba_start = None
    for line in log.read_text(errors="replace").splitlines():
        t = _time(line) or last
        if "Loading database" in line:
            current = {"init_tries": 0, "registered": 0, "failed": 0, "global_ba": 0, "global_ba_s": 0.0,
                       "start": t, "end": t, "models": 0}
            runs.append(current)
        if current is None:
            last = t
            continue
        if ba_start is not None and t is not None and "Global bundle adjustment" not in line:
            current["global_ba_s"] += (t - ba_start).total_seconds()
            ba_start = None
        if "Finding good initial image pair" in line:
            current["init_tries"] += 1
        elif "Registering image #" in line:
            current["registered"] += 1
        elif "Could not register" in line or "=> Failed" in line:
            current["failed"] += 1
        elif "Global bundle adjustment" in line:
            current["global_ba"] += 1
            ba_start = t
        elif "Keeping successful reconstruction" in line:
            current["models"] += 1
        elif "Elapsed time" in line:
            current["end"] = t
        last = t
    for run in runs:
        run["duration_s"] = (run.pop("end") - run.pop("start")).total_seconds() if run.get("start") else 0.0
    return runs


def main() -> None:
    for out in sys.argv[1:]:
        for log in sorted(Path(out, "logs").glob("*")):
            for k, run in enumerate(mapping_runs(log)):
                print(f"{out} [{k}] " + " ".join(f"{key} {value:.1f}" if isinstance(value, float) else f"{key} {value}"
                                                for key, value in run.items()))


if __name__ == "__main__":
    main()
