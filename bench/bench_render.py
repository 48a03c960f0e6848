"""Benchmark of the nightly build's render and publish (issue: versioned tiled map).

On the simulated 5 x 5 m lawnmower floor (``--seed 1``, 320 x 240 frames at 2.5 mm, the
defaults of ``mosaicmap simulate floor``), it runs ``mosaicmap build --map`` and prints:

- the published level-0 mosaic against the simulator's ground-truth world texture over the
  covered area, after the rigid SE(2) alignment of the optimized poses onto the ground
  truth (:func:`pipeline.evaluate.mosaic_vs_world`): NCC, and PSNR after a global linear
  intensity fit (the mosaic's exposure scale is that of the frames, not the world's);
- the seam metric (:func:`pipeline.evaluate.seam_ratio`): gradient energy within 2 px of
  the rendered frames' footprint edges over that elsewhere (1 = seams invisible);
- render throughput: level-0 MPix of touched shards per second, pyramid and layers
  included (the render stage's wall time), and the publish time;
- the same quality figures and time for a peer on the same frames, poses and gains:
  OpenCV's stitching ``detail.FeatherBlender`` (feeds every warped frame into one in-memory
  canvas, then blends); it is given exactly our warped frames, so the comparison isolates
  blending and bookkeeping.

Then a second day (same world, loop route, 5 floor changes, 20 % darker) is built
incrementally onto the map, and the shards/chunks it changed are printed.

    python bench/bench_render.py [--out DIR] [--seed 1] [--area 5x5] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import zarr

from mapstore.grid import MapGrid
from mapstore.layout import read_floor
from mapstore.repository import MapRepository
from pipeline.evaluate import align_se2, ground_truth_at, mosaic_vs_world, seam_ratio, threshold_agreement
from pipeline.framestore import STORE_NAME, FrameStore
from pipeline.mosaic import INTERPOLATIONS, texture_layer, uniqueness_cells
from pipeline.stages.render import frames_to_render, read_stage_poses
from pipeline.simulate.texture import read_float_tiff
from pipeline.config import load_config


def mosaicmap(*args) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "pipeline.cli", *map(str, args)], check=True)
    return time.perf_counter() - t0


def used_frames(work: Path, cfg: dict, grid: MapGrid):
    """The frames store, poses, log of each frame and the frames the render used."""
    store = FrameStore(work / "ingest" / STORE_NAME)
    poses = read_stage_poses(work / "optimize" / "poses.csv")
    log_of = np.concatenate([np.full(lf.count, k) for k, lf in enumerate(store.logs)])
    return store, poses, log_of, frames_to_render(store, poses, log_of, grid, cfg["render"])[1]


def border_mask(grid: MapGrid, store, poses, log_of, used) -> np.ndarray:
    mask = np.zeros(grid.shape, np.uint8)
    for g in np.flatnonzero(used):
        h, w = store.logs[log_of[g]].valid.shape
        a = grid.frame_to_grid_affine(poses[g], (h, w), store.pixel_size)
        corners = np.array([[0, 0, 1], [w - 1, 0, 1], [w - 1, h - 1, 1], [0, h - 1, 1]], float) @ a.T
        cv2.polylines(mask, [np.rint(corners).astype(np.int32)], True, 1, thickness=5)
    return mask > 0


def feather_peer(grid: MapGrid, store, poses, log_of, used, gains, cfg) -> tuple[np.ndarray, float]:
    """OpenCV detail.FeatherBlender on our warped frames (whole canvas in memory)."""
    t0 = time.perf_counter()
    blender = cv2.detail_FeatherBlender(1.0 / cfg["render"]["feather_px"])
    blender.prepare((0, 0, grid.width, grid.height))
    interp = INTERPOLATIONS[cfg["render"]["interpolation"]]
    offsets = np.cumsum([0] + [lf.count for lf in store.logs])
    for g in np.flatnonzero(used):
        k = int(log_of[g])
        lf = store.logs[k]
        img = lf.image(int(g - offsets[k])) / gains[g]
        valid = lf.valid.astype(np.uint8) * 255
        a = grid.frame_to_grid_affine(poses[g], img.shape, store.pixel_size)
        corners = np.array([[0, 0, 1], [img.shape[1], 0, 1], [img.shape[1], img.shape[0], 1], [0, img.shape[0], 1]],
                           float) @ a.T
        x0, y0 = np.floor(corners.min(axis=0)).astype(int) - 2
        x1, y1 = np.ceil(corners.max(axis=0)).astype(int) + 2
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, grid.width), min(y1, grid.height)
        a_roi = a.copy()
        a_roi[:, 2] -= (x0, y0)
        size = (x1 - x0, y1 - y0)
        warped = cv2.warpAffine(img.astype(np.float32), a_roi, size, flags=interp, borderMode=cv2.BORDER_REPLICATE)
        m = cv2.warpAffine(valid, a_roi, size, flags=cv2.INTER_NEAREST, borderValue=0)
        m = cv2.erode(m, np.ones((3, 3), np.uint8))
        rgb = cv2.merge([np.clip(np.rint(warped), 0, 255).astype(np.int16)] * 3)
        blender.feed(rgb, m, (x0, y0))
    out, out_mask = blender.blend(None, None)
    res = np.where(out_mask > 0, np.clip(out[..., 0], 1, 255), 0).astype(np.uint8)
    return res, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("/tmp/mosaicmap-bench-render"))
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--area", default="5x5")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--config", type=Path, default=None, help="A config file for both builds (default: none).")
    args = ap.parse_args()
    cfg_args = ("--config", args.config) if args.config else ()
    out = args.out
    shutil.rmtree(out / "map", ignore_errors=True)
    for d in ("w1", "w2"):
        shutil.rmtree(out / d / "render", ignore_errors=True)
        shutil.rmtree(out / d / "publish", ignore_errors=True)
    shutil.rmtree(out / "w2", ignore_errors=True)
    day1, day2 = out / "day1", out / "day2"
    if not (day1 / "drive.toml").exists():
        mosaicmap("simulate", "floor", day1, "--seed", args.seed, "--area", args.area, "--quiet")
    if not (day2 / "drive.toml").exists():
        mosaicmap("simulate", "floor", day2, "--world", day1, "--route", "loop", "--changes", 5,
                  "--illumination", 0.8, "--seed", args.seed + 1, "--quiet")
    cfg = load_config(args.config)
    t_build = mosaicmap("build", day1, "--map", out / "map", "-w", out / "w1", "--report", out / "r1.json", "--quiet",
                        *cfg_args)
    r1 = json.loads((out / "r1.json").read_text())

    root = zarr.open_group(MapRepository.open(str(out / "map")).readonly().store, mode="r")
    info = read_floor(root)
    mosaic = root["floor/0"][...]
    store, poses, log_of, used = used_frames(out / "w1", cfg, info.grid)
    gt = ground_truth_at(store.logs[0].t, day1 / "ground_truth.csv")
    rot, trans = align_se2(poses[:, :2], gt[:, :2])
    tex = read_float_tiff(day1 / "world" / "texture.tif")
    tex_grid = MapGrid.from_attrs(json.loads((day1 / "world" / "grid.json").read_text()))
    ours = mosaic_vs_world(mosaic, info.grid, tex, tex_grid, rot, trans)
    borders = border_mask(info.grid, store, poses, log_of, used)
    ours["seam_ratio"] = seam_ratio(mosaic, borders)
    gains = np.loadtxt(out / "w1" / "render" / "gains.csv", skiprows=1).reshape(-1)
    peer_img, peer_s = feather_peer(info.grid, store, poses, log_of, used, gains, cfg)
    peer = mosaic_vs_world(peer_img, info.grid, tex, tex_grid, rot, trans)
    peer["seam_ratio"] = seam_ratio(peer_img, borders)
    ren = r1["render"]
    # The texture layer as published (median over a lattice, [render] texture_sample_px) vs
    # the median over every pixel of each cell, on the whole published mosaic.
    r = cfg["render"]
    every = texture_layer(mosaic, info.spec.layer_cell_px, r["texture_window_px"], r["texture_sigma_px"])
    published = root["floor/layers/texture"][...]
    both = ~np.isnan(every) & ~np.isnan(published)
    tex_rel = np.abs(published[both] - every[both]) / np.maximum(every[both], 1e-6)
    tex_nan_same = bool(np.array_equal(np.isnan(every), np.isnan(published)))
    # The uniqueness layer as published ([render] uniqueness_level) vs on level 0.
    uni_level0 = uniqueness_cells(mosaic, info.spec.layer_cell_px, r["uniqueness_template_px"],
                                  r["uniqueness_search_radius_px"], r["uniqueness_exclusion_px"], level=0)
    uni_agree = threshold_agreement(uni_level0, root["floor/layers/uniqueness"][...], 0.2)

    t2 = mosaicmap("build", day2, "--map", out / "map", "-w", out / "w2", "--report", out / "r2.json", "--quiet",
                   *cfg_args)
    r2 = json.loads((out / "r2.json").read_text())
    repo = MapRepository.open(str(out / "map"))
    changed = repo.changed_chunks(r1["publish"]["tag"], r2["publish"]["tag"])
    total0 = int(np.prod([-(-s // info.spec.shard_px) for s in info.grid.shape]))

    mpix = ren["level0_mpix"]
    print(f"render benchmark: simulated {args.area} m floor, seed {args.seed}, "
          f"{r1['optimization']['frames']} frames ({ren['frames_used']} rendered), grid {info.grid.width} x "
          f"{info.grid.height} px, {info.levels} levels, shards {info.spec.shard_px} px")
    print(f"{'':28}{'mosaicmap':>14}{'OpenCV feather':>16}")
    print(f"{'NCC vs world':28}{ours['ncc']:>14.4f}{peer['ncc']:>16.4f}")
    print(f"{'PSNR vs world (dB)':28}{ours['psnr_db']:>14.2f}{peer['psnr_db']:>16.2f}")
    print(f"{'seam ratio (1 = invisible)':28}{ours['seam_ratio']:>14.3f}{peer['seam_ratio']:>16.3f}")
    print(f"{'blend time (s)':28}{ren['seconds']:>14.2f}{peer_s:>16.2f}")
    print(f"{'level-0 MPix/s (wall)':28}{mpix / ren['seconds']:>14.2f}{mpix / peer_s:>16.2f}")
    print(f"{'level-0 MPix per CPU s':28}{mpix / ren['cpu_seconds']:>14.2f}{'':>16}")
    print("(mosaicmap: pyramid + coverage/texture/uniqueness layers included, shards written to disk; CPU: the "
          "build process's threads during the render; peer: level 0 only, in memory)")
    print(f"render: {ren['frames_used']} of {ren['frames_decimated']} decimated frames rendered (selection "
          f"{ren['select_seconds']:.2f} s), {ren['tasks']} tasks of up to {ren['block_side']} x {ren['block_side']} "
          f"shards; level 0 {ren['level0_seconds']:.2f} s + pyramid {ren['pyramid_seconds']:.2f} s wall; in the "
          "level-0 tasks (s, summed over workers): " + ", ".join(f"{k} {v:.2f}" for k, v in ren["phase_seconds"].items()))
    print(f"texture layer (lattice step {r['texture_sample_px']} px) vs every pixel: relative difference median "
          f"{np.median(tex_rel):.4f}, p95 {np.percentile(tex_rel, 95):.4f}, max {tex_rel.max():.3f} over {both.sum()} "
          f"cells; same no-data cells: {tex_nan_same}")
    a = uni_agree
    print(f"uniqueness layer on level {r['uniqueness_level']} vs level 0: {100 * a.fraction:.3f} % of {a.cells} cells "
          f"on the same side of 0.2 (below 0.2: {a.below_reference} on level 0, {a.below_other} on level "
          f"{r['uniqueness_level']}; {a.missing} cells without a value there, {a.extra} with one only there)")
    print(f"build day 1: {t_build:.1f} s total, publish {r1['publish']['seconds']:.2f} s "
          f"({r1['publish']['shards_written']} shards written)")
    print(f"day 2 incremental: {r2['links']['map_accepted']}/{r2['links']['map_candidates']} frames anchored to "
          f"the map, {len(changed.get('floor/0', ()))} of {total0} level-0 shards changed, render "
          f"{r2['render']['seconds']:.2f} s, build {t2:.1f} s; day-2 poses vs ground truth RMS "
          f"{r2['ground_truth']['pose_rms_px']:.3f} px")
    if args.json:
        args.json.write_text(json.dumps({"ours": ours, "peer": peer, "peer_seconds": peer_s, "render": ren,
                                         "uniqueness_agreement": uni_agree.__dict__,
                                         "day2": r2["render"], "changed_level0": len(changed.get("floor/0", ()))},
                                        indent=2))


if __name__ == "__main__":
    main()
