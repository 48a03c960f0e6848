"""Benchmark of ``mosaicmap diff``: detection against the simulator's truth, and speed.

Two scenarios:

1. **Simulated day 1 / day 2.** Day 1: ``mosaicmap simulate floor --area 5x5 --seed
   --day1-seed`` built into a fresh map repository (version 1). Then, per ``--seeds`` N, a
   day 2 over the same world (``--world day1 --changes 5 --illumination 0.8 --route
   ROUTE --seed N``: 5 changes among stains 10-50 cm, repainted patches of 0.7-1.3 m^2
   and new markings, 20 % darker, with the simulator's exposure drift) built incrementally
   onto a copy of the day-1 repository (version 2), and ``mosaicmap diff day1 day2 --truth
   changes.png``. Day 1 is simulated and built once per run (the day-2 builds only read
   the published map, never day 1's work directory). With ``--demo`` the demo map
   (``demo-out/map``, day 2 on a loop route: most changes outside what day 2 saw) is diffed
   too, read-only. Printed per change: kinds, size (cm^2), observed share, detected?, IoU;
   false regions (count, largest cm^2); diff seconds.
   Target: every observed change detected with IoU >= 0.7, no false region > 25 cm^2.
2. **Speed on a large map.** A synthetic ``--area`` x ``--area`` m floor (default 40 x 40 m
   = 16000 x 16000 px, 256 MPix) published with :func:`pipeline.testing.synthmap.publish_raster`;
   version 2 repaints one 1 x 1 m patch (other texture, 25 grey levels brighter; only the
   shards it reaches are rewritten). ``mosaicmap diff v1 v2`` in a fresh process: the diff's
   own seconds (chunk diff, reads, detection, regions) and the command's wall time, peak RSS,
   and the region found against the patch (area ratio, bounding-box IoU). The same on a
   ``--small-area`` (5 x 5 m) map shows the cost does not grow with the map's size.
   Target: < 5 s on 40 x 40 m.

Timings are wall clock on a possibly busy 2-core machine: figures, not assertions. Data
goes to ``--out``; it is deleted at the end unless ``--keep``; ``--reuse`` takes kept
synthetic maps and simulated builds of the same parameters.

    python bench/bench_diff.py [--seeds 11 12 13] [--route lawnmower] [--demo] [--area 40]
                               [--small-area 5] [--skip-sim] [--skip-large] [--out /tmp/bench_diff]
                               [--keep] [--reuse] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from runner import COMMAND, REPO, child, child_env, reusable, run_cli

PATCH_M = 1.0
PATCH_DELTA = 25.0
TEXTURE_PERIOD_PX = 4096
IOU_MIN = 0.7
FALSE_MAX_CM2 = 25.0
DIFF_SECONDS_MAX = 5.0

_PUBLISH = r"""
import json, sys, time
from mapstore.grid import MapGrid
from pipeline.config import load_config
from pipeline.stages.render import layer_halo_px
from pipeline.testing.synthmap import Patch, periodic_texture, publish_raster, shards_for_box, texture_tile_fn
url, area, version, side, delta, period = sys.argv[1], float(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4]), float(sys.argv[5]), int(sys.argv[6])
cfg = load_config(None)
px = cfg["simulate"]["floor"]["pixel_size_m"]
n = int(round(area / px))
grid = MapGrid(0.0, (n - 1) * px, px, n, n)
tex = periodic_texture(11, period)
c = area / 2 + 0.3
patch = Patch(c, c, c + side, c + side, delta=delta)
t0 = time.perf_counter()
if version == 1:
    sid = publish_raster(url, grid, texture_tile_fn(tex, grid), cfg=cfg, tag="v1")
else:
    shards = shards_for_box(grid, cfg["map"]["shard_px"], patch.x0, patch.y0, patch.x1, patch.y1,
                            pad_px=layer_halo_px(cfg["render"]))
    sid = publish_raster(url, grid, texture_tile_fn(tex, grid, [patch]), cfg=cfg, tag="v2", shards=shards)
print(json.dumps({"snapshot": sid, "seconds": time.perf_counter() - t0, "grid": grid.to_attrs(),
                  "patch_box_px": list(patch.pixel_box(grid)), "patch_m": [patch.x0, patch.y0, patch.x1, patch.y1]}))
"""

def diff(report: Path, *args) -> dict:
    """``mosaicmap diff ...`` in a child writing ``report``: the report plus wall time and peak RSS."""
    run = child(COMMAND, "diff", *args, "--report", report, "--quiet")
    return {**json.loads(report.read_text()), "run": run}


# --- scenario 1: simulated pairs ----------------------------------------------------------------


def simulated(out: Path, seeds: list[int], route: str, day1_seed: int, reuse: bool) -> list[dict]:
    """Day 1 once, day 2 per seed; the diff of each against the simulator's truth."""
    day1 = out / "day1"
    params1 = {"seed": day1_seed, "area": "5x5"}
    if not reusable(out / "day1.json", params1, reuse):
        shutil.rmtree(out, ignore_errors=True)
        out.mkdir(parents=True)
        t = time.perf_counter()
        print(f"day 1: simulate 5 x 5 m (seed {day1_seed}) and build ...", flush=True)
        run_cli("simulate", "floor", day1, "--area", "5x5", "--seed", day1_seed, "--quiet")
        run_cli("build", day1, "--map", out / "map1", "-w", out / "w1", "--tag", "day1", "--quiet")
        (out / "day1.json").write_text(json.dumps({"params": params1, "seconds": time.perf_counter() - t}))
        print(f"  {time.perf_counter() - t:.0f} s", flush=True)
    results = []
    for seed in seeds:
        d = out / f"seed{seed}"
        params2 = {"day1": params1, "seed": seed, "route": route}
        if not reusable(d / "built.json", params2, reuse):
            shutil.rmtree(d, ignore_errors=True)
            d.mkdir(parents=True)
            t = time.perf_counter()
            print(f"day 2 seed {seed}: simulate ({route}, 5 changes, illumination 0.8) and build onto day 1 ...",
                  flush=True)
            shutil.copytree(out / "map1", d / "map")
            run_cli("simulate", "floor", d / "day2", "--world", day1, "--route", route, "--changes", 5,
                    "--illumination", 0.8, "--seed", seed, "--quiet")
            run_cli("build", d / "day2", "--map", d / "map", "-w", d / "w2", "--tag", "day2", "--quiet")
            (d / "built.json").write_text(json.dumps({"params": params2, "seconds": time.perf_counter() - t}))
            print(f"  {time.perf_counter() - t:.0f} s", flush=True)
        rep = diff(d / "diff.json", d / "map", "day1", "day2", "--truth", d / "day2" / "world" / "changes.png",
                   "--out", d / "out")
        results.append(_scenario(f"seed {seed} ({route})", rep))
    return results


def demo(out: Path) -> dict | None:
    """The demo map (read-only), if present."""
    url = REPO / "demo-out" / "map"
    truth = REPO / "demo-out" / "logs" / "day2" / "world" / "changes.png"
    if not (url.is_dir() and truth.is_file()):
        print("demo-out/map not found (make demo): skipped", flush=True)
        return None
    out.mkdir(parents=True, exist_ok=True)
    tags = sorted(json.loads(subprocess.run(
        [sys.executable, "-c", "import json; from mapstore.repository import MapRepository; "
         f"print(json.dumps(list(MapRepository.open({str(url)!r}).tags())))"],
        capture_output=True, text=True, cwd=REPO, env=child_env(), check=True).stdout))
    tags = [t for t in tags if not t.startswith("rollback-")]
    if len(tags) < 2:
        print("demo-out/map has fewer than two tagged versions: skipped", flush=True)
        return None
    rep = diff(out / "demo.json", url, tags[0], tags[1], "--truth", truth, "--out", out / "demo")
    return _scenario(f"demo {tags[0]} -> {tags[1]} (loop)", rep)


def _scenario(name: str, rep: dict) -> dict:
    t = rep["truth"]
    observed = [c for c in t["changes"] if c["status"] != "unobserved"]
    ok_changes = all(c["status"] == "detected" and (c["iou"] or 0) >= IOU_MIN for c in observed)
    ok_false = t["summary"]["max_false_area_cm2"] <= FALSE_MAX_CM2
    return {"name": name, "changes": t["changes"], "false_regions": t["false_regions"],
            "summary": t["summary"], "alignment": t["alignment"], "regions": rep["summary"]["regions"],
            "ignored_smooth": rep["summary"]["ignored_smooth"], "diff_seconds": rep["seconds"]["total"],
            "command_seconds": rep["run"]["wall_seconds"], "hwm_mb": rep["run"]["hwm_mb"],
            "targets": {"observed_detected_iou": ok_changes, "no_false_over_25cm2": ok_false}}


def print_scenario(s: dict) -> None:
    print(f"{s['name']}: {s['regions']} region(s), {s['ignored_smooth']} smooth difference(s) ignored; diff "
          f"{s['diff_seconds']:.2f} s (command {s['command_seconds']:.2f} s, peak RSS {s['hwm_mb']:.0f} MB); "
          f"alignment {s['alignment']['source']}")
    for c in s["changes"]:
        iou = "-" if c["iou"] is None else f"{c['iou']:.3f}"
        print(f"  change {c['id']}: {'+'.join(c['kinds']) or '?':24} {c['area_m2'] * 1e4:8.1f} cm^2  observed "
              f"{c['observed_fraction']:4.0%}  {c['status']:10}  IoU {iou}")
    f = s["false_regions"]
    print(f"  false regions: {len(f)}" + (f", largest {max(x['area_m2'] for x in f) * 1e4:.1f} cm^2" if f else ""))


# --- scenario 2: speed on a large map -----------------------------------------------------------


def synthetic(out: Path, area: float, reuse: bool) -> dict:
    """Publish (or reuse) the two-version synthetic map; diff it in a fresh process."""
    url = out / "map"
    params = {"area": area, "patch_m": PATCH_M, "delta": PATCH_DELTA, "period": TEXTURE_PERIOD_PX}
    if reusable(out / "published.json", params, reuse):
        pub = json.loads((out / "published.json").read_text())["publish"]
        print(f"reusing the {area:g} x {area:g} m map at {url}", flush=True)
    else:
        shutil.rmtree(out, ignore_errors=True)
        out.mkdir(parents=True)
        print(f"publishing a {area:g} x {area:g} m synthetic map (version 1, whole) ...", flush=True)
        v1 = child(_PUBLISH, url, area, 1, PATCH_M, PATCH_DELTA, TEXTURE_PERIOD_PX, prelude=False)
        print(f"  {v1['seconds']:.1f} s; version 2 (a {PATCH_M:g} x {PATCH_M:g} m repaint) ...", flush=True)
        v2 = child(_PUBLISH, url, area, 2, PATCH_M, PATCH_DELTA, TEXTURE_PERIOD_PX, prelude=False)
        print(f"  {v2['seconds']:.1f} s", flush=True)
        pub = {"v1": v1, "v2": v2}
        (out / "published.json").write_text(json.dumps({"params": params, "publish": pub}, indent=2) + "\n")
    rep = diff(out / "diff.json", url, "v1", "v2")
    rep_out = diff(out / "diff_out.json", url, "v1", "v2", "--out", out / "out")
    r0, r1, c0, c1 = pub["v2"]["patch_box_px"]
    patch_px = (r1 - r0) * (c1 - c0)
    best = max(rep["regions"], key=lambda r: r["area_m2"], default=None)
    iou = area_ratio = None
    if best is not None:
        a0, a1, b0, b1 = best["bbox_px"]
        inter = max(0, min(a1, r1) - max(a0, r0)) * max(0, min(b1, c1) - max(b0, c0))
        iou = inter / ((a1 - a0) * (b1 - b0) + patch_px - inter)
        area_ratio = best["area_m2"] / (patch_px * pub["v1"]["grid"]["pixel_size_m"] ** 2)
    n = pub["v1"]["grid"]["width_px"]
    return {"area_m": area, "px": n, "mpix": n * n / 1e6, "publish": pub, "regions": len(rep["regions"]),
            "tiles": {k: rep["tiles"][k] for k in ("shards_changed", "rewritten", "identical", "changed")},
            "diff_seconds": rep["seconds"], "command_seconds": rep["run"]["wall_seconds"],
            "import_seconds": rep["run"]["import_seconds"], "hwm_mb": rep["run"]["hwm_mb"],
            "with_outputs_seconds": rep_out["run"]["wall_seconds"], "with_outputs_hwm_mb": rep_out["run"]["hwm_mb"],
            "region_bbox_iou": iou, "region_area_ratio": area_ratio}


def print_synthetic(s: dict) -> None:
    d = s["diff_seconds"]
    print(f"synthetic {s['area_m']:g} x {s['area_m']:g} m ({s['px']} x {s['px']} px, {s['mpix']:.0f} MPix), "
          f"a {PATCH_M:g} m^2 repaint: diff {d['total']:.2f} s (chunks {d['chunks']:.2f}, read {d['read']:.2f}, "
          f"detect {d['detect']:.2f}, regions {d['regions']:.2f}); command {s['command_seconds']:.2f} s "
          f"(+ {s['import_seconds']:.1f} s imports), peak RSS {s['hwm_mb']:.0f} MB; with --out "
          f"{s['with_outputs_seconds']:.2f} s")
    iou = "-" if s["region_bbox_iou"] is None else f"{s['region_bbox_iou']:.3f}"
    ratio = "-" if s["region_area_ratio"] is None else f"{s['region_area_ratio']:.3f}"
    t = s["tiles"]
    print(f"  tiles: {t['shards_changed']} shard(s), {t['rewritten']} rewritten, {t['identical']} identical, "
          f"{t['changed']} compared; {s['regions']} region(s), largest vs the patch: bbox IoU {iou}, area ratio {ratio}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="*", default=[11, 12, 13], help="Day-2 simulator seeds.")
    ap.add_argument("--route", default="lawnmower", help="Day-2 route (lawnmower sees every change; loop few).")
    ap.add_argument("--day1-seed", type=int, default=1, help="Day-1 simulator seed.")
    ap.add_argument("--demo", action="store_true", help="Also diff demo-out/map (read-only) against its truth.")
    ap.add_argument("--area", type=float, default=40.0, help="Side of the large synthetic map, metres.")
    ap.add_argument("--small-area", type=float, default=5.0, help="Side of the small synthetic map (0 = skip).")
    ap.add_argument("--skip-sim", action="store_true", help="Skip the simulated scenario.")
    ap.add_argument("--skip-large", action="store_true", help="Skip the synthetic speed scenario.")
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_diff"), help="Data directory.")
    ap.add_argument("--keep", action="store_true", help="Keep the data directory.")
    ap.add_argument("--reuse", action="store_true", help="Reuse kept data of the same parameters.")
    ap.add_argument("--json", type=Path, default=None, help="Write the figures to this JSON file.")
    args = ap.parse_args()

    figures: dict = {"cpu_count": os.cpu_count(), "targets": {}}
    try:
        sims: list[dict] = []
        if not args.skip_sim:
            sims = simulated(args.out / "sim", args.seeds, args.route, args.day1_seed, args.reuse) if args.seeds else []
            if args.demo:
                d = demo(args.out / "demo")
                if d:
                    sims.append(d)
            figures["simulated"] = sims
        large = []
        if not args.skip_large:
            for area in [args.area] + ([args.small_area] if args.small_area > 0 else []):
                large.append(synthetic(args.out / f"synth{area:g}", area, args.reuse))
            figures["synthetic"] = large
        print()
        for s in sims:
            print_scenario(s)
        for s in large:
            print_synthetic(s)
        ok = figures["targets"]
        if sims:
            ok["observed_changes_detected_iou_0.7"] = all(s["targets"]["observed_detected_iou"] for s in sims)
            ok["no_false_region_over_25cm2"] = all(s["targets"]["no_false_over_25cm2"] for s in sims)
        if large:
            ok["large_diff_under_5s"] = large[0]["diff_seconds"]["total"] < DIFF_SECONDS_MAX
        print("targets: " + ", ".join(f"{k} {'PASS' if v else 'FAIL'}" for k, v in ok.items()))
        if args.json:
            args.json.write_text(json.dumps(figures, indent=2) + "\n")
            print(f"figures -> {args.json}")
        return 0 if all(ok.values()) else 1
    finally:
        if not args.keep:
            shutil.rmtree(args.out, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
