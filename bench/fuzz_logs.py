"""A longer run of the drive-log fuzz suite (tests/test_fuzz_logs.py) than CI's budget.

The suite's properties draw their examples at a fixed seed; ``--examples N`` raises the
ingest property's budget to N (the CLI property gets N/10, the build property N/18). Prints
pytest's summary and the wall time; exit code is pytest's (0: no example produced anything
but an accepted log or a clean BadInput naming the culprit).

    python bench/fuzz_logs.py [--examples 2000] [--workers 2]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--examples", type=int, default=2000, help="examples of the ingest property (default 2000)")
    ap.add_argument("--workers", type=int, default=1, help="pytest-xdist workers (default 1)")
    args = ap.parse_args()
    env = dict(os.environ, MOSAICMAP_FUZZ_EXAMPLES=str(args.examples),
               PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    cmd = [sys.executable, "-m", "pytest", str(REPO / "tests" / "test_fuzz_logs.py"), "-q", "-p", "no:cacheprovider"]
    if args.workers > 1:
        cmd += ["-n", str(args.workers)]
    t0 = time.perf_counter()
    rc = subprocess.call(cmd, cwd=REPO, env=env)
    print(f"fuzz_logs: {args.examples} ingest examples (+{max(10, args.examples // 10)} CLI, "
          f"+{max(6, args.examples // 18)} build): exit {rc} in {time.perf_counter() - t0:.1f} s")
    return rc


if __name__ == "__main__":
    sys.exit(main())
