"""Benchmark of the render stage (pipeline.stages.render.run_render) on a large simulated map.

Prints the render's peak memory (RSS) and throughput on a synthetic floor of ``--area`` x
``--area`` metres at the default 2.5 mm pixel (40 x 40 m: ~16000 x 16000 px of frame
centres' span, ~17000 x 17000 px = ~290 MPix level-0 grid with the footprints' reach and
the 0.5 m margin). Target: peak RSS < 2 GB; throughput = level-0 MPix of the touched
shards / render seconds (run_render's ``seconds``: level 0, layers and the whole pyramid).

The work directory is built directly, without the simulator (far too slow at this size):

- one log, a lawnmower route over ``[0.3, area - 0.3]`` m in x and y: lanes along x at most
  ``--lane-spacing`` (0.8 m) apart, heading 0 and pi alternating per lane, a frame every
  ``--step`` metres along a lane. The default step is the larger of 0.2 m and the render's
  own decimation step (``[render] frame_step_fraction`` x the frame's shorter side, 0.3 m
  for 640 x 480 at 2.5 mm with the default 0.25), so that the decimation keeps (nearly)
  every frame and the rendered frame density is the one a real 0.1 m-spaced drive has
  after decimation. ``--step 0.2`` writes more frames, half of which the render drops.
  Each pose is jittered as a vehicle holding its lane drives (``JITTER_ACROSS_M`` = 1 cm
  across the lane, ``JITTER_HEADING_RAD`` = 0.02 rad, seeded): frames at sub-pixel
  positions and headings off 0 / pi, as a real drive's. Lanes along the map's axes are the
  cheap case for the warps: OpenCV's cubic warp costs ~2.7 ns per box pixel at headings
  near 0 or pi/2 and ~4.5 at 45 degrees, over a box twice the frame's area (linear: ~1.4
  ns at any heading), so a site whose aisles run diagonally to the map's axes renders slower;
- 640 x 480 frames (1.6 x 1.2 m), valid mask all True, written with
  :class:`pipeline.framestore.LogFramesWriter` (16-frame shards, zstd) into
  ``WORKDIR/ingest/frames.zarr``; ``WORKDIR/optimize/poses.csv`` holds the same poses as
  the odometry prior (the optimized poses of a perfect run);
- frame content: crops of one periodic band-limited random texture (``--texture-px``,
  4096 x 4096 float32 = 10.24 m square, white noise Gaussian-filtered at two scales in the
  Fourier domain), which tiles the floor seamlessly: each frame is sampled (bilinear) with
  ``cv2.warpAffine`` through :meth:`mapstore.grid.MapGrid.frame_to_grid_affine` at its pose
  taken modulo the period, the texture's edges wrapping. No sensor noise or blur (the
  simulated 5 x 5 m floor of ``bench/bench_render.py`` has both);
- ``[render] gain_compensation = false`` (no links.csv: gains are all 1).

The rendered level 0 is then compared with the world, shard by shard
(:func:`pipeline.evaluate.mosaic_vs_world`, the texture wrapping; unless
``--no-quality``): NCC and PSNR (the render's quality targets: NCC >= 0.99, PSNR >= 35
dB), the worst shard and over all covered pixels.

The render runs in a fresh child process (``python -c``: imports, the C allocator tuned as
the command line tunes it (:func:`pipeline.allocator.tune_allocator`), ``run_render``, one
JSON line) so that its memory is its own. Peak RSS is reported three ways:

- ``VmHWM`` of the child (its own high-water mark; exact for the threads/sync schedulers);
- ``ru_maxrss`` from ``os.wait4`` on the child (the max over the child and the workers it
  reaped; Linux starts a child's mark at its parent's RSS at fork time, which is why data
  generation also runs in a child and this parent stays small);
- the peak of the summed RSS of the child and all its descendants, sampled every 0.2 s
  (``psutil``; the figure that matters for ``--scheduler processes``, a lower bound since
  a sample can miss coinciding peaks; an upper bound, VmHWM + workers x the largest
  worker's ru_maxrss, is printed beside it).

Then (unless ``--no-agreement``) the rendered uniqueness layer is checked against the same
cells computed on level 0 (``[render] uniqueness_level`` = 1 measures it on level 1): the
share of cells on the same side of Kelly's (2000) 0.2.

Timings are wall clock on a possibly busy 2-core machine: figures, not assertions. Exit
code 0 when peak RSS is under ``--rss-target-mb`` (2048), 1 otherwise.

    python bench/bench_render_large.py [--area 40] [--scheduler threads] [--keep] [--reuse]
                                       [--out /tmp/bench_large] [--step auto] [--json FILE]

Quick smoke test: ``--area 10``. The data under ``--out`` is deleted at the end unless
``--keep``; ``--reuse`` renders again from kept data of the same parameters.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

from peak_memory import CHILD_PRELUDE

REPO = Path(__file__).resolve().parents[1]
FRAME_H, FRAME_W = 480, 640
EDGE_M = 0.3  # route from EDGE_M to area - EDGE_M in x and y
SPEED_M_S = 0.5  # frame times: distance along the route / speed
JITTER_ACROSS_M = 0.01  # 1-sigma pose jitter across the lane (metres) ...
JITTER_HEADING_RAD = 0.02  # ... and of the heading (radians); none along the lane (spacing kept)

# The render child: imports, records the high-water mark, renders, prints one JSON line.
_CHILD = r"""
import json, resource, sys, time
from pathlib import Path


from peak_memory import hwm_kb

workdir, out_dir, scheduler, workers = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3], int(sys.argv[4])
import cv2, dask, numpy, zarr  # the render's imports, before the baseline
from pipeline.config import load_config
from pipeline.stages.render import STAGE, run_render
from pipeline.stages.stage import BuildContext
from pipeline.stages.workspace import Workspace
from pipeline.allocator import tune_allocator
tune_allocator()  # as the command line does (pipeline/cli): freed frame-sized blocks reused, not faulted in again
cfg = load_config(None)
cfg["render"]["gain_compensation"] = False
cfg["render"]["scheduler"] = scheduler
cfg["render"]["workers"] = workers
for kv in sys.argv[5:]:  # --set render.key=value overrides (TOML values)
    import tomllib
    key, value = kv.split("=", 1)
    section, name = key.split(".", 1)
    cfg[section][name] = tomllib.loads(f"v = {value}")["v"]
base_kb = hwm_kb()
t0 = time.perf_counter()
ru0 = resource.getrusage(resource.RUSAGE_SELF)
rep = run_render(Workspace(workdir).writing("render", out_dir), STAGE.params(cfg, BuildContext(quiet=True)))
ru1 = resource.getrusage(resource.RUSAGE_SELF)
wall = time.perf_counter() - t0
r = rep["render"]
r.update({"wall_seconds": wall, "rss_after_imports_mb": base_kb / 1024.0, "vmhwm_mb": hwm_kb() / 1024.0,
          "workers": cfg["render"]["workers"] or __import__("os").cpu_count(),
          # CPU of the whole render process (every thread, zarr's I/O loop included)
          "process_cpu_seconds": (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime),
          "process_sys_seconds": ru1.ru_stime - ru0.ru_stime,
          # worker processes (--scheduler processes), reaped when the render's pool closed
          "children_cpu_seconds": sum(getattr(resource.getrusage(resource.RUSAGE_CHILDREN), f) for f in ("ru_utime", "ru_stime")),
          "task_block_shards": cfg["render"]["task_block_shards"], "coverage_depth": cfg["render"]["coverage_depth"],
          "shard_px": cfg["map"]["shard_px"]})
print(json.dumps(r))
"""


# --- the synthetic work directory --------------------------------------------------------


def decimation_step_m(cfg: dict, px: float) -> float:
    """The render's decimation distance for our frames (0 when [render] frame_step_fraction is 0)."""
    frac = float(cfg["render"]["frame_step_fraction"])
    return frac * min(FRAME_H, FRAME_W) * px


def plan_route(area: float, step: float, lane_spacing: float, seed: int = 1):
    """(N, 3) poses of the lawnmower route (jittered across the lane and in heading, see the
    module docstring), (N,) frame times, the lane count and spacing."""
    import numpy as np

    lo, hi = EDGE_M, area - EDGE_M
    n_lanes = int(math.ceil((hi - lo) / lane_spacing - 1e-9)) + 1
    ys = np.linspace(lo, hi, n_lanes)
    n_along = int(math.floor((hi - lo) / step + 1e-9)) + 1
    xs = lo + step * np.arange(n_along)
    parts = []
    for j, y in enumerate(ys):
        x = xs if j % 2 == 0 else xs[::-1]
        theta = 0.0 if j % 2 == 0 else math.pi
        parts.append(np.column_stack([x, np.full_like(x, y), np.full_like(x, theta)]))
    poses = np.vstack(parts)
    rng = np.random.default_rng(seed)
    poses[:, 1] += rng.normal(0.0, JITTER_ACROSS_M, len(poses))
    poses[:, 2] += rng.normal(0.0, JITTER_HEADING_RAD, len(poses))
    d = np.r_[0.0, np.cumsum(np.hypot(np.diff(poses[:, 0]), np.diff(poses[:, 1])))]
    return poses, d / SPEED_M_S, n_lanes, float(ys[1] - ys[0]) if n_lanes > 1 else 0.0


def make_texture(side: int, seed: int):
    """float32 (side, side) band-limited random texture, grey levels ~128 +- 35, in 1..254:
    white noise Gaussian-filtered at two scales (1.5 and 12 px) in the Fourier domain, so it
    is periodic (it tiles the floor seamlessly, every ``side`` pixels)."""
    import numpy as np

    rng = np.random.default_rng(seed)
    fy, fx = np.fft.fftfreq(side)[:, None], np.fft.rfftfreq(side)[None, :]
    f2 = fx * fx + fy * fy

    def blurred(sigma: float) -> np.ndarray:
        spec = np.fft.rfft2(rng.standard_normal((side, side)))
        spec *= np.exp(-2.0 * math.pi ** 2 * sigma ** 2 * f2)
        b = np.fft.irfft2(spec, s=(side, side))
        return b / b.std()

    tex = (blurred(1.5) + 0.5 * blurred(12.0)).astype(np.float32)
    tex *= np.float32(35.0 / tex.std())
    tex += np.float32(128.0)
    return np.clip(tex, 1.0, 254.0, out=tex)


def texture_grid(texture_px: int, px: float):
    """The texture's grid: its pixel (0, 0) centred on the world origin's row / column
    (:class:`mapstore.grid.MapGrid`); the world is this tile repeated every ``texture_px`` px."""
    from mapstore.grid import MapGrid

    return MapGrid(0.0, (texture_px - 1) * px, px, texture_px, texture_px)


def generate(work: Path, area: float, step: float, lane_spacing: float, texture_px: int, seed: int) -> dict:
    """Write ``work/ingest/frames.zarr`` and ``work/optimize/poses.csv``; returns figures."""
    from concurrent.futures import ThreadPoolExecutor

    import cv2
    import numpy as np

    from pipeline.config import load_config
    from pipeline.drivelog import POSE_COLUMNS
    from pipeline.framestore import QUALITY_COLUMNS, STORE_NAME, LogFramesWriter, create_store

    t0 = time.perf_counter()
    cfg = load_config(None)
    px = float(cfg["simulate"]["floor"]["pixel_size_m"])
    poses, t, n_lanes, lane_m = plan_route(area, step, lane_spacing, seed)
    tex = make_texture(texture_px, seed)
    tex_grid = texture_grid(texture_px, px)
    period = texture_px * px  # the world repeats the (periodic) texture every period metres
    log_id = "bench_large"
    (work / "ingest").mkdir(parents=True, exist_ok=True)
    (work / "optimize").mkdir(parents=True, exist_ok=True)
    root = create_store(work / "ingest" / STORE_NAME, px)
    writer = LogFramesWriter(root, 0, {
        "log_id": log_id, "path": str(work / "log"), "camera": {}, "raw_shape": [FRAME_H, FRAME_W],
        "flat_field": {"source": "none"}, "frames_in_log": len(poses),
    }, np.ones((FRAME_H, FRAME_W), bool))

    def frame(i: int):
        x, y, th = poses[i]
        pose = np.array([x % period, y % period, th])
        m = tex_grid.frame_to_grid_affine(pose, (FRAME_H, FRAME_W), px)  # frame px -> texture px
        return cv2.warpAffine(tex, m, (FRAME_W, FRAME_H), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_WRAP)

    quality = tuple(0.0 for _ in QUALITY_COLUMNS)
    with ThreadPoolExecutor(os.cpu_count() or 1) as pool:
        for i, img in enumerate(pool.map(frame, range(len(poses)))):
            writer.append(img, float(t[i]), poses[i], i, quality)
    stored = writer.close()
    root.attrs["logs"] = [{
        "log_id": log_id, "frames_total": stored, "frames_accepted": stored, "frames_rejected": 0,
        "raw_shape": [FRAME_H, FRAME_W], "rectified_shape": [FRAME_H, FRAME_W], "flat_field": {"source": "none"},
    }]
    lines = [",".join(POSE_COLUMNS + ("log_id", "frame"))]
    lines += [f"{t[i]!r},{x!r},{y!r},{th!r},{log_id},{i}" for i, (x, y, th) in enumerate(poses.tolist())]
    (work / "optimize" / "poses.csv").write_text("\n".join(lines) + "\n")
    return {"frames": int(stored), "lanes": n_lanes, "step_m": step, "lane_spacing_m": lane_m,
            "texture_px": texture_px, "texture_period_m": period, "generate_seconds": time.perf_counter() - t0,
            "frames_zarr_mb": dir_bytes(work / "ingest" / STORE_NAME) / 2**20}


def dir_bytes(path: Path) -> int:
    """Apparent size of the files under ``path`` (bytes)."""
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def dir_files(path: Path) -> int:
    return sum(1 for f in path.rglob("*") if f.is_file())


# --- the render child, measured ------------------------------------------------------------


class TreeRss:
    """Samples the summed RSS of a process and its descendants (peak, MB)."""

    def __init__(self, pid: int, period_s: float = 0.2):
        self.peak_mb = float("nan")
        self.samples: list[tuple[float, float]] = []  # (seconds since start, MB)
        try:
            import psutil
        except ImportError:
            return
        self.peak_mb = 0.0
        self._proc = psutil.Process(pid)
        self._psutil = psutil
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(period_s,), daemon=True)
        self._thread.start()

    def _run(self, period_s: float) -> None:
        ps = self._psutil
        t0 = time.perf_counter()
        while not self._stop.is_set():
            try:
                procs = [self._proc] + self._proc.children(recursive=True)
            except ps.Error:
                return
            total = 0
            for p in procs:
                try:
                    total += p.memory_info().rss
                except ps.Error:
                    pass
            self.peak_mb = max(self.peak_mb, total / 2**20)
            self.samples.append((time.perf_counter() - t0, total / 2**20))
            self._stop.wait(period_s)

    def stop(self) -> float:
        if hasattr(self, "_stop"):
            self._stop.set()
            self._thread.join()
        return self.peak_mb


def render(work: Path, out_dir: Path, scheduler: str, workers: int, overrides: list[str] = ()) -> dict:
    """run_render in a child process; its figures plus the measured peaks."""
    out_dir.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.Popen([sys.executable, "-c", CHILD_PRELUDE + _CHILD, str(work), str(out_dir), scheduler, str(workers),
                          *overrides],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO, env=env)
    sampler = TreeRss(p.pid)
    err: list[str] = []
    reader = threading.Thread(target=lambda: err.append(p.stderr.read()), daemon=True)
    reader.start()
    out = p.stdout.read()
    _, status, ru = os.wait4(p.pid, 0)
    p.returncode = os.waitstatus_to_exitcode(status)
    tree_mb = sampler.stop()
    reader.join()
    if p.returncode != 0:
        raise RuntimeError(f"render failed ({p.returncode}):\n{''.join(err)[-4000:]}")
    r = json.loads(out.strip().splitlines()[-1])
    r["wait4_maxrss_mb"] = ru.ru_maxrss / 1024.0
    r["tree_rss_peak_mb"] = tree_mb
    r["tree_rss_trace"] = [(round(t, 1), round(mb)) for t, mb in sampler.samples]
    r["peak_rss_mb"] = max(v for v in (r["vmhwm_mb"], r["wait4_maxrss_mb"], tree_mb) if v == v)
    store = out_dir / "map.zarr"
    r["map_zarr_mb"] = dir_bytes(store) / 2**20
    r["map_zarr_files"] = dir_files(store)
    r["touched_json_kb"] = (out_dir / "touched.json").stat().st_size / 1024.0
    return r


# --- the uniqueness layer on level 1 against level 0 ------------------------------------


def uniqueness_agreement(map_dir: Path, workers: int, overrides: list[str] = ()) -> dict:
    """The rendered map's uniqueness layer against the same cells computed on level 0
    (:func:`pipeline.mosaic.uniqueness_cells`, every shard with its halo): the
    :class:`pipeline.evaluate.ThresholdAgreement` at Kelly's (2000) 0.2, and CPU seconds
    (``overrides``: the render's ``--set`` values)."""
    from concurrent.futures import ThreadPoolExecutor

    import numpy as np
    import zarr

    from mapstore.layout import read_floor
    from pipeline.config import load_config
    from pipeline.evaluate import threshold_agreement
    from pipeline.mosaic import shard_box, uniqueness_cells
    from pipeline.stages.render import layer_halo_px

    import tomllib

    t0 = time.process_time()
    cfg = load_config(None)
    for kv in overrides:
        key, value = kv.split("=", 1)
        section, name = key.split(".", 1)
        cfg[section][name] = tomllib.loads(f"v = {value}")["v"]
    rcfg = cfg["render"]
    root = zarr.open_group(str(map_dir), mode="r")
    info = read_floor(root)
    level0, layer = root["floor/0"], root["floor/layers/uniqueness"]
    cell, sp, halo = info.spec.layer_cell_px, info.spec.shard_px, layer_halo_px(rcfg)
    h, w = info.grid.shape
    ref = np.full(layer.shape, np.nan, np.float32)

    def one(ij):
        r0, r1, c0, c1 = shard_box(ij, (h, w), sp)
        ext = np.zeros((r1 - r0 + 2 * halo, c1 - c0 + 2 * halo), np.uint8)
        a0, a1, b0, b1 = max(r0 - halo, 0), min(r1 + halo, h), max(c0 - halo, 0), min(c1 + halo, w)
        ext[a0 - r0 + halo : a1 - r0 + halo, b0 - c0 + halo : b1 - c0 + halo] = level0[a0:a1, b0:b1]
        if ext.any():
            ref[r0 // cell : -(-r1 // cell), c0 // cell : -(-c1 // cell)] = uniqueness_cells(
                ext, cell, rcfg["uniqueness_template_px"], rcfg["uniqueness_search_radius_px"],
                rcfg["uniqueness_exclusion_px"], level=0, halo_px=halo)

    with ThreadPoolExecutor(max(1, workers)) as pool:
        list(pool.map(one, [(i, j) for i in range(-(-h // sp)) for j in range(-(-w // sp))]))
    a = threshold_agreement(ref, layer[...], 0.2)
    return dict(a.__dict__, level=int(rcfg["uniqueness_level"]), cpu_seconds=time.process_time() - t0)


# --- the rendered map against the world -------------------------------------------------


def render_quality(map_dir: Path, texture_px: int, seed: int, workers: int) -> dict:
    """Level 0 of the rendered map against the periodic world texture, shard by shard
    (:func:`pipeline.evaluate.mosaic_vs_world` with ``wrap``): the worst shard's NCC and
    PSNR, and over all covered pixels the pixel-weighted mean NCC and the PSNR of the
    pooled squared error (each shard after its own linear fit; with no gains to fit here
    they are ~1 and ~0)."""
    from concurrent.futures import ThreadPoolExecutor

    import numpy as np
    import zarr

    from mapstore.grid import MapGrid
    from mapstore.layout import read_floor
    from pipeline.evaluate import mosaic_vs_world
    from pipeline.mosaic import shard_box

    t0 = time.process_time()
    root = zarr.open_group(str(map_dir), mode="r")
    info = read_floor(root)
    level0, grid, sp = root["floor/0"], info.grid, info.spec.shard_px
    tex, tex_grid = make_texture(texture_px, seed), texture_grid(texture_px, grid.pixel_size)
    h, w = grid.shape

    def one(ij):
        r0, r1, c0, c1 = shard_box(ij, (h, w), sp)
        img = level0[r0:r1, c0:c1]
        if np.count_nonzero(img) < 1000:
            return None
        x0, y0 = grid.pixel_to_world(c0, r0)
        q = mosaic_vs_world(img, MapGrid(float(x0), float(y0), grid.pixel_size, c1 - c0, r1 - r0), tex, tex_grid,
                            wrap=True)
        return q

    with ThreadPoolExecutor(max(1, workers)) as pool:
        qs = [q for q in pool.map(one, [(i, j) for i in range(-(-h // sp)) for j in range(-(-w // sp))]) if q]
    n = np.array([q["pixels"] for q in qs], float)
    ncc, rmse = np.array([q["ncc"] for q in qs]), np.array([q["rmse"] for q in qs])
    pooled = float(np.sqrt((n * rmse ** 2).sum() / n.sum()))
    return {"shards": len(qs), "pixels": int(n.sum()), "ncc_min": float(ncc.min()),
            "ncc_mean": float((n * ncc).sum() / n.sum()), "psnr_min_db": float(min(q["psnr_db"] for q in qs)),
            "psnr_db": float(20 * np.log10(255.0 / max(pooled, 1e-9))), "cpu_seconds": time.process_time() - t0}


# --- main ------------------------------------------------------------------------------


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--area", type=float, default=40.0, help="Side of the square floor, metres (10 = quick smoke test).")
    ap.add_argument("--scheduler", default="threads", help="[render] scheduler: threads, processes, sync or tcp://...")
    ap.add_argument("--workers", type=int, default=0, help="[render] workers (0 = one per core).")
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_large"), help="Data directory (deleted unless --keep).")
    ap.add_argument("--keep", action="store_true", help="Keep the data directory.")
    ap.add_argument("--reuse", action="store_true", help="Reuse the kept frames store of the same parameters.")
    ap.add_argument("--step", default="auto", help="Frame spacing along a lane, metres, or 'auto' (see the docstring).")
    ap.add_argument("--lane-spacing", type=float, default=0.8, help="Largest lane spacing, metres.")
    ap.add_argument("--texture-px", type=int, default=4096, help="Side of the periodic texture, pixels.")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--rss-target-mb", type=float, default=2048.0)
    ap.add_argument("--trace", type=float, default=0.0, metavar="S",
                    help="Also print the sampled RSS of the render every S seconds.")
    ap.add_argument("--json", type=Path, default=None, help="Write the figures to this JSON file.")
    ap.add_argument("--no-agreement", action="store_true",
                    help="Skip the uniqueness layer's check against level 0 (~20 CPU s at 40 m).")
    ap.add_argument("--no-quality", action="store_true",
                    help="Skip the rendered level 0's comparison with the world texture (~1 CPU s per shard).")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                    help="Override a config value for the render (TOML value), e.g. render.coverage_depth=0.")
    args = ap.parse_args()

    from pipeline.config import load_config

    cfg = load_config(None)
    px = float(cfg["simulate"]["floor"]["pixel_size_m"])
    decim = decimation_step_m(cfg, px)
    step = max(0.2, decim * 1.0001) if args.step == "auto" else float(args.step)
    params = {"area": args.area, "step": step, "lane_spacing": args.lane_spacing, "texture_px": args.texture_px, "texture": "periodic",
              "seed": args.seed, "frame": [FRAME_H, FRAME_W], "px": px,
              "jitter": [JITTER_ACROSS_M, JITTER_HEADING_RAD]}
    data = args.out / f"area{args.area:g}"
    work, out_dir = data / "work", data / "render"
    params_file = data / "params.json"
    reuse = args.reuse and params_file.exists() and json.loads(params_file.read_text()).get("params") == params
    figures: dict = {"cpu_count": os.cpu_count(), "params": params, "decimation_step_m": decim}
    try:
        existing = next(p for p in (args.out, *args.out.parents) if p.exists())  # --out may not exist yet
        print(f"disk: {shutil.disk_usage(existing).free / 2**30:.0f} GiB "
              f"free at {args.out}", flush=True)
        if reuse:
            gen = json.loads(params_file.read_text())["generate"]
            shutil.rmtree(out_dir, ignore_errors=True)
            print(f"reusing {work} ({gen['frames']} frames)", flush=True)
        else:
            shutil.rmtree(data, ignore_errors=True)
            data.mkdir(parents=True)
            # In a child too, so that this process stays small (see the docstring on ru_maxrss).
            code = ("import json, sys; from pathlib import Path; sys.path.insert(0, sys.argv[1]); "
                    "from bench_render_large import generate; "
                    "print(json.dumps(generate(Path(sys.argv[2]), *map(float, sys.argv[3:6]), int(sys.argv[6]), "
                    "int(sys.argv[7]))))")
            p = subprocess.run([sys.executable, "-c", code, str(Path(__file__).resolve().parent), str(work),
                                str(args.area), str(step), str(args.lane_spacing), str(args.texture_px), str(args.seed)],
                               capture_output=True, text=True, cwd=REPO)
            if p.returncode != 0:
                raise RuntimeError(f"data generation failed ({p.returncode}):\n{p.stderr[-4000:]}")
            gen = json.loads(p.stdout.strip().splitlines()[-1])
            params_file.write_text(json.dumps({"params": params, "generate": gen}, indent=2) + "\n")
            print(f"generated {gen['frames']} frames of {FRAME_W}x{FRAME_H} ({gen['lanes']} lanes, "
                  f"{gen['step_m']:.4f} m apart along lanes, lanes {gen['lane_spacing_m']:.3f} m apart) in "
                  f"{gen['generate_seconds']:.1f} s; frames.zarr {gen['frames_zarr_mb']:.0f} MB "
                  f"(a periodic texture of {args.texture_px} px, every {gen['texture_period_m']:.2f} m)", flush=True)
        figures["generate"] = gen

        print(f"render ({args.scheduler}) ...", flush=True)
        r = render(work, out_dir, args.scheduler, args.workers, args.set)
        figures["render"] = r
        rows, cols = r["grid_px"]
        cpu = r["process_cpu_seconds"] + r.get("children_cpu_seconds", 0.0)
        print()
        print(f"render of a {args.area:g} x {args.area:g} m map at {px * 1000:g} mm/px "
              f"(scheduler {args.scheduler}, {r['workers']} workers, {r['tasks']} tasks of up to {r['block_side']} x "
              f"{r['block_side']} shards, {os.cpu_count()} cores){'; ' + ', '.join(args.set) if args.set else ''}")
        table = [
            ("frames", f"{gen['frames']}"),
            ("frames used", f"{r['frames_used']} of {r['frames_decimated']} after the decimation (step {decim:.3f} m; "
                            f"coverage_depth {r['coverage_depth']}, selection {r['select_seconds']:.2f} s)"),
            ("shards (level 0)", f"{r['shards']} of {r['shard_px']} px; {r['frames_per_shard_mean']:.1f} frames/shard"),
            ("grid", f"{cols} x {rows} px, {r['levels']} levels"),
            ("level-0 MPix", f"{r['level0_mpix']:.1f} ({r['covered_mpix']:.1f} covered)"),
            ("render seconds", f"{r['seconds']:.1f} (stage {r['stage_seconds']:.1f}, child wall {r['wall_seconds']:.1f})"),
            ("MPix/s", f"{r['level0_mpix'] / r['seconds']:.2f} wall, {r['level0_mpix'] / cpu:.2f} "
                       f"per CPU second ({cpu:.1f} CPU s, all threads and worker processes, {r['process_sys_seconds']:.1f} "
                       f"of them in the kernel; level-0 output, pyramid, layers and writing included)"),
            ("phases", f"level 0 {r['level0_seconds']:.1f} s + pyramid {r['pyramid_seconds']:.1f} s wall; in the "
                       "level-0 tasks (seconds summed over workers): " + ", ".join(
                           f"{k} {v:.1f}" for k, v in r["phase_seconds"].items())),
            ("peak RSS MB", f"{r['peak_rss_mb']:.0f} (VmHWM {r['vmhwm_mb']:.0f}, wait4 ru_maxrss "
                            f"{r['wait4_maxrss_mb']:.0f}, sampled tree {r['tree_rss_peak_mb']:.0f}; "
                            f"after imports {r['rss_after_imports_mb']:.0f})"),
        ]
        if args.scheduler not in ("threads", "sync"):
            # Worker processes: the sample may miss coinciding peaks; bound them from above by
            # the render process's own mark plus every worker at the largest worker's mark.
            bound = r["vmhwm_mb"] + r["workers"] * r["wait4_maxrss_mb"]
            r["peak_rss_upper_bound_mb"] = bound
            table.append(("peak RSS bound MB", f"{bound:.0f} (VmHWM + {r['workers']} workers x the largest "
                                                f"worker's ru_maxrss)"))
        table += [
            ("map.zarr", f"{r['map_zarr_mb']:.0f} MB in {r['map_zarr_files']} files; touched.json "
                         f"{r['touched_json_kb']:.1f} KB"),
            ("frames.zarr", f"{gen['frames_zarr_mb']:.0f} MB"),
        ]
        for name, value in table:
            print(f"  {name:18} {value}")
        if args.trace > 0 and r["tree_rss_trace"]:
            trace, last = [], -1e9
            for t, mb in r["tree_rss_trace"]:
                if t - last >= args.trace:
                    trace.append(f"{t:.0f}s:{mb}")
                    last = t
            print("  sampled RSS MB     " + " ".join(trace))
        if not args.no_quality:
            q = render_quality(out_dir / "map.zarr", args.texture_px, args.seed, os.cpu_count() or 1)
            figures["quality"] = q
            q_ok = q["ncc_min"] >= 0.99 and q["psnr_min_db"] >= 35.0
            print(f"  {'vs the world':18} NCC {q['ncc_mean']:.4f} (worst shard {q['ncc_min']:.4f}), PSNR "
                  f"{q['psnr_db']:.2f} dB (worst shard {q['psnr_min_db']:.2f}) over {q['pixels'] / 1e6:.1f} MPix "
                  f"of {q['shards']} shards: quality targets (NCC >= 0.99, PSNR >= 35 dB) "
                  f"{'met' if q_ok else 'NOT met'} ({q['cpu_seconds']:.0f} CPU s to check)")
        if not args.no_agreement:
            a = uniqueness_agreement(out_dir / "map.zarr", os.cpu_count() or 1, args.set)
            figures["uniqueness_agreement"] = a
            print(f"  {'uniqueness':18} layer on level {a['level']} vs level 0: {100 * a['fraction']:.3f} % of "
                  f"{a['cells']} cells on the same side of 0.2 (below 0.2: {a['below_reference']} on level 0, "
                  f"{a['below_other']} on level {a['level']}; {a['missing']} cells without a value there, "
                  f"{a['extra']} with one only there; {a['cpu_seconds']:.0f} CPU s to check)")
        ok = r["peak_rss_mb"] < args.rss_target_mb
        figures["rss_ok"] = ok
        print(f"target peak RSS < {args.rss_target_mb:.0f} MB: {'PASS' if ok else 'FAIL'}  "
              f"(no peer figure for this benchmark; wall clock on a possibly shared machine)")
        if args.json:
            args.json.write_text(json.dumps(figures, indent=2) + "\n")
            print(f"figures -> {args.json}")
        return 0 if ok else 1
    finally:
        if not args.keep:
            shutil.rmtree(data, ignore_errors=True)
            try:
                args.out.rmdir()  # only when nothing else is left in it
            except OSError:
                pass


if __name__ == "__main__":
    sys.exit(main())
