"""Benchmark of exports: bundle sizes, delta size, export and open times.

On a synthetic ``--area`` x ``--area`` m floor at 2.5 mm (default 40 x 40 m = 16000 x 16000
px, 256 MPix at level 0) published with :func:`pipeline.testing.synthmap.publish_raster` (a
seamless periodic texture, 4096 px period; version 1 = the whole floor; version 2 = the
same floor with one 1 x 1 m patch repainted, only the shards it reaches rewritten), it
prints:

- the full bundle of version 1 (default levels and layers of ``[export]``: every level;
  intensity, texture, uniqueness): bytes, members, seconds, peak RSS of the export;
- a corridor export along a 100 m guidepath polyline at 1 m width (a serpentine of 30, 10,
  30, 10 and 20 m legs, 10 m apart, inside the area): bytes and the ratio to the full
  bundle. Target <= 1/20. Geometry: 100 m x 1 m = 100 m^2, so on a 40 x 40 m map the
  pixel-area bound is already 100 / 1600 = 1/16 before the tiles' edges and the coarse
  levels' and layers' whole cells along the edge (each kept cell must cover the corridor).
  With ``--area2 S`` the same corridor is exported from an S x S m map too (60 m: bound
  100 / 3600 = 1/36), to show the ratio falls with the area while the corridor's bytes stay;
- the delta of version 2 since version 1 (``export --since``): bytes, ratio to the full
  bundle (target <= 2 %), changed tiles, seconds; then ``apply-delta`` onto the version-1
  bundle, checked against a full export of version 2 (same members and content hash);
- opening a bundle and reading one level-0 tile, in a fresh process: the import time of
  the reader (``mapstore.bundle``) and median / max over ``--opens`` fresh opens
  (``open_bundle`` + ``read_tile`` of a different tile each time). Target < 100 ms. The
  file is in the page cache (it was just written): a cold read adds the disk's latency.

- routes: a map holding a 1 km route panorama at 10 cm spacing and 1 sample/degree
  (10 001 rows x 360; synthetic lines: a straight 1 km corridor with textured walls 2 m to
  either side, seen from the route: rows change with the viewpoint as real horizon lines
  do, with 1 grey level of noise) beside a 1 x 1 m floor; version 2 changes the lines over
  10 m of it (an object appearing in a 30 deg sector). Printed: the route's bytes in a
  whole-map bundle per km of route (compressed, zstd 3; the map's 1000-row chunks), and the
  delta after the change (its size and route chunks), with the map's chunks and with
  ``[export] route_rows_per_chunk = 100`` (10 m chunks). ``--routes-only`` runs this row
  alone.

Every export runs in a fresh child process (``python -m pipeline.cli``) whose own peak
RSS (VmHWM) is printed. Timings are wall clock on a possibly busy machine: figures, not
assertions. The maps are kept under ``--out`` with ``--keep`` and reused with ``--reuse``
(same parameters); without ``--keep`` everything is deleted at the end.

    python bench/bench_export.py [--area 40] [--area2 0] [--out /tmp/bench_export] [--keep] [--reuse]
                                 [--opens 20] [--json FILE] [--routes-only]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

from runner import child, mosaicmap, reusable

PX = 0.0025
TEXTURE_PERIOD_PX = 4096
PATCH_M = 1.0  # side of the changed patch of version 2
CORRIDOR = [(5.0, 5.0), (35.0, 5.0), (35.0, 15.0), (5.0, 15.0), (5.0, 25.0), (25.0, 25.0)]  # 100 m
CORRIDOR_WIDTH_M = 1.0

# A map version published in a child (so this process stays small).
_PUBLISH = r"""
import json, sys, time
from mapstore.grid import MapGrid
from pipeline.config import load_config
from pipeline.stages.render import layer_halo_px
from pipeline.testing.synthmap import Patch, periodic_texture, publish_raster, shards_for_box, texture_tile_fn
url, area, version = sys.argv[1], float(sys.argv[2]), int(sys.argv[3])
cfg = load_config(None)
px = cfg["simulate"]["floor"]["pixel_size_m"]
n = int(round(area / px))
grid = MapGrid(0.0, (n - 1) * px, px, n, n)
tex = periodic_texture(11, 4096)
t0 = time.perf_counter()
if version == 1:
    sid = publish_raster(url, grid, texture_tile_fn(tex, grid), cfg=cfg, tag="v1")
else:
    c = area / 2 + 0.3
    patch = Patch(c, c, c + 1.0, c + 1.0)
    shards = shards_for_box(grid, cfg["map"]["shard_px"], patch.x0, patch.y0, patch.x1, patch.y1,
                            pad_px=layer_halo_px(cfg["render"]))
    sid = publish_raster(url, grid, texture_tile_fn(tex, grid, [patch]), cfg=cfg, tag="v2", shards=shards)
print(json.dumps({"snapshot": sid, "seconds": time.perf_counter() - t0}))
"""

# A 1 x 1 m floor (version 1), + a 1 km route (version 2), the route changed over 10 m (version 3).
_ROUTE_MAP = r"""
import json, sys, time
import numpy as np
import zarr
from mapstore.grid import MapGrid
from mapstore.layout import read_floor, set_version
from mapstore.repository import MapRepository
from mapstore.routes import RouteRecord, write_route
from pipeline.config import load_config
from pipeline.testing.synthmap import periodic_texture, publish_raster, texture_tile_fn
url, length, spacing, x_change = sys.argv[1], float(sys.argv[2]), float(sys.argv[3]), float(sys.argv[4])
cfg = load_config(None)
grid = MapGrid(0.0, 1.0, 0.0025, 400, 400)
t0 = time.perf_counter()
sids = {"v1": publish_raster(url, grid, texture_tile_fn(periodic_texture(3, 512), grid), cfg=cfg, tag="v1")}
rng = np.random.default_rng(5)
m = int(round(length / spacing)) + 1
x = spacing * np.arange(m)
theta = 0.02 * np.sin(x / 7.0)  # a slight weave (radians)
# the walls' texture along x (1 cm samples): smooth noise, features of ~5 cm .. 1 m
u0, du = -80.0, 0.01
n = int((length + 160.0) / du)
wall = np.zeros(n)
for sigma_m, weight in ((0.05, 1.0), (0.3, 1.0), (1.0, 0.7)):
    k = np.fft.rfftfreq(n, du)
    wall += weight * np.fft.irfft(np.fft.rfft(rng.standard_normal(n)) * np.exp(-2 * np.pi**2 * sigma_m**2 * k**2), n=n)
walls = [128 + 45 * (w - w.mean()) / w.std() for w in (wall, np.roll(wall, n // 3))]
phi = np.radians(np.arange(360.0))
def lines_at(xs, th):
    out = np.empty((len(xs), 360), np.float32)
    b = th[:, None] + phi[None, :]
    sb, cb = np.sin(b), np.cos(b)
    for side, w, y in ((0, walls[0], 2.0), (1, walls[1], -2.0)):
        hit = np.where(sb * y > 1e-3, y / np.where(np.abs(sb) > 1e-3, sb, 1.0), np.inf)  # ray length to the wall
        u = xs[:, None] + np.where(np.isfinite(hit), hit * cb, 0.0)
        val = np.interp(np.clip(u, u0, u0 + n * du), u0 + du * np.arange(n), w)
        far = ~np.isfinite(hit) | (hit > 60.0)
        val = np.where(far, 128.0, val)
        out = np.where(sb * y > 1e-3, val, out) if side else val
    return out
lines = np.concatenate([lines_at(x[i:i + 1000], theta[i:i + 1000]) for i in range(0, m, 1000)])
lines = np.clip(np.rint(lines + rng.normal(0, 1.0, lines.shape)), 1, 255).astype(np.uint8)
poses = np.column_stack([x, np.zeros(m), theta]).astype(np.float32)
def commit(rec, tag):
    repo = MapRepository.open(url)
    with repo.commit_lock():
        session = repo.writable()
        root = zarr.open_group(session.store, mode="a")
        v = read_floor(root).version + 1
        set_version(root, v)
        rec.version = v
        write_route(root, "corridor", rec)
        sid = repo.commit(session, f"route: version {v}", metadata={"version": v, "tag": tag})
        repo.tag(sid, tag)
    return sid
sids["v2"] = commit(RouteRecord(lines, poses, spacing_m=spacing), "v2")
changed = lines.copy()
rows = (x >= x_change) & (x < x_change + 10.0)
changed[np.ix_(rows, np.arange(30, 60))] = np.clip(np.rint(200 + rng.normal(0, 3, (rows.sum(), 30))), 1, 255)
sids["v3"] = commit(RouteRecord(changed, poses, spacing_m=spacing), "v3")
print(json.dumps({"snapshots": sids, "rows": m, "raw_bytes": int(lines.nbytes + poses.nbytes),
                  "changed_rows": int(rows.sum()), "seconds": time.perf_counter() - t0}))
"""

ROUTE_LENGTH_M, ROUTE_SPACING_M, ROUTE_CHANGE_AT_M = 1000.0, 0.1, 503.0


def routes_row(out: Path) -> dict:
    """The routes row: a 1 km route's bytes per km in a bundle, and its delta after a
    change over 10 m (the map's chunks, and 100-row chunks)."""
    data = out / "routes"
    shutil.rmtree(data, ignore_errors=True)
    data.mkdir(parents=True)
    url = str(data / "map")
    print("routes: publishing a 1 x 1 m floor and a 1 km route (2 versions) ...", flush=True)
    made = child(_ROUTE_MAP, url, ROUTE_LENGTH_M, ROUTE_SPACING_M, ROUTE_CHANGE_AT_M, prelude=False)
    small = data / "rows100.toml"
    small.write_text("[export]\nroute_rows_per_chunk = 100\n")
    res: dict = {"route": made}
    for name, extra in (("map_chunks", ()), ("rows100", ("--config", small))):
        print(f"routes: bundles and delta ({name}) ...", flush=True)
        full2 = mosaicmap(data / f"{name}-v2.json", "export", url, data / f"{name}-v2.zip", "--version", "v2", *extra)
        none = mosaicmap(data / f"{name}-none.json", "export", url, data / f"{name}-none.zip", "--version", "v2",
                         "--routes", "none", *extra)
        full3 = mosaicmap(data / f"{name}-v3.json", "export", url, data / f"{name}-v3.zip", "--version", "v3", *extra)
        delta = mosaicmap(data / f"{name}-delta.json", "export", url, data / f"{name}-delta.zip", "--version", "v3",
                          "--since", "v2", *extra)
        applied = mosaicmap(data / f"{name}-apply.json", "apply-delta", data / f"{name}-v2.zip",
                            data / f"{name}-delta.zip", data / f"{name}-patched.zip", quiet=False)
        route = full2["routes"][0]
        res[name] = {"bundle_bytes": full2["bytes"], "bundle_without_routes_bytes": none["bytes"],
                     "route_bytes": route["bytes"], "route_chunks": route["chunks"],
                     "bytes_per_km": route["bytes"] / (route["length_m"] / 1000.0),
                     "export_seconds": full2["seconds"], "delta_bytes": delta["bytes"],
                     "delta_route_chunks": sum(v for k, v in delta["tiles_by_array"].items() if k.startswith("routes/")),
                     "delta_members": delta["members"], "delta_seconds": delta["seconds"],
                     "apply_delta_equals_full_export": applied["content_sha256"] == full3["content_sha256"]}
    return res


# Import time of the reader, then fresh opens + one tile each.
_OPEN = r"""
import json, statistics, sys, time
t0 = time.perf_counter()
import mapstore.bundle as mb
t_import = time.perf_counter() - t0
path, opens = sys.argv[1], int(sys.argv[2])
heavy = sorted(m for m in sys.modules if m.split(".")[0] in ("icechunk", "click", "pipeline"))
with mb.open_bundle(path) as b:
    rows, cols = b.tiles_shape(0)
    tiles = [(r, c) for r in range(rows) for c in range(cols) if b.has_tile(0, r, c)]
step = max(1, len(tiles) // opens)
times, first = [], None
for i in range(opens):
    r, c = tiles[(i * step) % len(tiles)]
    t = time.perf_counter()
    b = mb.open_bundle(path)
    tile = b.read_tile(0, r, c)
    times.append(time.perf_counter() - t)
    assert tile.shape == (b.tile_px, b.tile_px) and tile.any()
    b.close()
print(json.dumps({"import_ms": 1000 * t_import, "median_ms": 1000 * statistics.median(times),
                  "max_ms": 1000 * max(times), "first_ms": 1000 * times[0], "tiles": len(tiles),
                  "heavy_modules": heavy}))
"""


def build_map(data: Path, area: float, reuse: bool) -> tuple[str, dict]:
    """The two-version map at ``data/map`` (published unless reused)."""
    url = str(data / "map")
    params = {"area": area, "px": PX, "texture_period_px": TEXTURE_PERIOD_PX, "patch_m": PATCH_M}
    params_file = data / "params.json"
    if reusable(params_file, params, reuse):
        pub = json.loads(params_file.read_text())["publish"]
        print(f"reusing the {area:g} x {area:g} m map at {url}", flush=True)
        return url, pub
    shutil.rmtree(data, ignore_errors=True)
    data.mkdir(parents=True)
    print(f"publishing a {area:g} x {area:g} m map (version 1, whole) ...", flush=True)
    v1 = child(_PUBLISH, url, area, 1, prelude=False)
    print(f"  {v1['seconds']:.1f} s; version 2 (a {PATCH_M:g} x {PATCH_M:g} m patch) ...", flush=True)
    v2 = child(_PUBLISH, url, area, 2, prelude=False)
    print(f"  {v2['seconds']:.1f} s", flush=True)
    pub = {"v1": v1, "v2": v2}
    params_file.write_text(json.dumps({"params": params, "publish": pub}, indent=2) + "\n")
    return url, pub


def corridor_csv(path: Path) -> Path:
    path.write_text("x,y\n" + "".join(f"{x},{y}\n" for x, y in CORRIDOR))
    return path


def mb(n: float) -> str:
    return f"{n / 1e6:.2f} MB"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--area", type=float, default=40.0, help="Side of the square map, metres.")
    ap.add_argument("--area2", type=float, default=0.0,
                    help="Also export the corridor from an AREA2 x AREA2 m map (0 = skip; 60 shows the geometry).")
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_export"), help="Data directory.")
    ap.add_argument("--keep", action="store_true", help="Keep the data directory.")
    ap.add_argument("--reuse", action="store_true", help="Reuse kept maps of the same parameters.")
    ap.add_argument("--opens", type=int, default=20, help="Fresh opens timed.")
    ap.add_argument("--json", type=Path, default=None, help="Write the figures to this JSON file.")
    ap.add_argument("--routes-only", action="store_true", help="Only the routes row (a 1 km route panorama).")
    args = ap.parse_args()

    figures: dict = {"cpu_count": os.cpu_count(), "area_m": args.area}
    try:
        routes = routes_row(args.out)
        figures["routes"] = routes
        r_rows = []
        for name, label in (("map_chunks", "1000-row chunks"), ("rows100", "100-row chunks")):
            r = routes[name]
            r_rows.append(f"  route 1 km, {label:15} {r['bytes_per_km'] / 1e6:.2f} MB per km in the bundle "
                          f"({r['route_chunks']} chunk members; raw {routes['route']['raw_bytes'] / 1e6:.2f} MB); "
                          f"delta after 10 m changed: {r['delta_bytes'] / 1e3:.1f} kB ({r['delta_route_chunks']} "
                          f"route chunks, {r['delta_members']} members); apply-delta equals the full export: "
                          f"{r['apply_delta_equals_full_export']}")
        print("\n".join(r_rows))
        if args.routes_only:
            if args.json:
                args.json.write_text(json.dumps(figures, indent=2) + "\n")
            return 0
        data = args.out / f"area{args.area:g}"
        url, pub = build_map(data, args.area, args.reuse)
        figures["publish"] = pub
        b = data / "bundles"
        shutil.rmtree(b, ignore_errors=True)
        b.mkdir()
        path = corridor_csv(b / "guidepath.csv")

        print("full bundle of version 1 ...", flush=True)
        full1 = mosaicmap(b / "full1.json", "export", url, b / "full1.zip", "--version", "v1")
        print("full bundle of version 2 ...", flush=True)
        full2 = mosaicmap(b / "full2.json", "export", url, b / "full2.zip", "--version", "v2")
        print("corridor ...", flush=True)
        corr = mosaicmap(b / "corridor.json", "export", url, b / "corridor.zip", "--version", "v1", "--corridor", path,
                         "--width", CORRIDOR_WIDTH_M)
        print("delta since version 1 ...", flush=True)
        delta = mosaicmap(b / "delta.json", "export", url, b / "delta.zip", "--version", "v2", "--since", "v1")
        print("apply-delta ...", flush=True)
        applied = mosaicmap(b / "apply.json", "apply-delta", b / "full1.zip", b / "delta.zip", b / "patched.zip",
                            quiet=False)
        print("verify ...", flush=True)
        verify = mosaicmap(b / "verify.json", "verify", b / "full2.zip", quiet=False)
        same = applied["content_sha256"] == full2["content_sha256"]
        print("open + read one tile ...", flush=True)
        opened = child(_OPEN, b / "full1.zip", args.opens, prelude=False)
        figures.update({"full1": full1, "full2": full2, "corridor": corr, "delta": delta, "apply_delta": applied,
                        "verify": verify, "open": opened, "apply_delta_equals_full_export": same})

        second = None
        if args.area2 > 0:
            data2 = args.out / f"area{args.area2:g}"
            url2, _ = build_map(data2, args.area2, args.reuse)
            b2 = data2 / "bundles"
            shutil.rmtree(b2, ignore_errors=True)
            b2.mkdir()
            print(f"full bundle and corridor of the {args.area2:g} m map ...", flush=True)
            f2 = mosaicmap(b2 / "full1.json", "export", url2, b2 / "full1.zip", "--version", "v1")
            c2 = mosaicmap(b2 / "corridor.json", "export", url2, b2 / "corridor.zip", "--version", "v1", "--corridor",
                           corridor_csv(b2 / "guidepath.csv"), "--width", CORRIDOR_WIDTH_M)
            second = {"full": f2, "corridor": c2}
            figures["area2"] = {"area_m": args.area2, **second}

        a = args.area
        ratio_c = corr["bytes"] / full1["bytes"]
        ratio_d = delta["bytes"] / full2["bytes"]
        n0 = int(round(a / PX))
        print()
        print(f"exports of a {a:g} x {a:g} m map at {PX * 1000:g} mm ({n0} x {n0} px level 0, "
              f"{len(full1['levels'])} levels; layers {','.join(full1['layers'])}; {os.cpu_count()} cores)")
        rows = [
            ("publish v1 / v2", f"{pub['v1']['seconds']:.1f} s / {pub['v2']['seconds']:.1f} s (synthmap)"),
            ("full bundle", f"{mb(full1['bytes'])}, {full1['members']} members, {full1['seconds']:.1f} s, "
                            f"peak RSS {full1['hwm_mb']:.0f} MB"),
            ("corridor 100 m x 1 m", f"{mb(corr['bytes'])}, {corr['members']} members, {corr['seconds']:.1f} s; "
                                     f"ratio {ratio_c:.4f} = 1/{1 / ratio_c:.1f} of the full bundle "
                                     f"(target <= 1/20; pixel-area bound 100/{a * a:g} = 1/{a * a / 100:.0f})"),
            ("delta after 1 m^2", f"{delta['bytes'] / 1e3:.1f} kB, {delta['changed_tiles']} changed tiles "
                                  f"{delta['tiles_by_array']}, {delta['seconds']:.1f} s, peak RSS "
                                  f"{delta['hwm_mb']:.0f} MB; ratio {100 * ratio_d:.3f} % of the full bundle "
                                  f"(target <= 2 %)"),
            ("apply-delta", f"{applied['seconds']:.1f} s (verifies base, delta and result); equals the full "
                            f"export of v2: {same}"),
            ("verify full bundle", f"{verify['seconds']:.2f} s"),
            ("open + read 1 tile", f"median {opened['median_ms']:.1f} ms, max {opened['max_ms']:.1f} ms over "
                                   f"{args.opens} fresh opens (target < 100 ms); import of mapstore.bundle "
                                   f"{opened['import_ms']:.0f} ms; heavy modules imported: "
                                   f"{opened['heavy_modules'] or 'none'}"),
        ]
        if second:
            r2 = second["corridor"]["bytes"] / second["full"]["bytes"]
            rows.append((f"corridor on {args.area2:g} m map",
                         f"{mb(second['corridor']['bytes'])} of {mb(second['full']['bytes'])}: ratio {r2:.4f} = "
                         f"1/{1 / r2:.1f} (pixel-area bound 1/{args.area2 ** 2 / 100:.0f})"))
            figures["area2"]["ratio"] = r2
        for name, value in rows:
            print(f"  {name:22} {value}")
        print("\n".join(r_rows))
        ok = {f"corridor_1_20_on_{a:g}m": ratio_c <= 1 / 20}
        if second:
            ok[f"corridor_1_20_on_{args.area2:g}m"] = figures["area2"]["ratio"] <= 1 / 20
        ok |= {"delta_2pc": ratio_d <= 0.02, "open_100ms": opened["max_ms"] < 100,
               "apply_delta_equals_full": same}
        figures.update({"corridor_ratio": ratio_c, "delta_ratio": ratio_d, "targets": ok})
        print("targets: " + ", ".join(f"{k} {'PASS' if v else 'FAIL'}" for k, v in ok.items()))
        if args.json:
            args.json.write_text(json.dumps(figures, indent=2) + "\n")
            print(f"figures -> {args.json}")
        return 0
    finally:
        if not args.keep:
            shutil.rmtree(args.out, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
