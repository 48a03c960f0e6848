"""Benchmark: what signature checking costs a vehicle opening a bundle.

On the 40 x 40 m bundle of bench/bench_export.py (a synthetic floor at 2.5 mm, 16000 x
16000 px, every level; ~13 000 members) exported signed (``mosaicmap keys new``, ``export
--sign``), a fresh child process times, alternating the two variants, ``--opens`` times each:

- open: :func:`mapstore.bundle.open_bundle` + reading one level-0 tile (a different tile
  each time), without signature checks (``keys=None``: what the vehicle did before) and
  with them (``keys=[owner.pub]``: the signature document checked at open, the pages of
  the manifest listing the members read and the members themselves checked at first
  read). Target: the median grows by <= 10 %;
- start-up: :func:`tracker.bundle_map.open_bundle` + the stored relocalization index
  (every index chunk read: ~4000 members, each checked when signed), insecure vs signed.

Printed: median and max wall time, median CPU time (process), and the ratios. The page
cache is warm (the file was just written or read). Figures on a shared machine: medians
over alternated runs, not assertions.

    python bench/bench_bundle_open.py [--area 40] [--out /tmp/bench_bundle_open] [--reuse] [--opens 30]
"""

from __future__ import annotations

import argparse
import json
import shutil
from datetime import datetime, timezone
from pathlib import Path

from bench_export import _PUBLISH
from runner import child, reusable, run_cli

_OPEN = r"""
import json, statistics, sys, time
from mapstore.bundle import open_bundle
from mapstore.signing import load_public_key
from tracker.bundle_map import open_bundle as tracker_open
path, pub, opens = sys.argv[1], sys.argv[2], int(sys.argv[3])
keys = [load_public_key(pub)]
with open_bundle(path) as b:
    rows, cols = b.tiles_shape(0)
    tiles = [(r, c) for r in range(rows) for c in range(cols) if b.has_tile(0, r, c)]
    members = len(b.store.index.entries())
step = max(1, len(tiles) // opens)

def timed(fn):
    w, c = time.perf_counter(), time.process_time()
    fn()
    return time.perf_counter() - w, time.process_time() - c

def open_read(k, tile):
    def run():
        with open_bundle(path, keys=k) as b:
            b.read_tile(0, *tile)
    return run

def startup(k):
    def run():
        with tracker_open(path, keys=k or (), insecure=not k) as tm:
            tm.stored_index()
    return run

res = {"plain": [], "signed": [], "start_plain": [], "start_signed": []}
for variant in (open_read(None, tiles[0]), open_read(keys, tiles[0])):  # warm up
    variant()
for i in range(opens):
    tile = tiles[(i * step) % len(tiles)]
    pair = [("plain", open_read(None, tile)), ("signed", open_read(keys, tile))]
    for name, fn in (pair if i % 2 == 0 else pair[::-1]):
        res[name].append(timed(fn))
for i in range(max(3, opens // 5)):
    pair = [("start_plain", startup(None)), ("start_signed", startup(keys))]
    for name, fn in (pair if i % 2 == 0 else pair[::-1]):
        res[name].append(timed(fn))
out = {"members": members, "tiles": len(tiles), "opens": opens}
for name, v in res.items():
    out[name] = {"median_ms": 1000 * statistics.median(w for w, _ in v), "max_ms": 1000 * max(w for w, _ in v),
                 "cpu_median_ms": 1000 * statistics.median(c for _, c in v), "n": len(v)}
print(json.dumps(out))
"""


def make_bundle(data: Path, area: float, reuse: bool) -> tuple[Path, Path]:
    """The signed full bundle of an ``area`` x ``area`` m map and its public key."""
    params = {"area": area}
    marker = data / "params.json"
    bundle, key = data / "full.zip", data / "owner.key"
    if reusable(marker, params, reuse) and bundle.exists():
        print(f"reusing {bundle}", flush=True)
        return bundle, key.with_name(key.name + ".pub")
    shutil.rmtree(data, ignore_errors=True)
    data.mkdir(parents=True)
    print(f"publishing a {area:g} x {area:g} m map ...", flush=True)
    pub = child(_PUBLISH, data / "map", area, 1, prelude=False)
    print(f"  {pub['seconds']:.1f} s; key pair and signed export ...", flush=True)
    run_cli("keys", "new", key)
    run_cli("export", data / "map", bundle, "--sign", key, "--quiet")
    marker.write_text(json.dumps({"params": params}) + "\n")
    return bundle, key.with_name(key.name + ".pub")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--area", type=float, default=40.0, help="Side of the square map, metres.")
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_bundle_open"), help="Data directory (kept).")
    ap.add_argument("--reuse", action="store_true", help="Reuse the kept bundle of the same area.")
    ap.add_argument("--opens", type=int, default=30, help="Opens timed per variant.")
    ap.add_argument("--json", type=Path, default=None, help="Write the figures to this JSON file.")
    args = ap.parse_args()
    bundle, pub = make_bundle(args.out / f"area{args.area:g}", args.area, args.reuse)
    print("timing opens in a fresh process ...", flush=True)
    r = child(_OPEN, bundle, pub, args.opens, prelude=False)
    r.update({"bundle": str(bundle), "bytes": bundle.stat().st_size, "area_m": args.area,
              "date": datetime.now(timezone.utc).isoformat(timespec="minutes")})
    p, s, sp, ss = r["plain"], r["signed"], r["start_plain"], r["start_signed"]
    r["open_ratio"] = s["median_ms"] / p["median_ms"]
    r["open_cpu_ratio"] = s["cpu_median_ms"] / p["cpu_median_ms"]
    r["startup_ratio"] = ss["median_ms"] / sp["median_ms"]
    print(f"{args.area:g} x {args.area:g} m bundle: {r['members']} members, {r['bytes'] / 1e6:.1f} MB; "
          f"{r['opens']} opens per variant, alternated")
    print(f"  open + read 1 tile, no signature check: median {p['median_ms']:.2f} ms (max {p['max_ms']:.2f}), "
          f"CPU {p['cpu_median_ms']:.2f} ms")
    print(f"  open + read 1 tile, signature checked:  median {s['median_ms']:.2f} ms (max {s['max_ms']:.2f}), "
          f"CPU {s['cpu_median_ms']:.2f} ms")
    print(f"  ratio signed / unchecked: wall {r['open_ratio']:.3f}, CPU {r['open_cpu_ratio']:.3f} (target <= 1.10)")
    print(f"  tracker start-up (open + stored reloc index, {sp['n']} runs): insecure {sp['median_ms']:.1f} ms, "
          f"signed {ss['median_ms']:.1f} ms (ratio {r['startup_ratio']:.3f}; CPU {sp['cpu_median_ms']:.1f} / "
          f"{ss['cpu_median_ms']:.1f} ms)")
    if args.json:
        args.json.write_text(json.dumps(r, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
