"""Benchmark of the vehicle-side tracker: `mosaicmap track` on held-out logs.

A 20 x 20 m world at 2.5 mm (``--area``) is simulated (seed 1). Its texture is published as
the **reference map** (:func:`pipeline.testing.synthmap.publish_raster`: the map a perfect build
would make, so that the tracker's own errors are measured against the simulator's ground
truth) and exported as a bundle (every level, the relocalization index). "Operations" logs
over the same world (``--world``), on another route (``--route``, default figure8), 20 %
darker, are replayed with ``mosaicmap track`` in a child process:

1. **held-out**, sensor noise sigma 10: error RMS (target <= 0.1 px), ok rate (>= 99.5 %),
   wrong ok (ok fixes off by > 2 px: target 0), fixes/s and latency p50 / p99 of the fixes
   (the tracker's own time, one thread; the +-2 cm speed target is measured by
   ``bench/bench_tracker_speed.py``);
2. **noise 40**: wrong ok must stay 0 (the tracker may say ambiguous or lost);
3. **kidnapped**: the first ``--kidnap-frames`` frames started 5 m off (a confident wrong
   prior) and with no prior at all: frames until the first ok fix, relocalization time
   (target < 1 s), wrong ok;
4. **low texture**: the held-out log with ``--bland`` frames in its middle replaced by
   bare floor (uniform grey, sensor noise): statuses along the stretch, whether it ended
   in ``lost``, the frames until recovery after it, wrong ok;
5. **off the map**: the held-out log against a bundle of the west half of the floor
   (``export --region``): frames in relative mode (frame to frame), its error growth per
   metre against the odometry's, wrong ok;
6. with ``--with-build``: day 1 is a lawnmower drive built into a map by the pipeline
   (~20 min at 20 x 20 m), and the held-out log is tracked against that map too; its errors
   against the ground truth then include the map's own (the build's pose error is printed
   beside them).

Data goes to ``--out`` (deleted at the end unless ``--keep``; ``--reuse`` takes a kept map
and logs of the same parameters). Wall clock on a possibly busy 2-core machine: figures,
not assertions.

    python bench/bench_tracker.py [--area 20] [--route figure8] [--with-build] [--out /tmp/bench_tracker]
                                  [--keep] [--reuse] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import numpy as np

from runner import child, mosaicmap, reusable, run_cli

RMS_MAX_PX = 0.1
OK_RATE_MIN = 0.995
RELOC_MAX_S = 1.0


_REFERENCE = r"""
import json, sys, time
from mapstore.grid import MapGrid
from pipeline.config import load_config
from pipeline.simulate.texture import read_float_tiff
from pipeline.testing.synthmap import publish_raster, texture_tile_fn
world, url = sys.argv[1], sys.argv[2]
g = json.load(open(world + "/grid.json"))
grid = MapGrid(g["x0_m"], g["y0_m"], g["pixel_size_m"], g["width_px"], g["height_px"])
t0 = time.perf_counter()
sid = publish_raster(url, grid, texture_tile_fn(read_float_tiff(world + "/texture.tif"), grid), cfg=load_config(None),
                     tag="reference", message="the simulator's world texture as a map")
print(json.dumps({"snapshot": sid, "seconds": time.perf_counter() - t0}))
"""


def build_site(out: Path, area: float, route: str, reuse: bool, with_build: bool) -> dict:
    """The world (a day-1 log), the reference map published from it and exported, the
    held-out logs; with ``with_build`` also day 1 built into a map by the pipeline."""
    params = {"area": area, "route": route, "with_build": with_build, "version": 2}
    marker = out / "site.json"
    if reusable(marker, params, reuse):
        return json.loads(marker.read_text())["info"]
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    t0 = time.perf_counter()
    # day 1: the world (and, with --with-build, the drive that maps it)
    day1 = ["--route", "lawnmower"] if with_build else ["--route", "random"]
    run_cli("simulate", "floor", out / "day1", "--seed", "1", "--area", f"{area:g}x{area:g}", *day1, "--quiet")
    info: dict = {"simulate_s": time.perf_counter() - t0}
    ref = child(_REFERENCE, out / "day1" / "world", out / "reference")
    export = mosaicmap(out / "export.json", "export", out / "reference", out / "reference.zip")
    half = area / 2
    mosaicmap(out / "export_west.json", "export", out / "reference", out / "west.zip", "--region",
              f"-1,-1,{half:g},{area + 1:g}")
    info.update({"reference_publish_s": ref["seconds"], "bundle_mb": export["bytes"] / 1e6,
                 "export_s": export["seconds"], "reloc_index": export.get("reloc_index")})
    if with_build:
        build = mosaicmap(out / "build.json", "build", out / "day1", "--map", out / "built", "-w", out / "work1",
                          "--tag", "day1")
        mosaicmap(out / "export_built.json", "export", out / "built", out / "built.zip")
        info["build"] = {"seconds": build["seconds_total"], "frames": build["ingest"]["frames_total"],
                         "pairs_per_s": build["registration"]["pairs_per_s"],
                         "pose_rms_px": build["ground_truth"]["pose_rms_px"],
                         "pose_max_px": build["ground_truth"]["pose_max_px"]}
    for name, noise, seed in (("ops10", 10, 31), ("ops40", 40, 32)):
        run_cli("simulate", "floor", out / name, "--world", out / "day1", "--route", route, "--noise", str(noise),
                "--illumination", "0.8", "--seed", str(seed), "--quiet")
    marker.write_text(json.dumps({"params": params, "info": info}))
    return info


def bland_copy(src: Path, dst: Path, first: int, count: int, seed: int = 5) -> None:
    """A copy of log ``src`` whose frames ``first .. first + count - 1`` show bare floor
    (uniform grey 120 with the simulator's sensor noise sigma 10): a long low-texture stretch."""
    import cv2

    if dst.exists():
        shutil.rmtree(dst)
    from pipeline.fsutil import link_tree

    link_tree(src, dst)  # hard links: a log's files must not lead outside it ([ingest] follow_symlinks)
    frames = (src / "frames.csv").read_text().splitlines()[1:]
    rng = np.random.default_rng(seed)
    for line in frames[first : first + count]:
        image = dst / line.split(",")[1]
        raw = cv2.imread(str(src / line.split(",")[1]), cv2.IMREAD_UNCHANGED)
        bare = np.clip(np.rint(120 + rng.normal(0, 10, raw.shape)), 0, 255).astype(raw.dtype)
        image.unlink()
        cv2.imwrite(str(image), bare)


def track(out: Path, name: str, bundle: Path, log: Path, *extra) -> dict:
    return mosaicmap(out / f"track_{name}.json", "track", bundle, log, "--insecure", "--plot", out / f"track_{name}.png",
                     *extra)  # unsigned bench bundles


def first_pose(log: Path, column_offset=(0.0, 0.0, 0.0)) -> str:
    row = (log / "odometry.csv").read_text().splitlines()[1].split(",")
    x, y, th = (float(v) + o for v, o in zip(row[1:4], column_offset))
    return f"{x!r},{y!r},{th!r}"


def run(out: Path, area: float, route: str, reuse: bool, kidnap_frames: int, bland: int, with_build: bool) -> dict:
    site = build_site(out, area, route, reuse, with_build)
    ref = out / "reference.zip"
    res: dict = {"site": site}
    res["held_out"] = track(out, "held_out", ref, out / "ops10")
    res["noise40"] = track(out, "noise40", ref, out / "ops40")
    n = res["held_out"]["fixes"]
    res["kidnapped_5m"] = track(out, "kidnapped", ref, out / "ops10", "--frames", f"0:{kidnap_frames}",
                                "--start", first_pose(out / "ops10", (5.0, 0.0, 0.3)))
    res["no_prior"] = track(out, "no_prior", ref, out / "ops10", "--frames", f"0:{kidnap_frames}", "--start", "none")
    first = n // 3
    bland_copy(out / "ops10", out / "ops10_bland", first, bland)
    low = track(out, "bland", ref, out / "ops10_bland", "--poses", out / "bland_poses.csv")
    rows = [line.split(",") for line in (out / "bland_poses.csv").read_text().splitlines()[1:]]
    status, mode = [r[4] for r in rows], [r[5] for r in rows]
    after = next((k for k in range(first + bland, len(rows)) if status[k] == "ok"), None)
    stretch = status[first : first + bland]
    low["stretch"] = {"first": first, "frames": bland, "statuses": {s: stretch.count(s) for s in set(stretch)},
                      "ended_lost": "lost" in stretch,
                      "first_lost": next((k for k, s in enumerate(stretch) if s == "lost"), None),
                      "recovered_after_frames": None if after is None else after - (first + bland),
                      "recovered_by": None if after is None else mode[after]}
    res["low_texture"] = low
    res["off_map"] = track(out, "off_map", out / "west.zip", out / "ops10")
    if with_build:
        res["built_map"] = track(out, "built", out / "built.zip", out / "ops10", "--poses", out / "built_poses.csv")
    return res


def _f(v, fmt=".3f") -> str:
    return "n/a" if v is None else format(v, fmt)


def print_results(res: dict) -> None:
    s = res["site"]
    ri = s.get("reloc_index") or {}
    print(f"reference map: the world texture published as a map ({s['reference_publish_s']:.0f} s), bundle "
          f"{s['bundle_mb']:.1f} MB exported in {s['export_s']:.1f} s (reloc index {ri.get('features')} features)")
    h = res["held_out"]
    print("\n1. held-out log (another route, noise 10, 20 % darker)")
    print(f"   frames {h['fixes']}, ok rate {100 * h['ok_rate']:.2f} % (target >= {100 * OK_RATE_MIN:.1f} %), "
          f"statuses {h['statuses']}")
    print(f"   error RMS {_f(h['error_rms_px'])} px (target <= {RMS_MAX_PX}), median {_f(h['error_median_px'])}, "
          f"max ok {_f(h['error_max_ok_px'])} px, heading RMS {_f(h['heading_error_rms_deg'])} deg; "
          f"wrong ok {h['wrong_ok']} (target 0)")
    lat = h["latency_ms"]
    print(f"   {_f(h['fixes_per_s'], '.0f')} fixes/s, latency p50 {_f(lat['p50'], '.2f')} ms, "
          f"p99 {_f(lat['p99'], '.2f')} ms, max {_f(lat['max'], '.2f')} ms (wall clock); in CPU time "
          f"{_f(h['cpu_fixes_per_s'], '.0f')} fixes/s, p50 {_f(h['cpu_latency_ms']['p50'], '.2f')} ms, p99 "
          f"{_f(h['cpu_latency_ms']['p99'], '.2f')} ms; relocalizations {h['relocalizations']}; index ready in "
          f"{h['index_seconds']:.2f} s; command {h['wall_seconds']:.1f} s")
    k = res["noise40"]
    print(f"\n2. noise 40: ok rate {100 * k['ok_rate']:.2f} %, statuses {k['statuses']}, wrong ok {k['wrong_ok']} "
          f"(target 0), error RMS {_f(k['error_rms_px'])} px, max ok {_f(k['error_max_ok_px'])} px")
    print("\n3. kidnapped")
    for name in ("kidnapped_5m", "no_prior"):
        r = res[name]
        rl = r["relocalization"]
        print(f"   {name}: {r['fixes']} frames, relocalizations {r['relocalizations']} of {rl['attempts']} attempts "
              f"(median {_f(rl['seconds_median'], '.2f')} s, max {_f(rl['seconds_max'], '.2f')} s; target < "
              f"{RELOC_MAX_S:g} s), statuses {r['statuses']}, wrong ok {r['wrong_ok']}, error RMS "
              f"{_f(r['error_rms_px'])} px")
    lo = res["low_texture"]
    st = lo["stretch"]
    print(f"\n4. low texture: {st['frames']} bare frames from frame {st['first']}: statuses {st['statuses']}; "
          f"lost {'after ' + str(st['first_lost']) + ' frames' if st['ended_lost'] else 'never'}; recovered "
          f"{'never' if st['recovered_after_frames'] is None else str(st['recovered_after_frames']) + ' frame(s) after the stretch by ' + st['recovered_by']}; "
          f"relocalizations {lo['relocalizations']}; wrong ok {lo['wrong_ok']}")
    om = res["off_map"]
    rel = om.get("relative") or {}
    print(f"\n5. off the map (bundle of the west half): statuses {om['statuses']}, poses from {om['modes']}; "
          f"relative mode {rel.get('frames', 0)} frames over {_f(rel.get('length_m'), '.1f')} m in "
          f"{len(rel.get('stretches', []))} stretch(es), error growth "
          f"{_f(None if rel.get('error_growth_per_m') is None else 100 * rel['error_growth_per_m'], '.2f')} % of "
          f"distance (odometry error gradient 1 %); wrong ok {om['wrong_ok']}")
    if "built_map" in res:
        b, bm = s["build"], res["built_map"]
        print(f"\n6. the same held-out log against the map the pipeline built from day 1 ({b['frames']} frames, "
              f"{b['seconds']:.0f} s, {b['pairs_per_s']:.0f} pairs/s; its poses vs truth RMS {b['pose_rms_px']:.2f} px, "
              f"max {b['pose_max_px']:.2f} px): ok rate {100 * bm['ok_rate']:.2f} %, statuses {bm['statuses']}; "
              f"vs ground truth RMS {_f(bm['error_rms_px'])} px, median {_f(bm['error_median_px'])} px, max "
              f"{_f(bm['error_max_ok_px'])} px, ok off by > 2 px {bm['wrong_ok']} (the map's own error)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--area", type=float, default=20.0, help="floor side, metres")
    ap.add_argument("--route", default="figure8", help="route of the held-out logs")
    ap.add_argument("--kidnap-frames", type=int, default=60)
    ap.add_argument("--bland", type=int, default=40, help="bare-floor frames of the low-texture run")
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_tracker"))
    ap.add_argument("--keep", action="store_true")
    ap.add_argument("--reuse", action="store_true")
    ap.add_argument("--with-build", action="store_true",
                    help="also build day 1 with the pipeline (lawnmower; ~20 min at 20 x 20 m) and track against it")
    ap.add_argument("--json", type=Path, default=None)
    a = ap.parse_args()
    try:
        res = run(a.out, a.area, a.route, a.reuse, a.kidnap_frames, a.bland, a.with_build)
        print_results(res)
        if a.json:
            a.json.write_text(json.dumps(res, indent=1, default=str))
    finally:
        if not a.keep and a.out.exists():
            shutil.rmtree(a.out)


if __name__ == "__main__":
    main()
