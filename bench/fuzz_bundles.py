"""The bundle fuzz suite (tests/test_fuzz_bundles.py) with a longer budget.

CI runs every mutation kind with a small fixed budget (>= 500 mutations, derandomized);
this runs the same properties ``--scale`` times as many examples (``FUZZ_BUNDLES_SCALE``)
and prints pytest's summary: mutated and forged bundles and deltas through verify,
apply-delta and the tracker's open + read path, every one refused cleanly or read as the
original content.

    python bench/fuzz_bundles.py [--scale 20]
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
    ap.add_argument("--scale", type=int, default=int(os.environ.get("FUZZ_BUNDLES_SCALE", "20")),
                    help="Examples per mutation kind, as a multiple of the CI budget (CI: 1).")
    args = ap.parse_args()
    env = dict(os.environ, FUZZ_BUNDLES_SCALE=str(args.scale),
               PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    t0 = time.perf_counter()
    rc = subprocess.call([sys.executable, "-m", "pytest", "tests/test_fuzz_bundles.py", "-q", "-W", "ignore",
                          "-p", "no:cacheprovider"], cwd=REPO, env=env)
    print(f"bundle fuzzing at {args.scale} x the CI budget (>= {540 * args.scale} mutations): "
          f"{'passed' if rc == 0 else 'FAILED'} in {time.perf_counter() - t0:.0f} s")
    return rc


if __name__ == "__main__":
    raise SystemExit(main())
