"""Benchmark of `mosaicmap track` on omni logs: the route panorama session and global
relocalization (tracker/orp_session.py, tracker/orp_reloc.py).

The 20.3 m loop of `bench/bench_orp.py` (default `mosaicmap simulate omni` world, frames every
2 cm): the memorized run's horizon lines at its ground-truth poses become an ORP (the build's
spacing, [orp] spacing_m, or --spacing; tracker.orp.build_orp), stored as route "loop" (mapstore.routes.write_route) in a
zarr directory zipped into a bundle-like file (stored members, read through
mapstore.bundle.BundleStore). The held-out runs (on the path, 30 deg across within +-30 cm,
night, camera 1 cm higher, objects over 25 % of the azimuths moved: with masking and
without) are tracked through the CLI (`mosaicmap track BUNDLE LOG`, odometry start, in
process, OpenCV on one thread). Printed per run: ok rate, mean / RMS / max position error (cm)
and heading RMS (deg) of the ok frames, wrong ok frames (> 10 cm), CPU ms per frame (the
horizon unwarp plus the session's mean localization time, this thread's CPU time: other
processes on the machine do not inflate it; the wall-clock p50 beside it).

Relocalization: (a) kidnapped starts: each run tracked with `--start none` over its first 50
frames (the frame of the first fix, its time); (b) every `--reloc-step`-th frame of every
run relocalized from nothing (tracker.orp_reloc.ORPRelocalizer.locate): success rate,
ambiguous / lost, wrong fixes (> 10 cm from the truth), time per attempt (wall: median, max;
CPU median).

    python bench/bench_orp_track.py [--work DIR] [--runs path,...] [--reloc-step 10] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import zipfile
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_orp import RUNS, TARGET_CM, load_lines, simulate  # noqa: E402
from mapstore.routes import RouteRecord, write_route  # noqa: E402
from tracker.orp import ORPLocalizer, ORPParams, build_orp  # noqa: E402
from tracker.orp_reloc import ORPRelocalizer, ORPRelocParams  # noqa: E402

ROUTE_ID = "loop"


def make_bundle(work: Path, params: ORPParams) -> tuple[Path, object]:
    """The memorized run's route in ``work/map.zarr`` and zipped into ``work/map.zip``."""
    import zarr

    lines, truth, _, _, _ = load_lines(work / "mem", params)
    orp = build_orp(lines, truth, params.spacing_m, params.samples_per_degree)
    rec = RouteRecord(orp.lines, orp.poses, 0.0, orp.spacing_m, orp.samples_per_degree, params.horizon_band_deg,
                      version=1, sources=[{"log_id": "mem", "path": str(work / "mem")}])
    d = work / "map.zarr"
    write_route(zarr.open_group(str(d), mode="w"), ROUTE_ID, rec)
    out = work / "map.zip"
    with zipfile.ZipFile(out, "w", zipfile.ZIP_STORED) as z:
        for p in sorted(d.rglob("*")):
            if p.is_file():
                z.write(p, p.relative_to(d).as_posix())
    return out, orp


def cli_track(bundle: Path, log: Path, report: Path, *extra: str) -> dict:
    """``mosaicmap track bundle log --report report extra...`` in process; the report."""
    from click.testing import CliRunner

    from pipeline.cli import cli

    r = CliRunner().invoke(cli, ["track", str(bundle), str(log), "--insecure", "--report", str(report), "--quiet",
                                 *extra])  # unsigned bench bundles
    if r.exit_code != 0:
        raise SystemExit(f"track {log} failed: {r.output}")
    return json.loads(report.read_text())


def track_row(rep: dict) -> dict:
    cpu_fix_ms = 1000.0 / rep["cpu_fixes_per_s"] if rep.get("cpu_fixes_per_s") else float("nan")
    return {
        "frames": rep["fixes"], "ok_rate": rep["ok_rate"], "statuses": rep["statuses"],
        "error_mean_cm": 100 * rep["error_mean_m"], "error_rms_cm": 100 * rep["error_rms_m"],
        "error_max_cm": 100 * rep["error_max_m"], "heading_rms_deg": rep["heading_rms_deg"],
        "wrong_ok": rep["wrong_ok"], "relocalizations": rep["relocalizations"],
        "cpu_ms_per_frame": rep["unwarp_ms"] + cpu_fix_ms, "wall_fix_p50_ms": rep["latency_ms"]["p50"],
        "unwarp_ms": rep["unwarp_ms"],
    }


def reloc_sweep(orp, lines: np.ndarray, truth: np.ndarray, step: int, params: ORPParams,
                rparams: ORPRelocParams) -> dict:
    """Relocalize every ``step``-th line from nothing; counts, wrong fixes (> 10 cm), times."""
    rl = ORPRelocalizer(ORPLocalizer(orp, params), rparams)
    counts = {"ok": 0, "ambiguous": 0, "lost": 0}
    wrong, errs, wall, cpu = 0, [], [], []
    for i in range(0, len(lines), step):
        c0 = time.thread_time()
        res = rl.locate(lines[i])
        cpu.append(time.thread_time() - c0)
        wall.append(res.seconds)
        counts[res.status] += 1
        if res.ok:
            e = math.hypot(*(res.fix.pose[:2] - truth[i, :2]))
            errs.append(e)
            wrong += e > 0.10
    n = sum(counts.values())
    return {"attempts": n, **counts, "success_rate": counts["ok"] / max(n, 1), "wrong": int(wrong),
            "error_median_cm": 100 * float(np.median(errs)) if errs else None,
            "ms_median": 1000 * float(np.median(wall)), "ms_max": 1000 * float(np.max(wall)),
            "cpu_ms_median": 1000 * float(np.median(cpu))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/mosaicmap-bench-orp"),
                    help="simulated logs (shared with bench_orp.py) and the route bundle")
    ap.add_argument("--runs", default=",".join(RUNS), help="comma-separated subset of: " + ",".join(RUNS))
    ap.add_argument("--reloc-step", type=int, default=10, help="relocalize every n-th frame of each run")
    ap.add_argument("--spacing", type=float, default=None,
                    help="ORP row spacing (metres; default the build's [orp] spacing_m)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    from dataclasses import replace

    from pipeline.config import load_config

    cfg = load_config(None)
    tcfg = cfg["tracker"]
    params = replace(ORPParams.from_dict(tcfg["orp"]),
                     spacing_m=float(args.spacing if args.spacing is not None else cfg["orp"]["spacing_m"]))
    rparams = ORPRelocParams.from_dict(tcfg["orp_reloc"])
    args.work.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    simulate(args.work)
    print(f"simulated logs in {args.work} ({time.perf_counter() - t:.0f} s)")
    bundle, orp = make_bundle(args.work, params)
    print(f"route {ROUTE_ID!r}: {len(orp.lines)} rows over {orp.length_m:.2f} m, {bundle} "
          f"({bundle.stat().st_size / 1e3:.0f} kB)")
    nomask = args.work / "nomask.toml"
    nomask.write_text("[tracker.orp]\nmasking = false\n")
    out: dict = {"route": {"rows": int(len(orp.lines)), "length_m": orp.length_m, "spacing_m": orp.spacing_m}, "track": {}, "kidnapped": {},
                 "reloc": {}}
    print(f"{'run':16s} {'frames':>6s} {'ok %':>6s} {'mean cm':>8s} {'rms cm':>7s} {'max cm':>7s} {'head rms':>8s} "
          f"{'wrong':>5s} {'reloc':>5s} {'CPU ms':>6s} {'wall p50':>8s} target (mean)")
    runs = args.runs.split(",")
    for name in runs:
        variants = [(name, ())] if name != "moved" else [("moved (masking)", ()),
                                                        ("moved (no mask)", ("--config", str(nomask)))]
        for label, extra in variants:
            r = track_row(cli_track(bundle, args.work / name, args.work / f"track-{name}.json", *extra))
            out["track"][label] = r
            tgt = TARGET_CM.get(label)
            verdict = "(printed)" if tgt is None else f"<= {tgt:g} cm: {'met' if r['error_mean_cm'] <= tgt else 'NOT met'}"
            print(f"{label:16s} {r['frames']:6d} {100 * r['ok_rate']:6.2f} {r['error_mean_cm']:8.3f} "
                  f"{r['error_rms_cm']:7.3f} {r['error_max_cm']:7.2f} {r['heading_rms_deg']:8.3f} {r['wrong_ok']:5d} "
                  f"{r['relocalizations']:5d} {r['cpu_ms_per_frame']:6.2f} {r['wall_fix_p50_ms']:8.2f} {verdict}")
    print("kidnapped starts (--start none, first 50 frames):")
    for name in runs:
        rep = cli_track(bundle, args.work / name, args.work / f"kidnap-{name}.json", "--start", "none",
                        "--frames", "0:50")
        rl = rep["relocalization"]
        k = {"first_ok_frame": rl["first_ok_frame"], "attempts": rl["attempts"],
             "reloc_ms_median": None if rl["seconds_median"] is None else 1000 * rl["seconds_median"],
             "ok_rate": rep["ok_rate"], "wrong_ok": rep["wrong_ok"],
             "error_mean_cm": None if rep.get("error_mean_m") is None else 100 * rep["error_mean_m"]}
        out["kidnapped"][name] = k
        print(f"  {name:10s} relocalized at frame {k['first_ok_frame']} after {k['attempts']} attempt(s) "
              f"({k['reloc_ms_median']:.0f} ms median), then ok {100 * k['ok_rate']:.0f} % of 50, "
              f"wrong ok {k['wrong_ok']}")
    print(f"relocalization from nothing, every {args.reloc_step}th frame:")
    tot = {"attempts": 0, "ok": 0, "wrong": 0}
    for name in runs:
        lines, truth, _, _, _ = load_lines(args.work / name, params)
        r = reloc_sweep(orp, lines, truth, args.reloc_step, params, rparams)
        out["reloc"][name] = r
        for key in tot:
            tot[key] += r[key]
        print(f"  {name:10s} {r['ok']:4d} / {r['attempts']:4d} ok ({100 * r['success_rate']:.1f} %), ambiguous "
              f"{r['ambiguous']}, lost {r['lost']}, wrong (> 10 cm) {r['wrong']}; median error "
              f"{r['error_median_cm']:.2f} cm; {r['ms_median']:.0f} ms median, {r['ms_max']:.0f} ms max wall "
              f"({r['cpu_ms_median']:.0f} ms CPU median)")
    out["reloc"]["total"] = tot
    print(f"  all runs: {tot['ok']} / {tot['attempts']} ({100 * tot['ok'] / max(tot['attempts'], 1):.1f} %), "
          f"wrong fixes {tot['wrong']} (target 0)")
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
