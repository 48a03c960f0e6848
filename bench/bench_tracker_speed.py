"""Benchmark of the floor tracker's fix speed on one core (issue: >= 1000 fixes/s at a +-2 cm prior).

A synthetic map (``--map-px`` square of :func:`pipeline.synthmap.periodic_texture`, seed
11, 2.5 mm pixels, grey levels 1..255, as ``tests/test_tracker_floor.py`` builds it) held
in memory (:class:`tracker.tiles.ArrayTiles`); ``--fixes`` rectified 320 x 240 frames cut
at random poses (bicubic, sensor noise ``--noise`` grey levels, default 10); each fix's
prior is the truth plus N(0, ``--sigma-m``) metres per axis and N(0, ``--sigma-rad``)
radians (defaults 2 cm, 0.01 rad), with that same 1-sigma as ``prior_sigma``. The process
is pinned to one core (``os.sched_setaffinity(0, {0})``, ``cv2.setNumThreads(1)``); the
frames are made before the timing starts. It prints:

- the search radius the prior gives (pixels, clamped as ``FloorTrackerParams`` says);
- fixes/s (fixes over the wall-clock time of the timed pass) and latency p50 / p99 / max
  (milliseconds per :meth:`FloorTracker.fix`, template selection included); beside them
  the CPU time of the fixes (``time.thread_time``: fixes per CPU second, per-fix p50 / p99),
  which other processes sharing the core do not inflate, and the load average;
- the ok rate, the position error of the ok fixes vs the truth (RMS / max, frame pixels),
  heading error RMS (mrad) and the wrong ok count (ok with error > 2 px: should be 0);
- a per-stage breakdown (mean milliseconds per fix) from a second pass whose stages are
  wrapped in ``time.perf_counter`` (that pass is slower by the wrappers' overhead): template
  selection (``select_templates``), map windows (``FloorTracker._map_windows``: the map cut
  and resampled), correlation (the rest of ``FloorTracker._search``: NCC and peaks), fit
  (``FloorTracker._pose_from`` and ``_covariance``), and the remainder of ``fix``.

Timings are wall clock on a possibly busy machine: figures, not assertions.

    python bench/bench_tracker_speed.py [--fixes 2000] [--noise 10] [--sigma-m 0.02]
                                        [--sigma-rad 0.01] [--map-px 2048] [--seed 0] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from collections import defaultdict

import cv2
import numpy as np

from mapstore.grid import MapGrid
from pipeline.synthmap import periodic_texture
from tracker import floor as floor_mod
from tracker.floor import FloorTracker
from tracker.tiles import ArrayTiles

PX = 0.0025
FRAME = (240, 320)


def make_map(map_px: int) -> tuple[np.ndarray, MapGrid]:
    """The synthetic map (uint8, 0 = no data never occurs) and its grid (2.5 mm pixels)."""
    m = np.clip(np.rint(periodic_texture(11, map_px)), 1, 255).astype(np.uint8)
    return m, MapGrid(0.0, (m.shape[0] - 1) * PX, PX, m.shape[1], m.shape[0])


def frame_at(m: np.ndarray, grid: MapGrid, pose: np.ndarray, rng: np.random.Generator, noise: float) -> np.ndarray:
    """A 320 x 240 rectified frame of the map at ``pose`` (bicubic) with Gaussian noise (grey levels)."""
    a = grid.frame_to_grid_affine(pose, FRAME, PX)
    f = cv2.warpAffine(m, a, FRAME[::-1], flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP).astype(np.float32)
    return np.clip(f + rng.normal(0, noise, f.shape), 0, 255).astype(np.uint8)


def make_cases(m, grid, n: int, noise: float, sigma: np.ndarray, seed: int):
    """(frames, truths, priors): random poses 0.5 m inside the map, priors = truth + N(0, sigma)."""
    rng = np.random.default_rng(seed)
    x0, y0, x1, y1 = grid.bounds
    truths = np.column_stack([rng.uniform(x0 + 0.5, x1 - 0.5, n), rng.uniform(y0 + 0.5, y1 - 0.5, n),
                              rng.uniform(-np.pi, np.pi, n)])
    frames = [frame_at(m, grid, t, rng, noise) for t in truths]
    priors = truths + rng.normal(0, 1, (n, 3)) * sigma
    return frames, truths, priors


class StageTimer:
    """Wraps the tracker's stage functions in perf_counter timers (seconds summed per stage)."""

    def __init__(self):
        self.t = defaultdict(float)
        self._saved = []

    def _wrap(self, owner, name: str, stage: str):
        fn = getattr(owner, name)
        self._saved.append((owner, name, fn))
        t = self.t

        def timed(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                t[stage] += time.perf_counter() - t0

        setattr(owner, name, timed)

    def __enter__(self):
        self._wrap(floor_mod, "select_templates", "template selection")
        self._wrap(FloorTracker, "_map_windows", "map windows")
        if hasattr(FloorTracker, "_map_patch"):
            self._wrap(FloorTracker, "_map_patch", "map windows")
        self._wrap(FloorTracker, "_search", "_search")
        self._wrap(FloorTracker, "_pose_from", "fit")
        self._wrap(FloorTracker, "_covariance", "fit")
        self._wrap(FloorTracker, "fix", "fix")
        return self

    def __exit__(self, *exc):
        for owner, name, fn in reversed(self._saved):
            setattr(owner, name, fn)

    def breakdown(self, n: int) -> dict:
        """Mean milliseconds per fix of each stage."""
        ms = {k: 1e3 * v / n for k, v in self.t.items()}
        out = {"template selection": ms.get("template selection", 0.0), "map windows": ms.get("map windows", 0.0)}
        out["correlation"] = ms.get("_search", 0.0) - out["map windows"]
        out["fit"] = ms.get("fit", 0.0)
        out["other"] = ms.get("fix", 0.0) - out["template selection"] - ms.get("_search", 0.0) - out["fit"]
        out["total (wrapped)"] = ms.get("fix", 0.0)
        return out


def run(args) -> dict:
    """The benchmark; returns the figures printed."""
    os.sched_setaffinity(0, {0})
    cv2.setNumThreads(1)
    m, grid = make_map(args.map_px)
    sigma = np.array([args.sigma_m, args.sigma_m, args.sigma_rad])
    frames, truths, priors = make_cases(m, grid, args.fixes, args.noise, sigma, args.seed)
    trk = FloorTracker(ArrayTiles(m), grid, PX)
    p = trk.p
    # the search radius as fix() derives it (the templates' worst lever: the frame corner)
    lever = np.hypot(*(np.array(FRAME[::-1]) / 2.0 - p.template_px // 2 - 1)) * PX
    radius = int(np.clip(np.ceil(p.search_sigmas * np.hypot(np.hypot(sigma[0], sigma[1]), sigma[2] * lever) / PX) + 1,
                         p.min_radius_px, p.max_radius_px))
    for i in range(min(20, len(frames))):  # warm-up (caches, lazy imports)
        trk.fix(frames[i], priors[i], sigma)
    lat = np.empty(len(frames))
    cpu = np.empty(len(frames))
    fixes = []
    t_start = time.perf_counter()
    for i, (f, pr) in enumerate(zip(frames, priors)):
        c0 = time.thread_time()
        t0 = time.perf_counter()
        fixes.append(trk.fix(f, pr, sigma))
        lat[i] = time.perf_counter() - t0
        cpu[i] = time.thread_time() - c0
    wall = time.perf_counter() - t_start
    ok = np.array([fx.ok for fx in fixes])
    err = np.array([np.hypot(*(fx.pose[:2] - t[:2])) / PX for fx, t in zip(fixes, truths)])
    herr = np.array([abs(np.angle(np.exp(1j * (fx.pose[2] - t[2])))) for fx, t in zip(fixes, truths)])
    statuses = defaultdict(int)
    for fx in fixes:
        statuses[fx.status] += 1
    with StageTimer() as st:
        for f, pr in zip(frames, priors):
            trk.fix(f, pr, sigma)
    res = {
        "fixes": len(frames), "noise": args.noise, "sigma_m": args.sigma_m, "sigma_rad": args.sigma_rad,
        "map_px": args.map_px, "search_radius_px": radius, "params": {k: v for k, v in vars(p).items()},
        "fixes_per_s": len(frames) / wall, "fixes_per_cpu_s": len(frames) / cpu.sum(),
        "cpu_ms": {"p50": 1e3 * float(np.percentile(cpu, 50)), "p99": 1e3 * float(np.percentile(cpu, 99)),
                   "mean": 1e3 * float(cpu.mean())},
        "load_avg_1min": os.getloadavg()[0],
        "latency_ms": {"p50": 1e3 * float(np.percentile(lat, 50)), "p99": 1e3 * float(np.percentile(lat, 99)),
                       "max": 1e3 * float(lat.max()), "mean": 1e3 * float(lat.mean())},
        "ok_rate": float(ok.mean()), "statuses": dict(statuses),
        "error_px": {"rms": float(np.sqrt(np.mean(err[ok] ** 2))) if ok.any() else float("nan"),
                     "max": float(err[ok].max()) if ok.any() else float("nan")},
        "heading_error_mrad_rms": 1e3 * float(np.sqrt(np.mean(herr[ok] ** 2))) if ok.any() else float("nan"),
        "wrong_ok": int((ok & (err > 2.0)).sum()),
        "stages_ms": st.breakdown(len(frames)),
    }
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--fixes", type=int, default=2000)
    ap.add_argument("--noise", type=float, default=10.0, help="sensor noise sigma (grey levels)")
    ap.add_argument("--sigma-m", type=float, default=0.02, help="prior 1-sigma per axis (metres)")
    ap.add_argument("--sigma-rad", type=float, default=0.01, help="prior heading 1-sigma (radians)")
    ap.add_argument("--map-px", type=int, default=2048, help="side of the synthetic map (pixels)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None, help="write the figures to this JSON file")
    args = ap.parse_args()
    r = run(args)
    lat = r["latency_ms"]
    print(f"one core, {r['fixes']} fixes, 320x240 frames, noise {r['noise']:g}, prior sigma "
          f"{100 * r['sigma_m']:g} cm / {r['sigma_rad']:g} rad -> search radius {r['search_radius_px']} px")
    print(f"fixes/s            {r['fixes_per_s']:.0f} (wall clock)  {r['fixes_per_cpu_s']:.0f} per CPU second"
          f"  (load average {r['load_avg_1min']:.2f} on {os.cpu_count()} cores)")
    print(f"latency ms         p50 {lat['p50']:.3f}  p99 {lat['p99']:.3f}  max {lat['max']:.3f}  "
          f"mean {lat['mean']:.3f}")
    cpu = r["cpu_ms"]
    print(f"CPU ms per fix     p50 {cpu['p50']:.3f}  p99 {cpu['p99']:.3f}  mean {cpu['mean']:.3f}")
    print(f"ok rate            {r['ok_rate']:.4f}  {r['statuses']}")
    print(f"error px (ok)      RMS {r['error_px']['rms']:.4f}  max {r['error_px']['max']:.4f}  "
          f"heading RMS {r['heading_error_mrad_rms']:.3f} mrad")
    print(f"wrong ok (>2 px)   {r['wrong_ok']}")
    print("stages ms/fix      " + "  ".join(f"{k} {v:.3f}" for k, v in r["stages_ms"].items()))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(r, fh, indent=2)


if __name__ == "__main__":
    main()
