"""Benchmark of the tracker's speed as ``mosaicmap track`` runs it: a drive log replayed on one core.

The same code as the command, in this process: ``mosaicmap track BUNDLE LOG`` is invoked
``--runs`` times (:mod:`pipeline.track_run`, which replays through
:mod:`pipeline.track_replay`: frames decoded and rectified before the timed loop, as a
camera delivers them, then one :class:`tracker.session.Session` step per frame). The
process is pinned to one core (``os.sched_setaffinity(0, {0})``, ``cv2.setNumThreads(1)``).

Without ``--bundle`` / ``--log`` the replay of the speed target is made in ``--out`` (kept
with ``--reuse``)::

    mosaicmap simulate floor m --seed 5151 --area 5x5
    mosaicmap simulate floor ops --seed 5152 --area 5x5 --world m --route random --noise 10
    mosaicmap build m --map map -w w && mosaicmap export map b.zip

Per run it prints the command's figures (``speed`` of the report, see
:func:`pipeline.track_replay.speed_figures`): fixes/s over the wall time of the fixes and
over the tracker thread's CPU time, latency p50 / p99 / max per fix in both clocks, the
same per whole step, the conditions (prior 1-sigma median, search radius, load average),
and the accuracy (RMS of the ok fixes vs ground truth, wrong ok fixes). Then the median
over the runs, and a per-stage breakdown (mean CPU milliseconds per fix) from one more
run whose stages are wrapped in thread-CPU timers (that run is slower by the wrappers):
noise estimate, coverage (map data under the prior), template selection,
map windows (the map box read from the tile cache and resampled), correlation (NCC),
peaks (subpixel, uniqueness), fit (robust rigid fit and covariance), the rest of the fix
(the prefilter of noisy frames among it),
the session's own work around the fix, and map tiles read ahead of the fixes.

Timings on a busy machine: figures, not assertions; the CPU ones are what other processes
inflate least, the load average is printed beside them.

    python bench/bench_tracker_speed.py [--bundle B.zip --log LOG (--key PUB | --insecure)] [--runs 3]
                                        [--out DIR] [--reuse] [--no-stages] [--json FILE]

(the replay made here is signed with a key of its own, as a vehicle needs it: its open
checks the signature, its tiles are checked at their first read, inside the timing)
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from runner import reusable, run_cli  # noqa: E402

SITE = {"world_seed": 5151, "ops_seed": 5152, "area": "5x5", "route": "random", "noise": 10, "version": 2}


def make_site(out: Path, reuse: bool) -> tuple[Path, Path, Path]:
    """The replay of the module docstring in ``out``, the bundle signed as a vehicle
    needs it: (bundle, log, the owner's public key)."""
    marker = out / "site.json"
    if not reusable(marker, SITE, reuse):
        out.mkdir(parents=True, exist_ok=True)
        s = SITE
        run_cli("simulate", "floor", out / "m", "--seed", s["world_seed"], "--area", s["area"], "--quiet")
        run_cli("simulate", "floor", out / "ops", "--seed", s["ops_seed"], "--area", s["area"], "--world", out / "m",
                "--route", s["route"], "--noise", s["noise"], "--quiet")
        run_cli("build", out / "m", "--map", out / "map", "-w", out / "w", "--quiet")
        key = out / "owner.key"
        for k in (key, Path(f"{key}.pub")):
            k.unlink(missing_ok=True)
        run_cli("keys", "new", key)
        run_cli("export", out / "map", out / "b.zip", "--sign", key, "--quiet")
        marker.write_text(json.dumps({"params": SITE}))
    return out / "b.zip", out / "ops", out / "owner.key.pub"


def track(bundle: Path, log: Path, extra: list[str]) -> dict:
    """``mosaicmap track BUNDLE LOG --report ... --quiet`` in this process (its printed
    summary discarded); its report."""
    from pipeline.cli import cli

    with tempfile.TemporaryDirectory() as d, open(os.devnull, "w") as null, contextlib.redirect_stdout(null):
        rep = Path(d) / "track.json"
        code = cli.main(["track", str(bundle), str(log), "--report", str(rep), "--quiet", *extra],
                        standalone_mode=False)
        if code:
            raise SystemExit(f"mosaicmap track exited {code}")
        return json.loads(rep.read_text())


class StageTimer:
    """Wraps the tracker's stage functions in thread-CPU timers (seconds summed per stage;
    a stage called inside another is subtracted from it)."""

    def __init__(self):
        self.t = defaultdict(float)
        self._saved = []
        self._stack: list[float] = []

    def _wrap(self, owner, name: str, stage: str):
        fn = getattr(owner, name)
        self._saved.append((owner, name, fn))
        t, stack = self.t, self._stack

        def timed(*a, **k):
            stack.append(0.0)
            c0 = time.thread_time()
            try:
                return fn(*a, **k)
            finally:
                dt = time.thread_time() - c0
                inner = stack.pop()
                t[stage] += dt - inner
                if stack:
                    stack[-1] += dt

        setattr(owner, name, timed)

    def __enter__(self):
        from tracker import floor as floor_mod
        from tracker.floor import FloorTracker
        from tracker.session import Session

        self._wrap(Session, "step", "session (around the fix)")
        self._wrap(FloorTracker, "prefetch", "tiles read ahead")
        self._wrap(FloorTracker, "fix", "fix (rest)")
        self._wrap(floor_mod, "noise_sigma", "noise estimate")
        self._wrap(floor_mod, "coverage_mask", "coverage")
        self._wrap(floor_mod, "select_templates", "template selection")
        self._wrap(floor_mod, "half_frame", "template selection")
        self._wrap(FloorTracker, "_map_patch", "map windows")
        self._wrap(FloorTracker, "_map_windows", "map windows")
        self._wrap(floor_mod, "match_stack", "correlation")
        self._wrap(floor_mod, "peaks_of", "peaks")
        self._wrap(FloorTracker, "_pose_from", "fit")
        self._wrap(FloorTracker, "_covariance", "fit")
        return self

    def __exit__(self, *exc):
        for owner, name, fn in reversed(self._saved):
            setattr(owner, name, fn)

    def breakdown(self, n: int) -> dict:
        """Mean CPU milliseconds per fix of each stage."""
        return {k: 1e3 * v / max(n, 1) for k, v in sorted(self.t.items(), key=lambda kv: -kv[1])}


def figures(rep: dict) -> dict:
    """The figures of one run (a track report)."""
    sp = rep["speed"]
    return {"wall_fixes_per_s": sp["wall"]["fixes_per_s"], "wall_ms": sp["wall"]["latency_ms"],
            "cpu_fixes_per_s": sp["cpu"]["fixes_per_s"], "cpu_ms": sp["cpu"]["latency_ms"],
            "step_ms": sp["step"]["latency_ms"], "step_cpu_ms": sp["step"]["cpu_latency_ms"],
            "fixes": sp["fixes"], "prior_sigma_median": sp["prior_sigma_median"],
            "search_radius_px": sp["search_radius_px"], "load_avg_1min": sp["load_avg_1min"],
            "ok_rate": rep["ok_rate"], "error_rms_px": rep.get("error_rms_px"), "wrong_ok": rep.get("wrong_ok"),
            "decode_seconds": sp["decode_seconds"]}


def line(f: dict) -> str:
    w, c = f["wall_ms"], f["cpu_ms"]
    rms = "n/a" if f["error_rms_px"] is None else f"{f['error_rms_px']:.4f}"
    return (f"wall {f['wall_fixes_per_s']:.0f} fixes/s p50 {w['p50']:.3f} p99 {w['p99']:.3f} max {w['max']:.3f} ms | "
            f"CPU {f['cpu_fixes_per_s']:.0f} fixes/s p50 {c['p50']:.3f} p99 {c['p99']:.3f} max {c['max']:.3f} ms | "
            f"step p50 {f['step_ms']['p50']:.3f} p99 {f['step_ms']['p99']:.3f} ms | ok {100 * f['ok_rate']:.1f} % "
            f"RMS {rms} px wrong {f['wrong_ok']} | load {f['load_avg_1min']:.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--bundle", type=Path, default=None, help="bundle to track on (default: the replay above, made in --out)")
    ap.add_argument("--log", type=Path, default=None, help="drive log to replay (with --bundle)")
    ap.add_argument("--runs", type=int, default=3, help="replays timed (the median is printed)")
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_tracker_speed"), help="where the replay is made")
    ap.add_argument("--reuse", action="store_true", help="reuse the replay kept in --out")
    ap.add_argument("--no-stages", action="store_true", help="skip the per-stage breakdown run")
    ap.add_argument("--json", type=Path, default=None, help="write the figures to this JSON file")
    args, extra = ap.parse_known_args()
    if (args.bundle is None) != (args.log is None):
        ap.error("--bundle and --log go together")
    if args.bundle is not None:
        bundle, log = args.bundle, args.log  # (its trust as track takes it: --key PUB or --insecure, passed on)
    else:
        bundle, log, pub = make_site(args.out, args.reuse)
        extra = ["--key", str(pub), *extra]
    os.sched_setaffinity(0, {0})
    cv2.setNumThreads(1)
    runs = []
    for k in range(args.runs):
        f = figures(track(bundle, log, extra))
        runs.append(f)
        print(f"run {k + 1}: {line(f)}", flush=True)
    f0 = runs[0]
    sig = f0["prior_sigma_median"]
    print(f"{log.name} on {bundle.name}, one core: {f0['fixes']} fixes, prior 1-sigma median {1000 * sig[0]:.1f} mm / "
          f"{1000 * sig[2]:.1f} mrad -> search radius {f0['search_radius_px']} px; frames decoded before timing "
          f"({f0['decode_seconds']:.1f} s)")
    med = {k: float(np.median([r[k] for r in runs])) for k in ("wall_fixes_per_s", "cpu_fixes_per_s")}
    for clock in ("wall_ms", "cpu_ms", "step_ms"):
        med[clock] = {q: float(np.median([r[clock][q] for r in runs])) for q in ("p50", "p99", "max")}
    print(f"median of {len(runs)}: wall {med['wall_fixes_per_s']:.0f} fixes/s p50 {med['wall_ms']['p50']:.3f} "
          f"p99 {med['wall_ms']['p99']:.3f} max {med['wall_ms']['max']:.3f} ms | CPU {med['cpu_fixes_per_s']:.0f} "
          f"fixes/s p50 {med['cpu_ms']['p50']:.3f} p99 {med['cpu_ms']['p99']:.3f} max {med['cpu_ms']['max']:.3f} ms")
    res = {"bundle": str(bundle), "log": str(log), "runs": runs, "median": med}
    if not args.no_stages:
        with StageTimer() as st:
            f = figures(track(bundle, log, extra))
        res["stages_cpu_ms"] = st.breakdown(f["fixes"])
        print("CPU ms per fix by stage (wrapped run): "
              + ", ".join(f"{k} {v:.3f}" for k, v in res["stages_cpu_ms"].items())
              + f"; total {sum(res['stages_cpu_ms'].values()):.3f}")
    if args.json:
        args.json.write_text(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
