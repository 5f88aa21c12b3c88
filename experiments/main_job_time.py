"""How long the README's main job takes: generating the built-in ``default`` data,
then ``python -m jtus.train`` (train DLCTUS briefly at 4x and compare it with JAU, TUS
and the shipped weights), each timed as the command a user runs, in a scratch folder.

    python experiments/main_job_time.py                 # docs/results/main-job/
    taskset -c 1 python experiments/main_job_time.py --name main-job-1core
    python experiments/main_job_time.py --preset diverse --generate-only --name diverse-2core

The machine's load average before each part is recorded next to its time: a figure
taken while other jobs ran is an upper bound.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

from common import write


def timed(argv, cwd):
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    subprocess.run([sys.executable, *argv], cwd=cwd, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0, load


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--name", default="main-job", help="docs/results/NAME/")
    p.add_argument("--preset", default="default", help="the data preset to generate")
    p.add_argument("--generate-only", action="store_true", help="time the data alone")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as d:
        data = os.path.join(d, f"{args.preset}.h5")
        parts = {
            f"generate the `{args.preset}` data": ["-m", "jtus.data", "generate", "--preset",
                                                   args.preset, "--out", data, "--quiet"],
        }
        if not args.generate_only:
            parts["`python -m jtus.train` (train 4x, evaluate)"] = [
                "-m", "jtus.train", "--dataset", data, "--workdir", os.path.join(d, "run"),
                "--quiet"]
        rows, data_out = [], {}
        for what, cmd in parts.items():
            seconds, load = timed(cmd, os.path.dirname(os.path.dirname(os.path.abspath(
                __file__))))
            rows.append(f"| {what} | {seconds:.0f} s ({seconds / 60:.1f} min) | {load:.2f} |")
            data_out[what] = {"seconds": seconds, "load_before": load,
                              "command": "python " + " ".join(cmd)}
            print(rows[-1], flush=True)
    table = "\n".join(["| part | wall time | load average before |", "| --- | --- | --- |"]
                      + rows)
    write(args.name, table, data_out,
          note=f"CPU affinity of this run: {sorted(os.sched_getaffinity(0))} (cores).")


if __name__ == "__main__":
    main()
