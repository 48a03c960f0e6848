"""Benchmark: a floor log built from a prior that is loose or wrong.

One simulated 5 x 5 m lawnmower (the simulator's defaults, 1 % odometry drift, noise sigma 5)
is built to ``--until optimize`` four times, from the same images, with the odometry.csv
rewritten (:mod:`pipeline.simulate.prior_errors`):

- ``tight``: as simulated, with the default error model (today's prior);
- ``loose``: odometry positions scaled by 1.05 about the start (a wheel radius 5 % off) and
  the build told the prior's heading is only good to 0.2 rad
  (``[optimize] odometry_heading_sigma_floor_rad = 0.2``): a loose prior;
- ``flipped``: one lane's heading turned by pi, its positions kept (gimbal vs body yaw);
- ``heading``: a smooth heading error of sigma 0.2 rad added to the odometry's theta, the
  positions kept, the build not told (a wandering compass): harder than the issue asks.

For each: registration pairs/s (and its ratio to ``tight``), links accepted / rejected with
reasons, the prior corrections the register stage made (report ``registration.prior``), and
the optimized poses against the simulator's ground truth (RMS / max, pixels). A ghosted map
shows as a large max error. Figures, not assertions; the machine load is printed.

    python bench/bench_loose_prior.py [--out DIR] [--seed 1] [--area 5] [--variants tight,flipped]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--area", type=float, default=5.0)
    ap.add_argument("--log", type=Path, default=None, help="An existing simulated log.")
    ap.add_argument("--variants", default="tight,loose,flipped,heading")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    from pipeline.stages.build import run_build
    from pipeline.config import load_config
    from pipeline.simulate.floor import simulate_floor
    from pipeline.simulate.prior_errors import rewrite_prior

    print(f"bench_loose_prior {time.strftime('%Y-%m-%d %H:%M')}, load {os.getloadavg()[0]:.2f}", flush=True)
    out = args.out or Path(tempfile.mkdtemp(prefix="loose_"))
    figures = {}
    try:
        log = args.log
        if log is None:
            log = out / "log"
            shutil.rmtree(log, ignore_errors=True)
            simulate_floor(log, load_config(), {"seed": args.seed, "area": f"{args.area:g}x{args.area:g}"}, quiet=True)
        base = None
        for v in args.variants.split(","):
            vlog = out / f"log_{v}"
            shutil.rmtree(vlog, ignore_errors=True)
            rewrite_prior(log, vlog, v, args.seed)
            work = out / f"work_{v}"
            shutil.rmtree(work, ignore_errors=True)
            cfg = load_config()
            cfg["register"]["scheduler"] = "threads"
            if v == "loose":
                cfg["optimize"]["odometry_heading_sigma_floor_rad"] = 0.2
            t0 = time.perf_counter()
            rep = run_build([vlog], work, cfg, until="optimize", quiet=True)
            R, G, L = rep["registration"], rep.get("ground_truth", {}), rep["links"]
            pps = R["pairs_per_s"]
            base = pps if v == "tight" else base
            figures[v] = {"pairs_per_s": pps, "ratio_to_tight": (pps / base) if base else None,
                          "candidates": L["candidates"], "accepted": L["accepted"],
                          "rejected_registration": L["rejected_registration"], "rejected_outliers": L["rejected_outliers"],
                          "reasons": R["rejection_reasons"], "prior": R.get("prior"),
                          "pose_rms_px": G.get("pose_rms_px"), "pose_max_px": G.get("pose_max_px"),
                          "seconds": time.perf_counter() - t0}
            f = figures[v]
            print(f"\n{v}: {pps:.0f} pairs/s" + (f" ({f['ratio_to_tight']:.2f}x tight)" if base and v != "tight" else "")
                  + f", {f['accepted']} of {f['candidates']} links accepted ({f['rejected_registration']} rejected by "
                  f"registration {f['reasons']}, {f['rejected_outliers']} as outliers)")
            pr = f["prior"] or {}
            print(f"  prior corrections: {pr.get('heading_segments')} heading segments, scales {pr.get('scales')}, "
                  f"{pr.get('pairs_searched_wide', 0)} pairs searched wide ({pr.get('pairs_found_wide', 0)} found)")
            print(f"  poses vs ground truth: RMS {f['pose_rms_px']:.4f} px, max {f['pose_max_px']:.4f} px  "
                  f"[target: RMS <= 0.2 px, nothing ghosted]", flush=True)
        print(f"\nload at the end {os.getloadavg()[0]:.2f}")
        if args.json:
            args.json.write_text(json.dumps(figures, indent=1, default=float))
    finally:
        if args.out is None:
            shutil.rmtree(out, ignore_errors=True)


if __name__ == "__main__":
    main()
