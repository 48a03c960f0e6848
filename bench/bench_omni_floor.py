"""Floor mosaic from an omni log's bird's-eye views: pose error figures and mosaic vs truth.

Simulates an omni drive (``mosaicmap simulate omni``: 640 x 480 hyperboloidal-mirror frames,
viewpoint 1 m up, frames every 2 cm, 1 % odometry drift; default the 20.3 m loop of the
11 x 6 m room), builds it (``mosaicmap build LOG --map REPO --report r.json``) at the omni
pixel size (``[map] pixel_size_m``, configs/omni.toml explains the choice) and prints, as the
registration issue's report does:

- pose error vs ground truth after the rigid SE(2) alignment: RMS and max in px and mm
  (report ``ground_truth.pose_rms_px``, ``pose_max_px``), and the odometry's;
- link error median / p95 (px), accepted / candidate links and the rejection reasons;
- registration pairs/s (report ``registration.pairs_per_s``, the stage on all cores);
- the published level-0 mosaic against the simulator's floor texture over the covered area
  (:func:`pipeline.evaluate.mosaic_vs_world`, after the same alignment): NCC and PSNR. The
  floor texture is rendered on its own grid (1 cm texels) and sampled at each map pixel; the
  mosaic sees it through the camera (14-23 mm ground pixels), so the reference is smoothed
  to the map pixel first (a Gaussian of half a map pixel, as the bird's-eye check does).

    python bench/bench_omni_floor.py [--out DIR] [--route loop] [--seed 1] [--pixel 0.01]
        [--clearance 1.0] [--objects N] [--reuse] [--json FILE]

``--clearance`` (metres) keeps the simulated objects that far from the route (the default
world keeps 0.7 m, inside the 1.0 m floor annulus: object faces then land in some frames);
0 = the simulator's default.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import zarr

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from runner import mosaicmap, reusable, run_cli  # noqa: E402

from mapstore.layout import read_floor  # noqa: E402
from mapstore.repository import MapRepository  # noqa: E402
from pipeline.evaluate import align_se2, ground_truth_at, mosaic_vs_world  # noqa: E402
from pipeline.framestore import STORE_NAME, FrameStore  # noqa: E402
from pipeline.stages.render import read_stage_poses  # noqa: E402
from pipeline.simulate.omni import load_world  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=None, help="Keep logs, work dirs and the map here.")
    ap.add_argument("--route", default="loop", help="Simulated route (loop, lawnmower, figure8, random).")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--pixel", type=float, default=0.01, help="[map] pixel_size_m of the build (metres).")
    ap.add_argument("--clearance", type=float, default=1.0,
                    help="Objects' clearance from the route (metres); 0 = the simulator's default.")
    ap.add_argument("--objects", type=int, default=0, help="Objects in the room; 0 = the simulator's default (8).")
    ap.add_argument("--drift", type=float, default=0.01, help="Odometry drift (error gradient).")
    ap.add_argument("--reuse", action="store_true", help="Reuse a kept simulated log with the same parameters.")
    ap.add_argument("--json", type=Path, default=None, help="Also write the figures as JSON here.")
    args = ap.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="bench_omni_floor_"))
    out.mkdir(parents=True, exist_ok=True)

    sim_cfg = out / "sim.toml"
    world = ([f"object_route_clearance_m = {args.clearance}"] if args.clearance > 0 else []) + \
        ([f"objects = {args.objects}"] if args.objects > 0 else [])
    sim_cfg.write_text("[simulate.omni.world]\n" + "\n".join(world) + "\n" if world else "")
    log = out / "log"
    params = {"route": args.route, "seed": args.seed, "clearance": args.clearance, "objects": args.objects,
              "drift": args.drift}
    marker = out / "log.json"
    t_sim = 0.0
    if not reusable(marker, params, args.reuse):
        import shutil

        shutil.rmtree(log, ignore_errors=True)
        t0 = time.perf_counter()
        run_cli("simulate", "omni", log, "--route", args.route, "--seed", args.seed, "--odometry-drift",
                args.drift, "--config", sim_cfg, "--quiet")
        t_sim = time.perf_counter() - t0
        marker.write_text(json.dumps({"params": params}))

    build_cfg = out / "build.toml"
    build_cfg.write_text(f"[map]\npixel_size_m = {args.pixel}\n")
    import shutil

    for d in ("w", "map"):
        shutil.rmtree(out / d, ignore_errors=True)
    rep = mosaicmap(out / "r.json", "build", log, "--map", out / "map", "-w", out / "w", "--config", build_cfg)

    px_mm = args.pixel * 1000.0
    G, R, L = rep.get("ground_truth", {}), rep.get("registration", {}), rep.get("links", {})
    om = rep["ingest"]["logs"][0].get("omni", {})
    # the mosaic against the floor texture
    root = zarr.open_group(MapRepository.open(str(out / "map")).readonly().store, mode="r")
    info = read_floor(root)
    mosaic = root["floor/0"][...]
    store = FrameStore(out / "w" / "ingest" / STORE_NAME)
    poses = read_stage_poses(out / "w" / "optimize" / "poses.csv")
    gt = ground_truth_at(store.logs[0].t, log / "ground_truth.csv")
    rot, trans = align_se2(poses[:, :2], gt[:, :2])
    world, _ = load_world(log)
    tex_grid = world.floor_grid()
    tex = cv2.GaussianBlur(world.floor_texture(), (0, 0), 0.5 * args.pixel / tex_grid.pixel_size)
    mvw = mosaic_vs_world(mosaic.astype(np.float32), info.grid, tex, tex_grid, rot, trans)

    figs = {
        "route": args.route, "frames": rep["ingest"]["frames_total"], "accepted_frames": rep["ingest"]["frames_accepted"],
        "pixel_size_m": args.pixel, "annulus_m": [om.get("inner_radius_m"), om.get("outer_radius_m")],
        "frame_shape": om.get("frame_shape"), "ground_pixel_m": om.get("ground_pixel_m"),
        "pose_rms_px": G.get("pose_rms_px"), "pose_max_px": G.get("pose_max_px"),
        "pose_rms_mm": G.get("pose_rms_px", float("nan")) * px_mm, "pose_max_mm": G.get("pose_max_px", float("nan")) * px_mm,
        "odometry_rms_mm": G.get("odometry_rms_px", float("nan")) * px_mm,
        "link_error_median_px": G.get("link_error_median_px"), "link_error_p95_px": G.get("link_error_p95_px"),
        "links_accepted": L.get("accepted"), "links_candidates": L.get("candidates"),
        "rejection_reasons": R.get("rejection_reasons"), "pairs_per_s": R.get("pairs_per_s"),
        "mosaic_ncc": mvw["ncc"], "mosaic_psnr_db": mvw["psnr_db"], "mosaic_pixels": mvw["pixels"],
        "simulate_s": t_sim, "build_s": rep["wall_seconds"],
        "stage_s": {k: v["seconds"] for k, v in rep["stages"].items()},
    }
    print(f"omni floor mosaic: {args.route} route, seed {args.seed}, {figs['frames']} frames "
          f"({figs['accepted_frames']} accepted), {args.drift:.0%} odometry drift, map pixel {px_mm:g} mm")
    print(f"  bird's-eye frames: {om.get('frame_shape')} px, floor annulus {om.get('inner_radius_m'):.3f} .. "
          f"{om.get('outer_radius_m'):.3f} m, camera ground pixel {1000 * om.get('ground_pixel_m', 0):.1f} mm")
    print(f"  pose error vs ground truth: RMS {figs['pose_rms_px']:.4f} px = {figs['pose_rms_mm']:.3f} mm, "
          f"max {figs['pose_max_px']:.4f} px = {figs['pose_max_mm']:.3f} mm (odometry RMS {figs['odometry_rms_mm']:.1f} mm)")
    print(f"  link error: median {figs['link_error_median_px']:.4f} px, p95 {figs['link_error_p95_px']:.4f} px; "
          f"links accepted {figs['links_accepted']} of {figs['links_candidates']}, rejected: {figs['rejection_reasons']}")
    print(f"  registration: {figs['pairs_per_s']:.1f} pairs/s; stages {json.dumps({k: round(v, 1) for k, v in figs['stage_s'].items()})}")
    print(f"  mosaic vs floor texture: NCC {figs['mosaic_ncc']:.4f}, PSNR {figs['mosaic_psnr_db']:.1f} dB over "
          f"{figs['mosaic_pixels']} px")
    print(f"  simulate {t_sim:.1f} s, build {figs['build_s']:.1f} s -> {out}")
    if args.json:
        args.json.write_text(json.dumps(figs, indent=2))


if __name__ == "__main__":
    main()
