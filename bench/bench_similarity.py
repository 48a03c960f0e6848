"""Benchmark of ``[optimize] pose_model = "similarity2"`` on a camera whose height varies.

A simulated lawnmower (default 5 x 5 m, 2.5 mm, 320 x 240 frames, 1 % odometry drift, noise
sigma 5, ``--seed 1``) with ``--height-jitter 0.02`` (the camera height varies smoothly by up
to +-2 %, unknown to the log; truth in ``ground_truth_height.csv``) is built to a map with
``pose_model = "pose2"`` and with ``"similarity2"``. For each it prints:

- links accepted / rejected (registration, outliers);
- pose error vs ground truth after a rigid SE(2) alignment, RMS / max (map pixels; report
  ``ground_truth.pose_rms_px`` / ``pose_max_px``);
- link residual RMS / max after optimization (report ``optimization.residual_*``);
- link error vs ground truth, median / p95 (report ``ground_truth.link_error_*``: where the
  link puts the point of b that the truth puts midway between the frame centres, in a's
  pixels; similarity links against the true relative pose and scale, rigid ones against
  the true relative pose);
- scale error vs truth (similarity2): RMS / max of ``scale - true scale`` per frame, and
  the link log-scale error median / p95;
- the published mosaic vs the world texture (:func:`pipeline.evaluate.mosaic_vs_world`):
  NCC and PSNR;
- build seconds.

Timings are wall clock on a possibly busy machine: figures, not assertions.

    python bench/bench_similarity.py [--out DIR] [--seed 1] [--area 5x5] [--jitter 0.02] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import zarr

from mapstore.layout import read_floor
from mapstore.repository import MapRepository
from pipeline.evaluate import align_se2, ground_truth_at, mosaic_vs_world
from pipeline.links import read_links
from pipeline.optimize import sim_between
from pipeline.stages.optimize import read_poses_table
from pipeline.simulate.texture import read_float_tiff

PX = 0.0025


def mosaicmap(*args) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "pipeline.cli", *map(str, args)], check=True)
    return time.perf_counter() - t0


def true_scales(log: Path, t: np.ndarray) -> np.ndarray:
    """Per-frame truth scale (height / calibrated height) at frame times ``t``; ones without the file."""
    path = log / "ground_truth_height.csv"
    if not path.exists():
        return np.ones(len(t))
    d = np.atleast_1d(np.genfromtxt(path, delimiter=",", names=True))
    return np.interp(t, d["t"], d["scale"])


def figures(log: Path, work: Path, mapdir: Path, report: dict) -> dict:
    poses_tab = read_poses_table(work / "optimize" / "poses.csv")
    t = np.asarray(poses_tab["t"], float)
    poses = np.column_stack([poses_tab["x"], poses_tab["y"], poses_tab["theta"]]).astype(float)
    scales = np.asarray(poses_tab["scale"], float) if "scale" in poses_tab.dtype.names else None
    gt = ground_truth_at(t, log / "ground_truth.csv")
    s_true = true_scales(log, t)
    gt4 = np.column_stack([gt, s_true])
    links = [lk for lk in read_links(work / "optimize" / "links.csv") if lk.status == "accepted"]
    a = np.array([lk.a for lk in links])
    b = np.array([lk.b for lk in links])
    truth_rel = sim_between(gt4[a], gt4[b])
    res = np.array([float(lk.extra["residual_px"]) for lk in links])
    out = {
        "links_accepted": report["links"]["accepted"],
        "links_rejected_registration": report["links"]["rejected_registration"],
        "links_rejected_outliers": report["links"]["rejected_outliers"],
        "pose_rms_px": report["ground_truth"]["pose_rms_px"],
        "pose_max_px": report["ground_truth"]["pose_max_px"],
        "residual_rms_px": float(np.sqrt(np.mean(res**2))),
        "residual_max_px": float(res.max()),
        "link_error_median_px": report["ground_truth"]["link_error_median_px"],
        "link_error_p95_px": report["ground_truth"]["link_error_p95_px"],
    }
    if scales is not None:
        ds = scales - s_true
        out["scale_error_rms"] = float(np.sqrt(np.mean(ds**2)))
        out["scale_error_max"] = float(np.abs(ds).max())
        ls = np.array([lk.log_scale for lk in links], float)
        le = np.abs(ls - truth_rel[:, 3])
        out["link_log_scale_error_median"] = float(np.median(le))
        out["link_log_scale_error_p95"] = float(np.percentile(le, 95))
    out["true_scale_range"] = [float(s_true.min()), float(s_true.max())]
    root = zarr.open_group(MapRepository.open(str(mapdir)).readonly().store, mode="r")
    info = read_floor(root)
    mosaic = root["floor/0"][...]
    rot, trans = align_se2(poses[:, :2], gt[:, :2])
    tex = read_float_tiff(log / "world" / "texture.tif")
    from mapstore.grid import MapGrid

    tex_grid = MapGrid.from_attrs(json.loads((log / "world" / "grid.json").read_text()))
    mv = mosaic_vs_world(mosaic, info.grid, tex, tex_grid, rot, trans)
    out["mosaic_ncc"] = mv["ncc"]
    out["mosaic_psnr_db"] = mv["psnr_db"]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--area", default="5x5")
    ap.add_argument("--jitter", type=float, default=0.02)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="bench_similarity_"))
    out.mkdir(parents=True, exist_ok=True)
    log = out / "log"
    if not (log / "drive.toml").exists():
        t = mosaicmap("simulate", "floor", log, "--seed", args.seed, "--area", args.area,
                      "--height-jitter", args.jitter, "--quiet")
        print(f"simulated {args.area} m, height jitter {args.jitter:g}: {t:.1f} s")
    results = {}
    for model in ("pose2", "similarity2"):
        work, mapdir, rep = out / f"w_{model}", out / f"map_{model}", out / f"report_{model}.json"
        shutil.rmtree(work, ignore_errors=True)
        shutil.rmtree(mapdir, ignore_errors=True)
        cfg = out / f"{model}.toml"
        cfg.write_text(f'[optimize]\npose_model = "{model}"\n')
        secs = mosaicmap("build", log, "-w", work, "--map", mapdir, "--config", cfg, "--report", rep, "--quiet")
        r = figures(log, work, mapdir, json.loads(rep.read_text()))
        r["build_seconds"] = secs
        results[model] = r
        print(f"\n== {model} ==")
        for k, v in r.items():
            print(f"  {k}: {v:.4g}" if isinstance(v, float) else f"  {k}: {v}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
