"""Benchmark of the omni simulator's rendering and of omni unwarping.

The default ``[simulate.omni]`` world (an 11 x 6 m room, 8 boxes, the 20.3 m loop) and camera
(640 x 480, hyperboloidal mirror) are generated once; then ``--frames`` poses spread along
the route are rendered one after the other on one thread (``cv2.setNumThreads(1)``), by day
and at night, and each rendered frame is unwarped to

- a panorama strip (``--spd`` samples per degree, elevations ``--elevation`` degrees), and
- a bird's-eye view of the floor (``--birdseye-px`` metres per pixel over ``--birdseye-m``),

with the remap tables precomputed (their build time is printed apart). It prints render
seconds per frame (mean, max) and unwarp milliseconds per frame (mean) for both views, with
the fixed-point (default) and the float tables. Wall clock on a possibly busy machine:
figures, not assertions.

    python bench/bench_omni_sim.py [--frames 40] [--spd 1] [--elevation -10,10]
                                   [--birdseye-px 0.01] [--birdseye-m 4] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from pipeline.config import load_config  # noqa: E402
from pipeline.simulate.omni import OmniRenderer, camera_from_config, generate_world  # noqa: E402
from pipeline.simulate.route import make_route  # noqa: E402
from tracker.omnicam import birdseye_unwarp, panorama_unwarp  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--spd", type=float, default=1.0, help="panorama samples per degree")
    ap.add_argument("--elevation", default="-10,10", help="panorama elevation range, degrees")
    ap.add_argument("--birdseye-px", type=float, default=0.01, help="bird's-eye pixel size, metres")
    ap.add_argument("--birdseye-m", type=float, default=4.0, help="bird's-eye extent (square), metres")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    cfg = load_config()
    om = cfg["simulate"]["omni"]
    cam = camera_from_config(om["camera"])
    w, h = om["camera"]["frame_size"]
    room = tuple(om["room_m"])
    t = time.perf_counter()
    route = make_route(om["route"], room, np.random.default_rng(1), om["routes"], om["routes"]["lane_spacing_m"])
    xy = np.stack([route.x, route.y], 1)[::25]
    world = generate_world(np.random.default_rng(2), np.random.default_rng(3), cfg, room, xy,
                           om["world"]["object_route_clearance_m"], 0)
    world_s = time.perf_counter() - t
    poses = route.at(np.linspace(0, route.length, args.frames, endpoint=False))
    figures: dict = {"frame_size": [w, h], "frames": args.frames, "world_s": world_s,
                     "load_average": list(os.getloadavg())}
    t = time.perf_counter()
    lo, hi = (float(v) for v in args.elevation.split(","))
    pan = panorama_unwarp(cam, samples_per_degree=args.spd, elevation_range_deg=(lo, hi))
    be = birdseye_unwarp(cam, args.birdseye_px, (args.birdseye_m, args.birdseye_m))
    figures["unwarp_tables_s"] = time.perf_counter() - t
    figures["panorama_shape"] = list(pan.unwarp.shape)
    figures["birdseye_shape"] = list(be.shape)
    for mode in ("day", "night"):
        t = time.perf_counter()
        r = OmniRenderer(cam, (h, w), world, cam.height_m, mode == "night", om, tuple(om["camera"]["vignetting"]))
        setup_s = time.perf_counter() - t
        times, frames = [], []
        for i, p in enumerate(poses):
            t = time.perf_counter()
            frames.append(r.render(p, 1.0, om["sensor"]["noise_sigma"], np.random.default_rng(i)))
            times.append(time.perf_counter() - t)
        figures[f"render_{mode}"] = {"setup_s": setup_s, "s_per_frame_mean": float(np.mean(times)),
                                     "s_per_frame_max": float(np.max(times))}
    for name, table in (("panorama", pan.unwarp), ("birdseye", be)):
        for exact in (False, True):
            t = time.perf_counter()
            for f in frames:
                table.apply(f, exact=exact)
            ms = 1e3 * (time.perf_counter() - t) / len(frames)
            figures[f"unwarp_{name}_{'float' if exact else 'fixed'}_ms"] = ms
    print(f"omni simulator, {w} x {h} frames, {args.frames} poses along the {route.length:.1f} m route, one thread "
          f"(load average {figures['load_average'][0]:.2f})")
    print(f"  world generation            {world_s:8.3f} s (atlas {world.atlas.shape[1]} x {world.atlas.shape[0]})")
    for mode in ("day", "night"):
        f = figures[f"render_{mode}"]
        print(f"  render {mode:5s}                {f['s_per_frame_mean']:8.4f} s/frame mean, "
              f"{f['s_per_frame_max']:.4f} max (renderer setup {f['setup_s']:.2f} s)")
    print(f"  unwarp tables               {figures['unwarp_tables_s']:8.3f} s (panorama {pan.unwarp.shape[1]} x "
          f"{pan.unwarp.shape[0]}, bird's-eye {be.shape[1]} x {be.shape[0]})")
    for name in ("panorama", "birdseye"):
        print(f"  unwarp {name:9s}            {figures[f'unwarp_{name}_fixed_ms']:8.3f} ms/frame "
              f"(float tables {figures[f'unwarp_{name}_float_ms']:.3f} ms)")
    if args.json:
        args.json.write_text(json.dumps(figures, indent=2))


if __name__ == "__main__":
    main()
