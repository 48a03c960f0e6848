"""Benchmark of the route panorama build: 3 runs of a route -> one versioned ORP.

Simulates 3 runs of the default 20.3 m loop (`mosaicmap simulate omni`, frames every 2 cm,
1 % odometry drift; the second and third with `--world` the first, the third 10 cm to the
left of it, `--offset 0.1`) and a held-out fourth run, builds the three into a map repository
(`mosaicmap build`, all stages at a 1 cm map pixel: the floor from the bird's-eye views, the
route from the floor's optimized poses; `--routes-only`: stages ingest, orp, publish, the
route from odometry)
and prints the route's pose errors against the simulator's truth (after a rigid alignment),
the registration figures, the stored bytes per km (zstd chunks as stored in the repository)
and the time. Then the held-out run is localized frame by frame (tracking: first prior its
odometry start moved by (+5 cm, -5 cm, +2 deg), then the last fix composed with odometry)
with tracker.orp.ORPLocalizer on (a) the built route read back with mapstore.routes.read_route
and (b) an ORP of the first run's frames at their ground-truth poses, and prints the position
error of each. The map's world frame is the first run's odometry frame corrected by the
optimization: it differs from the simulator's by what is left of the odometry drift, so the
errors are given after a rigid SE(2) alignment of the estimates onto the truth (and raw).

Horizon files: ingest writes them (OMNI-INGEST); `--ingest fixture` (or a failing ingest)
writes them here instead, in the contract's format (frames decoded, tracker.orp.HorizonSampler,
odometry interpolated at the frame times).

    python bench/bench_orp_build.py [--work DIR] [--ingest real|fixture] [--routes-only] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mapstore.grid import interpolate_trajectory, se2_between, se2_compose, wrap_angle  # noqa: E402
from pipeline.drivelog import read_drive_log, read_pose_csv  # noqa: E402
from pipeline.evaluate import align_se2  # noqa: E402
from tracker.orp import ORP, HorizonSampler, ORPLocalizer, build_orp  # noqa: E402

RUNS = {  # name: simulate options
    "r1": ["--seed", "11", "--odometry-drift", "0.01"],
    "r2": ["--seed", "12", "--odometry-drift", "0.01"],
    "r3": ["--seed", "13", "--odometry-drift", "0.01", "--offset", "0.1"],
    "held": ["--seed", "14", "--odometry-drift", "0.01"],
}


def simulate(work: Path) -> None:
    from click.testing import CliRunner

    from pipeline.cli import cli

    for name, opts in RUNS.items():
        out = work / name
        if (out / "drive.toml").is_file():
            continue
        world = [] if name == "r1" else ["--world", str(work / "r1")]
        r = CliRunner().invoke(cli, ["simulate", "omni", str(out), "--quiet", *opts, *world])
        if r.exit_code != 0:
            raise SystemExit(r.output)


def fixture_horizons(log_dirs: list[Path], out: Path, cfg: dict, route_id: str) -> None:
    """Contract 2's horizon files written straight from the logs (no floor ingest)."""
    from pipeline.omni_ingest import write_log_horizons

    for k, d in enumerate(log_dirs):
        write_log_horizons(read_drive_log(d), out / f"{k:03d}.npz", cfg["tracker"]["orp"], route_id)


def build(work: Path, logs: list[Path], mode: str, floor: bool) -> tuple[dict, str]:
    """Build the logs into WORK/map (fresh); returns (report, ingest mode used). ``floor``: all
    stages at a 1 cm map pixel (the bird's-eye views' ground pixel is 1.7 cm), the routes from
    the floor's optimized poses; else routes only from odometry (stages ingest, orp, publish)."""
    import pipeline.stages.build as b
    from pipeline.config import load_config

    cfg = load_config(None)
    if floor:
        cfg["map"]["pixel_size_m"] = 0.01
    else:
        cfg["build"]["stages"] = ["ingest", "publish"]  # routes only (orp is added after ingest)
    for d in ("w", "map"):
        shutil.rmtree(work / d, ignore_errors=True)
    if mode == "real":
        try:
            rep = b.run_build(logs, work / "w", cfg, quiet=True, map_url=str(work / "map"), tag="bench")
            if rep.get("orp"):
                return rep, "real"
            print("ingest wrote no horizon files: falling back to the fixture")
        except Exception as e:  # noqa: BLE001 - a bench: say why and go on with the fixture
            print(f"real ingest failed ({type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}): "
                  "falling back to the fixture")
        for d in ("w", "map"):
            shutil.rmtree(work / d, ignore_errors=True)

    def fake(ws, params):
        fixture_horizons([lg.path for lg in params.build.logs], ws.horizons_dir, params.cfg, "loop")
        return {"ingest": {"frames_total": 0}}

    saved = b.STAGES["ingest"]
    b.STAGES["ingest"] = replace(saved, run=fake)
    try:
        return b.run_build(logs, work / "w", cfg, quiet=True, map_url=str(work / "map"), tag="bench"), "fixture"
    finally:
        b.STAGES["ingest"] = saved


def stored_bytes(repo_dir: Path, route_id: str) -> int:
    """Bytes of /routes/<id>'s chunks as stored in the repository (compressed)."""
    from zarr.core.sync import sync

    from mapstore.repository import MapRepository

    store = MapRepository.open(str(repo_dir)).readonly().store

    async def total() -> int:
        n = 0
        async for key in store.list_prefix(f"routes/{route_id}/"):
            if "/c/" in key:
                n += await store.getsize(key)
        return n

    return int(sync(total()))


def route_truth(work: Path, route_id: str, ref_log: Path, orp: ORP) -> np.ndarray:
    """The true pose ``(M, 3)`` of every row of the built route: row ``s`` is where the
    reference run's optimized path (``WORKDIR/orp/runs.csv``, kept frames) reaches path length
    ``s``; its truth there is the reference run's ground truth at that (fractional) frame."""
    from mapstore.grid import se2_interpolate
    from tracker.orp import path_length

    rows = np.genfromtxt(work / "w" / "orp" / "runs.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    sel = (rows["route"] == route_id) & (rows["log_id"] == ref_log.name)
    frame = rows["frame"][sel].astype(float)
    s_k = path_length(np.column_stack([rows["x"][sel], rows["y"][sel], rows["theta"][sel]]))
    lg = read_drive_log(ref_log)
    truth = interpolate_trajectory(read_pose_csv(ref_log / "ground_truth.csv"), lg.frame_t)
    f = np.interp(orp.s, s_k, frame)
    i = np.clip(np.floor(f).astype(int), 0, len(truth) - 2)
    return se2_interpolate(truth[i], truth[i + 1], f - i)


def track(orp: ORP, log_dir: Path, spd: float, row_truth: np.ndarray | None = None) -> dict:
    """Localize every frame of a log on ``orp`` (tracking); errors raw, after a rigid
    alignment, and (with ``row_truth``, the true pose of every ORP row) relative to the route:
    each estimate carried from its nearest route row's map pose to that row's true pose."""
    from pipeline.config import load_config
    from pipeline.stages.orp import orp_params

    cfg = load_config(None)
    params = orp_params(cfg)
    lg = read_drive_log(log_dir)
    hs = HorizonSampler(lg.camera.omni, params.samples_per_degree, params.horizon_band_deg, params.oversample)
    truth = interpolate_trajectory(read_pose_csv(log_dir / "ground_truth.csv"), lg.frame_t)
    odo = interpolate_trajectory(lg.odometry, lg.frame_t)
    loc = ORPLocalizer(orp, params)
    est = np.empty((len(odo), 3))
    prior = se2_compose(odo[0], np.array([0.05, -0.05, math.radians(2.0)]))
    t0 = time.perf_counter()
    ok = 0
    for i in range(len(odo)):
        fix = loc.localize(hs.line(cv2.imread(str(lg.image_path(i)), cv2.IMREAD_GRAYSCALE)), prior)
        est[i] = fix.pose
        ok += fix.ok
        if i + 1 < len(odo):
            prior = se2_compose(fix.pose, se2_between(odo[i], odo[i + 1]))
    secs = time.perf_counter() - t0
    raw = np.hypot(*(est[:, :2] - truth[:, :2]).T)
    r, t = align_se2(est[:, :2], truth[:, :2])
    d = np.linalg.norm(est[:, :2] @ r.T + t - truth[:, :2], axis=1)
    h = np.degrees(np.abs(wrap_angle(est[:, 2] + math.atan2(r[1, 0], r[0, 0]) - truth[:, 2])))
    rel = {}
    if row_truth is not None:
        from pipeline.orp_register import project_on_path

        s_e, _, _ = project_on_path(orp.poses.astype(float), orp.s, est[:, :2])
        r = np.clip((s_e - orp.s0) / orp.spacing_m, 0, len(orp.s) - 1.000001)
        i = r.astype(int)
        from mapstore.grid import se2_interpolate

        mp = se2_interpolate(orp.poses[i].astype(float), orp.poses[i + 1].astype(float), r - i)
        tp = se2_interpolate(row_truth[i], row_truth[i + 1], r - i)
        carried = se2_compose(tp, se2_between(mp, est))
        e = np.hypot(*(carried[:, :2] - truth[:, :2]).T)
        rel = {"route_mean_m": float(e.mean()), "route_rms_m": float(np.sqrt((e**2).mean())), "route_max_m": float(e.max()),
               "route_heading_mean_deg": float(np.degrees(np.abs(wrap_angle(carried[:, 2] - truth[:, 2]))).mean())}
    return {**rel, "frames": int(len(odo)), "ok": int(ok), "mean_m": float(d.mean()), "rms_m": float(np.sqrt((d**2).mean())),
            "max_m": float(d.max()), "raw_mean_m": float(raw.mean()), "raw_max_m": float(raw.max()),
            "heading_mean_deg": float(h.mean()), "ms_per_frame": 1000 * secs / len(odo)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/mosaicmap-bench-orp-build"))
    ap.add_argument("--ingest", choices=("real", "fixture"), default="real")
    ap.add_argument("--routes-only", action="store_true",
                    help="leave the floor stages out: the routes from odometry alone")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    args.work.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    simulate(args.work)
    print(f"simulated {', '.join(RUNS)} in {args.work} ({time.perf_counter() - t:.0f} s)")
    logs = [args.work / n for n in ("r1", "r2", "r3")]
    t = time.perf_counter()
    rep, mode = build(args.work, logs, args.ingest, not args.routes_only)
    wall = time.perf_counter() - t
    o = rep["orp"]
    reg = o["registration"]
    print(f"build ({mode} ingest, stages {', '.join(rep['stages'])}): {wall:.1f} s wall, ingest "
          f"{rep['stages']['ingest']['seconds']:.1f} s, orp stage {o['seconds']:.1f} s; route priors: {o['priors']}; "
          f"published version {rep['publish']['version']} ({rep['publish']['tag']})")
    if "ground_truth" in rep:
        print(f"floor poses vs truth: RMS {rep['ground_truth']['pose_rms_px'] * 0.01 * 100:.3f} cm")
    print(f"registration (all routes): fixes {reg['fixes_accepted']} / {reg['fixes_tried']} accepted, NCC median "
          f"{reg['ncc_median']:.3f}, loop closures {reg['loop_closures']}")
    for route in o["routes"]:
        print(f"route {route['id']!r}: {route['runs']} runs, {route['rows']} rows, {route['length_m']:.2f} m; "
              f"reference {route['registration']['reference']}; rows fed per run {route['rows_fed']}")
        for r in route["registration"]["runs"]:
            print(f"  {r['log_id']}: coarse offset {r['coarse_offset_m']:+.3f} m, heading {r['coarse_heading_deg']:+.2f} deg, "
                  f"NCC {r['coarse_ncc']:.3f}; fixes {r['fixes_accepted']} / {r['fixes_tried']}")
        gt = route.get("ground_truth")
        if gt:
            print(f"  route poses vs truth (rigid alignment): RMS {gt['pose_rms_m'] * 100:.2f} cm, max "
                  f"{gt['pose_max_m'] * 100:.2f} cm, heading RMS {gt['heading_rms_deg']:.3f} deg "
                  f"(odometry alone: RMS {gt['odometry_rms_m'] * 100:.2f} cm)")
    route = next(r for r in o["routes"] if "r1" in r["rows_fed"])
    rid = route["id"]
    import zarr

    from mapstore.repository import MapRepository
    from mapstore.routes import read_route

    root = zarr.open_group(MapRepository.open(str(args.work / "map")).readonly().store, mode="r")
    rec = read_route(root, rid)
    nbytes = stored_bytes(args.work / "map", rid)
    print(f"stored: {nbytes} bytes compressed = {nbytes / rec.length_m * 1000 / 1e6:.2f} MB/km at {rec.spacing_m:g} m, "
          f"{rec.samples_per_degree:g} sample/deg (uncompressed {(rec.lines.nbytes + rec.poses.nbytes) / rec.length_m * 1000 / 1e6:.2f} MB/km)")
    built = ORP(rec.lines, rec.poses, rec.s0_m, rec.spacing_m, rec.samples_per_degree)
    # the ground-truth ORP: the first run's lines at its true poses
    from pipeline.config import load_config
    from pipeline.stages.orp import orp_params

    params = orp_params(load_config(None))
    lg = read_drive_log(logs[0])
    hs = HorizonSampler(lg.camera.omni, params.samples_per_degree, params.horizon_band_deg, params.oversample)
    lines = hs.lines(cv2.imread(str(lg.image_path(i)), cv2.IMREAD_GRAYSCALE) for i in range(len(lg.frame_images)))
    truth = interpolate_trajectory(read_pose_csv(logs[0] / "ground_truth.csv"), lg.frame_t)
    gt_orp = build_orp(lines, truth, params.spacing_m, params.samples_per_degree)
    out = {"build": {"mode": mode, "wall_s": wall, "orp": o}, "stored_bytes": nbytes,
           "stored_mb_per_km": nbytes / rec.length_m * 1000 / 1e6, "held_out": {}}
    print("held-out run localized (tracking): errors after a rigid alignment [raw]; relative to the route "
          "(each fix carried from its route row's map pose to that row's true pose)")
    row_truth = route_truth(args.work, rid, logs[0], built)
    for name, orp, rt in (("built route", built, row_truth), ("ground-truth ORP", gt_orp, gt_orp.poses.astype(float))):
        r = track(orp, args.work / "held", params.samples_per_degree, rt)
        out["held_out"][name] = r
        print(f"  {name:17s} aligned mean {r['mean_m'] * 100:.2f} cm, RMS {r['rms_m'] * 100:.2f} cm, max "
              f"{r['max_m'] * 100:.2f} cm [raw mean {r['raw_mean_m'] * 100:.2f} cm, max {r['raw_max_m'] * 100:.2f} cm]; "
              f"heading mean {r['heading_mean_deg']:.3f} deg; ok {r['ok']}/{r['frames']}; {r['ms_per_frame']:.1f} ms/frame")
        print(f"  {'':17s} relative to the route: mean {r['route_mean_m'] * 100:.2f} cm, RMS {r['route_rms_m'] * 100:.2f} cm, "
              f"max {r['route_max_m'] * 100:.2f} cm, heading mean {r['route_heading_mean_deg']:.3f} deg "
              f"(target mean <= 1 cm: {'met' if r['route_mean_m'] <= 0.01 else 'NOT met'})")
    if args.json:
        args.json.write_text(json.dumps(out, indent=2, default=float))


if __name__ == "__main__":
    main()
