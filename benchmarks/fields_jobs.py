"""Run many ``fields_curve.py`` jobs side by side, one torch thread each.

    python benchmarks/fields_jobs.py JOBS_FILE --parallel N --out DIR

JOBS_FILE holds one job per line, ``TAG DATA MARKS [key=value ...]`` (``#`` starts a
comment), e.g. ``vm-yard scenes/yard-128x128-3x6-v4 250,500,1000,1500 field.encoding=vm``.
Each job is a separate process (``OMP_NUM_THREADS=1``), so CPU times of jobs that ran at
the same time stay comparable on a machine with at least N free cores. Curves are appended
to DIR/curves.jsonl; each job's output goes to DIR/logs/TAG.log.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path


def read_jobs(path: Path) -> list[list[str]]:
    jobs = []
    for line in path.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            jobs.append(line.split())
    return jobs


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("jobs")
    parser.add_argument("--parallel", type=int, default=2)
    parser.add_argument("--out", default="outputs/benchmarks/fields")
    parser.add_argument("--method", default="nerf")
    args = parser.parse_args(argv)
    out = Path(args.out)
    (out / "logs").mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    script = Path(__file__).resolve().parent / "fields_curve.py"
    pending, running = read_jobs(Path(args.jobs)), []
    while pending or running:
        while pending and len(running) < args.parallel:
            tag, data, marks, *overrides = pending.pop(0)
            cmd = [sys.executable, str(script), "--data", data, "--tag", tag, "--marks", marks,
                   "--method", args.method, "--out", str(out), *overrides]
            log = open(out / "logs" / f"{tag}.log", "w")
            running.append((tag, subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env), log))
        time.sleep(1.0)
        for item in list(running):
            tag, proc, log = item
            if proc.poll() is not None:
                log.close()
                running.remove(item)
                print(f"{tag}: exit {proc.returncode}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
