"""Lower bounds on the render's CPU time (the former 100 MPix/s target on 2 cores), measured.

On the 40 x 40 m map of ``bench_render_large.py`` (its data kept under ``--data``, made or
reused by running it first, which also renders the map and gives the measured figures of the
same run), this measures, one thread, CPU seconds (``time.process_time``), the primitives no
render producing the published outputs can skip, each done once with the library at its best:

- **read**: decoding each frame the render uses, as the render reads it (one direct shard
  read and one zstd decode per frame, uint16 as ingest stores it); and a memory copy of the
  decoded frame (the cost if the frames store were uncompressed);
- **warp**: one ``cv2.warpAffine`` of each used frame over its own bounding box in the map
  grid, nearest / linear / cubic;
- **weight**: the same warp of the frame's feather weight (float32; nearest / linear): a
  feathered blend needs a weight per pixel per frame;
- **accumulate**: the warped frame times its weight added to a float32 accumulator, the
  weight to another (OpenCV: one multiply, two adds over the box);
- **uniqueness** (Kelly's (2000) C1 - C2 at every layer cell, ``[render] uniqueness_*``):
  :func:`pipeline.mosaic.uniqueness_cells` as the render computes it (``uniqueness_level``) on every rendered shard (or ``--sample-shards``
  of them, scaled to the map's shards); and the arithmetic floor of its correlations (template px x shifts
  multiply-adds per cell) at this CPU's single-thread SGEMM rate, measured here;
- **texture**: :func:`pipeline.mosaic.texture_layer` on the same shards;
- **pyramid**: :func:`pipeline.mosaic.downsample2` on them (x 4/3: every level above);
- **zstd**: encoding every non-empty 256 x 256 chunk of every level of the rendered map at
  the map's zstd level (numcodecs; the compression alone, no file writes).

Their sums per setting give an upper bound on the render's throughput on 2 cores (2 x the
single-thread rate: perfect scaling), before what else a render does (normalization,
no-data masks, coverage counts, the published map's files, Python and dask):

- "as rendered": the frames of ``[render] coverage_depth`` and ``interpolation``
  (cubic), the settings of the quality figures in bench/README.md, the layers as implemented;
- "depth 1, linear; uniqueness at SGEMM": fewer frames, the cheaper kernel (on the 5 x 5 m
  quality benchmark these still pass: ``bench_render.py --config`` a file setting both),
  and the uniqueness correlations at the SGEMM rate (an ideal implementation);
- "floor": besides, nearest-neighbour warps and uncompressed frames (a bound, not a render
  anyone would ship).

    python bench/bench_render_floor.py [--area 40] [--data /tmp/bench_large] [--sample-shards 0]
                                       [--skip-render] [--json FILE]

Figures, not assertions: exit code 0 always (1 only when the data cannot be made).
"""

from __future__ import annotations

import os

# One thread everywhere (OpenBLAS, OpenCV): the figures are per core.
for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

TARGET_MPIX_S = 100.0
CORES = 2


def cpu_of(fn, *args, **kw):
    """(result, CPU seconds of this thread) of ``fn(*args, **kw)``."""
    t = time.thread_time()
    out = fn(*args, **kw)
    return out, time.thread_time() - t


def sgemm_gflops() -> float:
    """Single-thread float32 matrix-product rate (GFLOP/s), best of 5 on 1024^3."""
    a = np.random.default_rng(0).random((1024, 1024), dtype=np.float32)
    np.matmul(a, a)
    best = min(cpu_of(np.matmul, a, a)[1] for _ in range(5))
    return 2 * 1024**3 / best / 1e9


def frame_costs(store, poses, grid, used: np.ndarray, shape, px: float, feather_px: float) -> dict:
    """Per used frame, CPU seconds: to decode it, to copy it, to warp it (3 kernels), to warp
    its feather weight (nearest, linear) and to accumulate it (weighted grey levels and weight
    added to box-sized float32 accumulators: one multiply, two adds)."""
    import cv2

    from pipeline.mosaic import feather_weight, frame_boxes

    lf = store.logs[0]
    weight = feather_weight(lf.valid, feather_px)
    boxes = frame_boxes(grid, poses[used], shape, px, pad_px=0)
    h, w = grid.shape
    out = {k: np.zeros(len(used)) for k in ("decode", "copy", "nearest", "linear", "cubic", "weight_nearest",
                                            "weight_linear", "accumulate", "box_px")}
    buf = np.empty(shape, np.uint16)
    kernels = {"nearest": cv2.INTER_NEAREST, "linear": cv2.INTER_LINEAR, "cubic": cv2.INTER_CUBIC}

    def accumulate(v, wv, acc, wacc):
        cv2.add(acc, cv2.multiply(v, wv, dtype=cv2.CV_32F), dst=acc)
        cv2.add(wacc, wv, dst=wacc)

    for n, (g, box) in enumerate(zip(used, boxes)):
        img, out["decode"][n] = cpu_of(lf.images_uint16, int(g), int(g) + 1)
        img = img[0]
        out["copy"][n] = cpu_of(np.copyto, buf, img)[1]
        r0, r1, c0, c1 = max(box[0], 0), min(box[1], h), max(box[2], 0), min(box[3], w)
        f2s = grid.frame_to_grid_affine(poses[g], shape, px).copy()
        f2s[:, 2] -= (c0, r0)
        s2f = cv2.invertAffineTransform(f2s)
        size = (int(c1 - c0), int(r1 - r0))
        out["box_px"][n] = size[0] * size[1]
        for name, flag in kernels.items():
            v, out[name][n] = cpu_of(cv2.warpAffine, img, s2f, size, flags=flag | cv2.WARP_INVERSE_MAP,
                                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        for name, flag in (("weight_nearest", cv2.INTER_NEAREST), ("weight_linear", cv2.INTER_LINEAR)):
            wv, out[name][n] = cpu_of(cv2.warpAffine, weight, s2f, size, flags=flag | cv2.WARP_INVERSE_MAP,
                                      borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        acc, wacc = np.zeros(v.shape, np.float32), np.zeros(v.shape, np.float32)
        out["accumulate"][n] = cpu_of(accumulate, v, wv, acc, wacc)[1]
    return out


def shard_costs(root, shards: list, spec, rcfg: dict, n: int) -> dict:
    """Mean CPU seconds per level-0 shard of the layers and the pyramid reduction, over ``n``
    shards spread over ``shards`` (all of them when ``n`` <= 0)."""
    from pipeline.mosaic import downsample2, shard_box, texture_layer, uniqueness_cells
    from pipeline.stages.render import _clipped, layer_halo_px

    params = {k: rcfg[k] for k in ("texture_window_px", "texture_sigma_px", "uniqueness_template_px",
                                   "uniqueness_search_radius_px", "uniqueness_level")}
    halo = layer_halo_px(params)
    arr = root["floor/0"]
    n = len(shards) if n <= 0 else min(n, len(shards))
    pick = [shards[i] for i in np.linspace(0, len(shards) - 1, n).round().astype(int)]
    cost = {"uniqueness": [], "texture": [], "downsample": []}
    cell = spec.layer_cell_px
    for ij in pick:
        r0, r1, c0, c1 = shard_box(ij, arr.shape, spec.shard_px)
        ext = _clipped(arr, r0 - halo, r1 + halo, c0 - halo, c1 + halo, np.uint8(0))
        # as the render measures it ([render] uniqueness_level; level 1 includes its 2x reduction)
        cost["uniqueness"].append(cpu_of(uniqueness_cells, ext, cell, rcfg["uniqueness_template_px"],
                                         rcfg["uniqueness_search_radius_px"], rcfg["uniqueness_exclusion_px"],
                                         level=rcfg["uniqueness_level"], halo_px=halo)[1])
        cost["texture"].append(cpu_of(texture_layer, ext, cell, rcfg["texture_window_px"], rcfg["texture_sigma_px"],
                                      halo_px=halo, sample_px=rcfg["texture_sample_px"])[1])
        cost["downsample"].append(cpu_of(downsample2, np.ascontiguousarray(ext[halo:-halo, halo:-halo]))[1])
    return {k: float(np.mean(v)) for k, v in cost.items()} | {"sampled": len(pick)}


def zstd_seconds(root, levels: int, spec) -> tuple[float, float]:
    """(CPU seconds, MB raw) to zstd-encode every chunk of every level of the floor."""
    import numcodecs

    codec = numcodecs.Zstd(level=spec.zstd_level)
    total, raw = 0.0, 0
    cp, sp = spec.chunk_px, spec.shard_px
    for k in range(levels):
        arr = root[f"floor/{k}"]
        h, w = arr.shape
        for r in range(0, h, sp):
            band = arr[r : r + sp, :]
            for c in range(0, w, cp):
                for rr in range(0, band.shape[0], cp):
                    chunk = np.ascontiguousarray(band[rr : rr + cp, c : c + cp])
                    if not chunk.any():
                        continue  # an empty chunk is not written
                    total += cpu_of(codec.encode, chunk)[1]
                    raw += chunk.nbytes
    return total, raw / 1e6


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--area", type=float, default=40.0, help="Side of bench_render_large's floor, metres.")
    ap.add_argument("--data", type=Path, default=Path("/tmp/bench_large"), help="bench_render_large's --out (kept).")
    ap.add_argument("--sample-shards", type=int, default=0,
                    help="Shards the layers are timed on, spread over the map (0 = every shard; a sample "
                         "is rough: partly covered edge shards cost the texture layer 2x an inner one).")
    ap.add_argument("--skip-render", action="store_true",
                    help="Use the kept render instead of rendering again (no measured render figure).")
    ap.add_argument("--json", type=Path, default=None, help="Write the figures to this JSON file.")
    args = ap.parse_args()

    data = args.data / f"area{args.area:g}"
    measured = None
    if not args.skip_render or not (data / "render" / "touched.json").exists():
        fig = args.data / f"render_area{args.area:g}.json"
        p = subprocess.run([sys.executable, str(REPO / "bench" / "bench_render_large.py"), "--area", f"{args.area:g}",
                            "--out", str(args.data), "--keep", "--reuse", "--json", str(fig)], cwd=REPO)
        if p.returncode not in (0, 1) or not fig.exists():
            print(f"bench_render_large.py failed ({p.returncode})", file=sys.stderr)
            return 1
        measured = json.loads(fig.read_text())["render"]

    import cv2
    import zarr

    from mapstore.layout import read_floor
    from pipeline.config import load_config
    from pipeline.framestore import STORE_NAME, FrameStore
    from pipeline.mosaic import shard_box
    from pipeline.stages.render import frames_to_render, read_stage_poses

    cv2.setNumThreads(1)
    cfg = load_config(None)
    rcfg = cfg["render"]
    work = data / "work"
    store = FrameStore(work / "ingest" / STORE_NAME)
    poses = read_stage_poses(work / "optimize" / "poses.csv")
    log_of = np.zeros(len(poses), np.int64)
    root = zarr.open_group(str(data / "render" / "map.zarr"), mode="r")
    info = read_floor(root)
    grid, spec = info.grid, info.spec
    touched = json.loads((data / "render" / "touched.json").read_text())
    shards0 = [tuple(t) for t in touched["shards"]["0"]]
    boxes = [shard_box(ij, grid.shape, spec.shard_px) for ij in shards0]
    mpix = sum((r1 - r0) * (c1 - c0) for r0, r1, c0, c1 in boxes) / 1e6
    shape, px = store.logs[0].valid.shape, store.pixel_size
    used = {}
    for depth in (int(rcfg["coverage_depth"]), 1):
        used[depth] = np.flatnonzero(frames_to_render(store, poses, log_of, grid, dict(rcfg, coverage_depth=depth))[1])
    every = np.union1d(*used.values()) if len(used) > 1 else next(iter(used.values()))
    print(f"{len(poses)} frames; used at coverage depth {', '.join(f'{d}: {len(u)}' for d, u in used.items())}; "
          f"timing {len(every)} frames, {len(shards0)} shards "
          f"({args.sample_shards if 0 < args.sample_shards < len(shards0) else 'all'} for the layers), one thread ...", flush=True)
    per_frame = frame_costs(store, poses, grid, every, shape, px, float(rcfg["feather_px"]))
    where = {d: np.searchsorted(every, u) for d, u in used.items()}
    per_shard = shard_costs(root, shards0, spec, rcfg, args.sample_shards)
    zstd_s, zstd_mb = zstd_seconds(root, info.levels, spec)
    gflops = sgemm_gflops()
    t, rad = int(rcfg["uniqueness_template_px"]), int(rcfg["uniqueness_search_radius_px"])
    cells = len(shards0) * (spec.shard_px // spec.layer_cell_px) ** 2
    uniq_floor = cells * 2.0 * t * t * (2 * rad + 1) ** 2 / (gflops * 1e9)

    def frames_sum(depth: int, key: str) -> float:
        return float(per_frame[key][where[depth]].sum())

    depth0 = int(rcfg["coverage_depth"])
    kernel0 = rcfg["interpolation"] if rcfg["interpolation"] in ("linear", "cubic") else "cubic"
    layers = {"uniqueness": per_shard["uniqueness"] * len(shards0), "texture": per_shard["texture"] * len(shards0),
              "pyramid": per_shard["downsample"] * len(shards0) * 4 / 3, "zstd": zstd_s}
    settings = {
        f"as rendered (depth {depth0}, {kernel0})": {
            "read": frames_sum(depth0, "decode"), "warp": frames_sum(depth0, kernel0),
            "weight": frames_sum(depth0, "weight_linear"), "accumulate": frames_sum(depth0, "accumulate"), **layers},
        "depth 1, linear; uniqueness at SGEMM": {
            "read": frames_sum(1, "decode"), "warp": frames_sum(1, "linear"), "weight": frames_sum(1, "weight_linear"),
            "accumulate": frames_sum(1, "accumulate"), **layers, "uniqueness": uniq_floor},
        "floor: + nearest, uncompressed": {
            "read": frames_sum(1, "copy"), "warp": frames_sum(1, "nearest"), "weight": frames_sum(1, "weight_nearest"),
            "accumulate": frames_sum(1, "accumulate"), **layers, "uniqueness": uniq_floor},
    }
    budget = mpix / TARGET_MPIX_S * CORES
    print()
    print(f"render lower bounds, {args.area:g} x {args.area:g} m map: {mpix:.1f} MPix level 0 ({len(shards0)} shards, "
          f"{info.levels} levels); {TARGET_MPIX_S:g} MPix/s on {CORES} cores allows {budget:.2f} CPU s in all")
    ms = {k: 1e3 * float(v.mean()) for k, v in per_frame.items() if k != "box_px"}
    print(f"  per frame (ms, mean): decode {ms['decode']:.2f}, copy {ms['copy']:.3f}, warp nearest {ms['nearest']:.2f} / "
          f"linear {ms['linear']:.2f} / cubic {ms['cubic']:.2f}, weight nearest {ms['weight_nearest']:.2f} / linear "
          f"{ms['weight_linear']:.2f}, accumulate {ms['accumulate']:.2f}, over {per_frame['box_px'].mean() / 1e6:.2f} MPix boxes")
    print(f"  per shard (ms, mean of {per_shard['sampled']}): uniqueness {1e3 * per_shard['uniqueness']:.0f}, "
          f"texture {1e3 * per_shard['texture']:.0f}, downsample {1e3 * per_shard['downsample']:.1f}; "
          f"zstd {zstd_mb:.0f} MB in {zstd_s:.2f} s; SGEMM {gflops:.0f} GFLOP/s -> uniqueness correlations "
          f">= {uniq_floor:.2f} s ({cells} cells x {t * t} px x {(2 * rad + 1) ** 2} shifts)")
    rows = ("read", "warp", "weight", "accumulate", "uniqueness", "texture", "pyramid", "zstd")
    print(f"  {'CPU seconds':13}" + "".join(f" | {name:>36}" for name in settings))
    for row in rows:
        print(f"  {row:13}" + "".join(f" | {s[row]:36.2f}" for s in settings.values()))
    totals = {name: sum(s.values()) for name, s in settings.items()}
    print(f"  {'sum':13}" + "".join(f" | {v:36.2f}" for v in totals.values()))
    bounds = {name: CORES * mpix / v for name, v in totals.items()}
    print(f"  {'<= MPix/s':13}" + "".join(f" | {v:36.1f}" for v in bounds.values()))
    figures = {"level0_mpix": mpix, "shards": len(shards0), "budget_cpu_s": budget, "sgemm_gflops": gflops,
               "frames_used": {str(d): len(u) for d, u in used.items()},
               "per_frame_ms": ms,
               "per_shard_ms": {k: 1e3 * v for k, v in per_shard.items() if k != "sampled"},
               "zstd_seconds": zstd_s, "uniqueness_floor_seconds": uniq_floor,
               "settings": settings, "bound_mpix_per_s": bounds}
    if measured is not None:
        cpu = measured["process_cpu_seconds"] + measured.get("children_cpu_seconds", 0.0)
        figures["measured"] = {"seconds": measured["seconds"], "cpu_seconds": cpu,
                               "mpix_per_s": measured["level0_mpix"] / measured["seconds"],
                               "phase_seconds": measured["phase_seconds"]}
        print(f"  measured render, same run: {measured['seconds']:.1f} s wall, {cpu:.1f} CPU s, "
              f"{measured['level0_mpix'] / measured['seconds']:.1f} MPix/s wall")
    print("  not counted above: normalization, no-data masks, coverage counts, the map's files, Python and dask; "
          "perfect 2-core scaling assumed")
    if args.json:
        args.json.write_text(json.dumps(figures, indent=2) + "\n")
        print(f"figures -> {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
