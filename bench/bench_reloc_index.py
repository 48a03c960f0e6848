"""Benchmark of the relocalization index stored in bundles (``floor/reloc/features``).

On a synthetic ``--area`` x ``--area`` m floor at 2.5 mm (default 20 x 20 m = 8000 x 8000 px,
1024 level-0 tiles of 256 px) published with :func:`pipeline.testing.synthmap.publish_raster`
(:func:`floor_tile_fn`: two seamless periodic textures of 4096 and 2896 px mixed, so that no
place repeats on the floor: with bench/bench_export.py's single 4096-px texture every place
of a 20 m map exists up to 4 times and a global relocalization is rightly ambiguous;
version 2 repaints a 1 x 1 m patch), it prints:

- the full bundle of version 1 (default levels and layers) with and without the index
  (``--no-reloc-index``): bytes, members, export seconds; the index's features, members
  and bytes, and the export time it adds (its feature seconds as the export reports them,
  and the difference of the two exports' wall clock);
- the delta of version 2 since version 1 with and without the index: bytes and index
  chunks carried (the changed tiles and the neighbours whose features read the patch);
- on the vehicle, in a fresh process: import time, then ``open_bundle`` +
  ``feature_index()`` (the stored index: median and max over ``--loads`` fresh opens);
  the fallback (``build_index`` over the bundle's tiles, what a bundle without the index
  costs at start-up); whether the two indexes are identical;
- relocalization of ``--frames`` kidnapped frames (random poses and headings, gain 0.85,
  noise 6 grey levels) with the loaded index: successes, position error, median and max
  seconds per ``Relocalizer.locate``.

Timings are wall clock on a possibly busy machine (figures, not assertions). The maps are
kept under ``--out`` with ``--keep`` and reused with ``--reuse``.

    python bench/bench_reloc_index.py [--area 20] [--out /tmp/bench_reloc] [--keep] [--reuse]
                                      [--loads 5] [--frames 10] [--json FILE]
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

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

PX = 0.0025
FRAME = (240, 320)

_PUBLISH = r"""
import json, sys, time
sys.path.insert(0, sys.argv[4])
from bench_reloc_index import floor_tile_fn
from mapstore.grid import MapGrid
from pipeline.config import load_config
from pipeline.stages.render import layer_halo_px
from pipeline.testing.synthmap import Patch, publish_raster, shards_for_box
url, area, version = sys.argv[1], float(sys.argv[2]), int(sys.argv[3])
cfg = load_config(None)
px = cfg["simulate"]["floor"]["pixel_size_m"]
n = int(round(area / px))
grid = MapGrid(0.0, (n - 1) * px, px, n, n)
t0 = time.perf_counter()
if version == 1:
    sid = publish_raster(url, grid, floor_tile_fn(grid), cfg=cfg, tag="v1")
else:
    c = area / 2 + 0.3
    patch = Patch(c, c, c + 1.0, c + 1.0)
    shards = shards_for_box(grid, cfg["map"]["shard_px"], patch.x0, patch.y0, patch.x1, patch.y1,
                            pad_px=layer_halo_px(cfg["render"]))
    sid = publish_raster(url, grid, floor_tile_fn(grid, [patch]), cfg=cfg, tag="v2", shards=shards)
print(json.dumps({"snapshot": sid, "seconds": time.perf_counter() - t0}))
"""

# On the vehicle: a fresh process opens the bundle and loads its index.
_LOAD = r"""
import json, sys, time
t0 = time.perf_counter()
from tracker.bundle_map import open_bundle
t_import = time.perf_counter() - t0
t1 = time.perf_counter()
tm = open_bundle(sys.argv[1], insecure=True)  # an unsigned bench bundle
t_open = time.perf_counter() - t1
idx = tm.feature_index()
t_total = time.perf_counter() - t1
print(json.dumps({"import_s": t_import, "open_s": t_open, "open_load_s": t_total, "features": len(idx),
                  "source": tm.index_source}))
"""


def floor_tile_fn(grid, patches=()):
    """Level-0 pixels of the bench's floor (uint8 1..255): two periodic textures (4096 and
    2896 px: the mix repeats only after 4096 x 181 px) averaged to the usual +-35 grey levels,
    ``patches`` (:class:`pipeline.testing.synthmap.Patch`) painted over both."""
    import numpy as np

    from pipeline.testing.synthmap import periodic_texture, texture_tile_fn

    a = texture_tile_fn(periodic_texture(11, 4096), grid, patches)
    b = texture_tile_fn(periodic_texture(12, 2896), grid, patches)

    def tile(r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        mix = (a(r0, r1, c0, c1).astype(np.float32) + b(r0, r1, c0, c1) - 256.0) * np.float32(0.7071) + 128.0
        return np.clip(np.rint(mix), 1, 255).astype(np.uint8)

    return tile


def _run(args: list[str], env: dict | None = None) -> str:
    p = subprocess.run([sys.executable, *args], cwd=REPO, capture_output=True, text=True,
                       env=dict(os.environ, PYTHONPATH=str(REPO), **(env or {})))
    if p.returncode != 0:
        raise SystemExit(f"failed: {args[:3]}...\n{p.stdout}\n{p.stderr}")
    return p.stdout


def _export(url: str, out: Path, *extra: str) -> dict:
    rep = out.with_suffix(".json")
    t0 = time.perf_counter()
    _run(["-m", "pipeline.cli", "export", url, str(out), "--quiet", "--report", str(rep), *extra])
    r = json.loads(rep.read_text())
    r["wall_s"] = time.perf_counter() - t0
    return r


def _frame(tile_fn, grid, pose, rng):
    """A live frame at ``pose`` cut from the synthetic floor (only the footprint's window
    of pixels is generated)."""
    import cv2
    import numpy as np

    a = grid.frame_to_grid_affine(pose, FRAME, PX)  # frame pixel -> grid pixel (2 x 3)
    h, w = FRAME
    corners = np.array([[0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], float) @ np.asarray(a).T
    c0, r0 = np.floor(corners.min(axis=0)).astype(int) - 4
    c1, r1 = np.ceil(corners.max(axis=0)).astype(int) + 4
    win = np.clip(np.rint(tile_fn(r0, r1, c0, c1)), 1, 255).astype(np.uint8)
    a_local = np.asarray(a, float).copy()
    a_local[0, 2] -= c0
    a_local[1, 2] -= r0
    f = cv2.warpAffine(win, a_local, (w, h), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP).astype(np.float32)
    return np.clip(0.85 * f + rng.normal(0, 6.0, f.shape), 0, 255).astype(np.uint8)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--area", type=float, default=20.0)
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_reloc"))
    ap.add_argument("--keep", action="store_true")
    ap.add_argument("--reuse", action="store_true")
    ap.add_argument("--loads", type=int, default=5)
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()

    import numpy as np

    out = args.out
    url = str(out / "map")
    stamp = out / f"published-mix-{args.area:g}.json"
    if not (args.reuse and stamp.is_file()):
        shutil.rmtree(out, ignore_errors=True)
        out.mkdir(parents=True)
        here = str(Path(__file__).resolve().parent)
        pub = [json.loads(_run(["-c", _PUBLISH, url, str(args.area), str(v), here]).strip().splitlines()[-1])
               for v in (1, 2)]
        stamp.write_text(json.dumps(pub))
    pub = json.loads(stamp.read_text())
    n = int(round(args.area / PX))
    res: dict = {"area_m": args.area, "pixels": n, "level0_tiles": (-(-n // 256)) ** 2,
                 "publish_s": [p["seconds"] for p in pub]}
    print(f"map {args.area:g} x {args.area:g} m = {n} x {n} px, {res['level0_tiles']} level-0 tiles; "
          f"published in {pub[0]['seconds']:.1f} + {pub[1]['seconds']:.1f} s")

    # --- exports -------------------------------------------------------------------------------
    with_i = _export(url, out / "v1.zip", "--version", "v1")
    without = _export(url, out / "v1_noidx.zip", "--version", "v1", "--no-reloc-index")
    ri = with_i["reloc_index"]
    l0 = with_i["tiles_by_array"]["floor/0"]
    res["full"] = {"bytes": with_i["bytes"], "bytes_without": without["bytes"], "members": with_i["members"],
                   "members_without": without["members"], "seconds": with_i["seconds"],
                   "seconds_without": without["seconds"], "index": ri}
    print(f"full bundle v1: {with_i['bytes'] / 1e6:.2f} MB, {with_i['members']} members, {with_i['seconds']:.1f} s; "
          f"without the index {without['bytes'] / 1e6:.2f} MB, {without['members']} members, "
          f"{without['seconds']:.1f} s")
    print(f"  index: {ri['features']} features in {ri['tiles']} members ({l0} level-0 tiles), "
          f"{ri['bytes'] / 1e6:.2f} MB = {100 * ri['bytes'] / with_i['bytes']:.1f} % of the bundle, "
          f"{ri['bytes'] / max(ri['tiles'], 1):.0f} B per tile; feature time {ri['seconds']:.1f} s, "
          f"export wall clock +{with_i['seconds'] - without['seconds']:.1f} s")
    d_with = _export(url, out / "d.zip", "--since", "v1")
    d_without = _export(url, out / "d_noidx.zip", "--since", "v1", "--no-reloc-index")
    dri = d_with["reloc_index"]
    res["delta"] = {"bytes": d_with["bytes"], "bytes_without": d_without["bytes"],
                    "changed_tiles": d_with["tiles_by_array"], "seconds": d_with["seconds"],
                    "seconds_without": d_without["seconds"], "index": dri}
    print(f"delta v1->v2: {d_with['bytes'] / 1e3:.1f} kB ({d_with['seconds']:.1f} s), without the index "
          f"{d_without['bytes'] / 1e3:.1f} kB ({d_without['seconds']:.1f} s); level-0 tiles carried "
          f"{d_with['tiles_by_array'].get('floor/0', 0)}, index chunks carried {dri['tiles']} "
          f"({dri['bytes'] / 1e3:.1f} kB; {dri['tiles_computed']} computed per version)")
    # apply-delta = full export of v2 (members)
    _run(["-m", "pipeline.cli", "apply-delta", str(out / "v1.zip"), str(out / "d.zip"), str(out / "patched.zip")])
    v2 = _export(url, out / "v2.zip")
    _run(["-m", "pipeline.cli", "verify", str(out / "patched.zip"), "--report", str(out / "verify.json")])
    same = v2["content_sha256"] == json.loads((out / "verify.json").read_text())["content_sha256"]
    res["delta"]["apply_equals_full"] = same
    print(f"  apply-delta(v1, delta) == full export of v2: {same}")

    # --- vehicle: open + load -----------------------------------------------------------------
    loads = [json.loads(_run(["-c", _LOAD, str(out / "v1.zip")]).strip()) for _ in range(args.loads)]
    ol = sorted(x["open_load_s"] for x in loads)
    res["vehicle"] = {"import_s": float(np.median([x["import_s"] for x in loads])),
                      "open_load_s_median": ol[len(ol) // 2], "open_load_s_max": ol[-1],
                      "features": loads[0]["features"]}
    print(f"vehicle: import {res['vehicle']['import_s']:.2f} s; open + load stored index "
          f"median {ol[len(ol) // 2] * 1e3:.0f} ms, max {ol[-1] * 1e3:.0f} ms over {len(ol)} fresh processes "
          f"({loads[0]['features']} features, source {loads[0]['source']})")

    import warnings

    from mapstore.grid import MapGrid
    from tracker.bundle_map import open_bundle

    with open_bundle(out / "v1_noidx.zip", cache_tiles=64, insecure=True) as tm:
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            built = tm.feature_index()
        t_build = time.perf_counter() - t0
    with open_bundle(out / "v1.zip", insecure=True) as tm:
        stored = tm.feature_index()
        identical = (np.array_equal(stored.xy, built.xy) and np.array_equal(stored.descriptors, built.descriptors)
                     and np.array_equal(stored.angle, built.angle))
        res["vehicle"].update({"fallback_build_s": t_build, "identical": identical})
        print(f"  fallback (no index in the bundle): build_index over the tiles {t_build:.2f} s; "
              f"stored == built: {identical}")

        # --- kidnapped frames ---------------------------------------------------------------
        grid = tm.grid
        tile_fn = floor_tile_fn(MapGrid(0.0, (n - 1) * PX, PX, n, n))
        rl = tm.relocalizer(PX)
        rng = np.random.default_rng(7)
        x0, y0, x1, y1 = grid.bounds
        secs, errs, ok = [], [], 0
        for _ in range(args.frames):
            gt = np.array([rng.uniform(x0 + 0.5, x1 - 0.5), rng.uniform(y0 + 0.5, y1 - 0.5),
                           rng.uniform(-np.pi, np.pi)])
            f = rl.locate(_frame(tile_fn, grid, gt, rng))
            secs.append(rl.last_seconds)
            if f.ok:
                ok += 1
                errs.append(float(np.hypot(*(f.pose[:2] - gt[:2])) / PX))
        res["reloc"] = {"frames": args.frames, "ok": ok, "err_px_max": max(errs) if errs else None,
                        "seconds_median": float(np.median(secs)), "seconds_max": float(max(secs))}
        print(f"kidnapped frames: {ok}/{args.frames} relocalized, position error max "
              f"{max(errs) if errs else float('nan'):.2f} px; locate median {np.median(secs) * 1e3:.0f} ms, "
              f"max {max(secs) * 1e3:.0f} ms ({len(stored)} features in the index)")
    if args.json:
        args.json.write_text(json.dumps(res, indent=1))
    if not args.keep:
        shutil.rmtree(out, ignore_errors=True)


if __name__ == "__main__":
    main()
