"""Benchmark of the route panorama (ORP) localizer (Yagi et al. (2005)).

A memorized run (`mosaicmap simulate omni`, default world and 20.3 m loop, frames every 2 cm)
gives the ORP (its ground-truth poses as the route: the build's optimized poses come later);
test runs over the same world (`--world`) are localized against it, frame by frame, in
tracking mode as in Yagi et al. (2005) (section 4.1): the first prior is the truth moved by
(+5 cm, -5 cm, +2 deg), every next prior the previous estimate composed with the odometry
increment; each run is also localized frame by frame independently, every prior the truth
moved by (+3 cm, -3 cm, +1.5 deg) (the `independent` rows). Runs: on the path, at 30 deg
across it within +-30 cm (`--angle 30`), at night
(`--night`), with the camera 1 cm above its declared height (`--height-offset 0.01`), and
with objects moved over 25 % of the horizon azimuths (`--move-objects 0.25`) with masking
and without. Printed per run: mean / RMS / max position error (m) and mean / RMS / max heading
error (deg) against the ground truth, ms per frame on one core (`cv2.setNumThreads(1)`, the
horizon unwarp included), the ORP's bytes per km at 1 sample/degree and 2, 5, 10 cm spacing,
and the localizer's load time (the motion-compensated interpolation's row flow, estimated
from the stored rows; `--no-flow`: rows blended linearly, as before).
Wall clock on a possibly busy machine: figures, not assertions.

    python bench/bench_orp.py [--work DIR] [--spd 1] [--spacing 0.02] [--no-flow] [--step 1] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mapstore.grid import interpolate_trajectory, se2_between, se2_compose, wrap_angle  # noqa: E402
from pipeline.drivelog import read_drive_log, read_pose_csv  # noqa: E402
from tracker.orp import HorizonSampler, ORPLocalizer, ORPParams, build_orp  # noqa: E402

RUNS = {  # name: simulate options over the memorized world (seed differs: noise, odometry, exposure)
    "path": ["--seed", "1"],
    "angle30": ["--seed", "2", "--angle", "30"],
    "night": ["--seed", "3", "--night"],
    "height": ["--seed", "4", "--height-offset", "0.01"],
    "moved": ["--seed", "5", "--move-objects", "0.25"],
}
TARGET_CM = {"path": 1.0, "angle30": 2.0, "night": 5.0, "height": 2.0, "moved (masking)": 2.0}


def simulate(work: Path) -> None:
    """Simulate the memorized run and the test runs into ``work`` (skipping existing ones)."""
    from click.testing import CliRunner

    from pipeline.cli import cli

    def run(out: Path, *args: str) -> None:
        if (out / "drive.toml").is_file():
            return
        r = CliRunner().invoke(cli, ["simulate", "omni", str(out), "--quiet", *args])
        if r.exit_code != 0:
            raise SystemExit(r.output)

    run(work / "mem")
    for name, opts in RUNS.items():
        run(work / name, "--world", str(work / "mem"), *opts)


def load_lines(log_dir: Path, params: ORPParams) -> tuple[np.ndarray, np.ndarray, np.ndarray, list, HorizonSampler]:
    """Horizon lines (N, A), ground truth (N, 3), odometry at frame times (N, 3), images, sampler."""
    log = read_drive_log(log_dir)
    hs = HorizonSampler(log.camera.omni, params.samples_per_degree, params.horizon_band_deg, params.oversample)
    images = [cv2.imread(str(log.image_path(i)), cv2.IMREAD_GRAYSCALE) for i in range(len(log.frame_images))]
    lines = hs.lines(images)
    gt = read_pose_csv(log_dir / "ground_truth.csv")
    truth = interpolate_trajectory(gt, log.frame_t)
    odo = interpolate_trajectory(log.odometry, log.frame_t)
    return lines, truth, odo, images, hs


def track(loc: ORPLocalizer, hs: HorizonSampler, images: list, truth: np.ndarray, odo: np.ndarray, step: int,
          masking: bool, independent: bool = False) -> dict:
    """Localize every ``step``-th frame in tracking mode (``independent``: each from the truth
    moved by (+3 cm, -3 cm, +1.5 deg) instead); errors against ``truth`` and timing."""
    idx = np.arange(0, len(images), step)
    est = np.empty((len(idx), 3))
    offset = np.array([0.03, -0.03, np.radians(1.5)])
    prior = se2_compose(truth[idx[0]], offset if independent else np.array([0.05, -0.05, np.radians(2.0)]))
    secs = []
    ok = 0
    for k, i in enumerate(idx):
        t = time.perf_counter()
        line = hs.line(images[i])
        fix = loc.localize(line, prior, masking=masking)
        secs.append(time.perf_counter() - t)
        est[k] = fix.pose
        ok += fix.ok
        if k + 1 < len(idx):
            prior = (se2_compose(truth[idx[k + 1]], offset) if independent
                     else se2_compose(fix.pose, se2_between(odo[i], odo[idx[k + 1]])))
    d = np.hypot(*(est[:, :2] - truth[idx, :2]).T)
    h = np.degrees(np.abs(wrap_angle(est[:, 2] - truth[idx, 2])))
    return {
        "frames": int(len(idx)),
        "ok": int(ok),
        "pos_mean_m": float(d.mean()), "pos_rms_m": float(np.sqrt((d**2).mean())), "pos_max_m": float(d.max()),
        "pos_p95_m": float(np.percentile(d, 95)),
        "head_mean_deg": float(h.mean()), "head_rms_deg": float(np.sqrt((h**2).mean())), "head_max_deg": float(h.max()),
        "ms_per_frame": 1000.0 * float(np.mean(secs)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/mosaicmap-bench-orp"))
    ap.add_argument("--spd", type=float, default=None, help="samples per degree (default: [tracker.orp])")
    ap.add_argument("--spacing", type=float, default=None, help="ORP spacing, metres (default: [tracker.orp])")
    ap.add_argument("--no-flow", action="store_true", help="linear row interpolation (interp_flow = false)")
    ap.add_argument("--step", type=int, default=1, help="localize every step-th frame")
    ap.add_argument("--runs", default=",".join(RUNS), help="comma-separated subset of: " + ",".join(RUNS))
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    cv2.setNumThreads(1)
    from pipeline.config import load_config

    cfg = dict(load_config(None)["tracker"]["orp"])
    if args.spd is not None:
        cfg["samples_per_degree"] = args.spd
    if args.spacing is not None:
        cfg["spacing_m"] = args.spacing
    if args.no_flow:
        cfg["interp_flow"] = False
    params = ORPParams.from_dict(cfg)
    args.work.mkdir(parents=True, exist_ok=True)
    t = time.perf_counter()
    simulate(args.work)
    print(f"simulated logs in {args.work} ({time.perf_counter() - t:.0f} s)")
    lines, truth, _, _, _ = load_lines(args.work / "mem", params)
    orp = build_orp(lines, truth, params.spacing_m, params.samples_per_degree)
    p1 = ORPParams.from_dict({**cfg, "samples_per_degree": 1.0, "spacing_m": 0.10})
    l1, tr1, _, _, _ = load_lines(args.work / "mem", p1) if params.samples_per_degree != 1.0 else (lines, truth, 0, 0, 0)
    orp10 = build_orp(l1, tr1, 0.10, 1.0)
    per_km = {f"{sp * 100:g}cm": build_orp(l1, tr1, sp, 1.0).bytes_per_km() for sp in (0.02, 0.05, 0.10)}
    out = {"params": {k: (list(v) if isinstance(v, tuple) else v) for k, v in cfg.items()},
           "orp": {"rows": int(len(orp.lines)), "length_m": orp.length_m, "bytes": orp.nbytes,
                   "bytes_per_km": orp.bytes_per_km(), "bytes_per_km_1spd_10cm": orp10.bytes_per_km(),
                   "bytes_per_km_1spd": per_km},
           "runs": {}}
    print(f"ORP: {len(orp.lines)} rows x {orp.lines.shape[1]} azimuths over {orp.length_m:.2f} m "
          f"({params.spacing_m * 100:g} cm spacing, {params.samples_per_degree:g} sample/deg): "
          f"{orp.bytes_per_km() / 1e6:.2f} MB/km; at 1 sample/deg and 10 cm: {orp10.bytes_per_km() / 1e6:.2f} MB/km "
          f"(target <= 4, seed 3.6)")
    print("at 1 sample/deg: " + ", ".join(f"{k} {v / 1e6:.2f} MB/km" for k, v in per_km.items()))
    t = time.perf_counter()
    loc = ORPLocalizer(orp, params)
    out["orp"]["load_ms"] = 1000.0 * (time.perf_counter() - t)
    print(f"localizer load ({'row flow' if loc.flow is not None else 'linear rows'}): {out['orp']['load_ms']:.0f} ms "
          f"({out['orp']['load_ms'] / max(orp.length_m, 1e-9):.1f} ms per metre of route)")
    print(f"{'run':18s} {'frames':>6s} {'ok':>5s} {'mean m':>8s} {'rms m':>8s} {'max m':>8s} "
          f"{'head mean':>9s} {'rms deg':>8s} {'max deg':>8s} {'ms/frame':>8s} target")
    for name in args.runs.split(","):
        _, truth_r, odo_r, images, hs = load_lines(args.work / name, params)
        variants = [(name, params.masking)] if name != "moved" else [("moved (no mask)", False), ("moved (masking)", True)]
        for label, masking in variants:
            r = track(loc, hs, images, truth_r, odo_r, args.step, masking)
            ind = track(loc, hs, images, truth_r, odo_r, args.step, masking, independent=True)
            r["independent"] = ind
            out["runs"][label] = r
            tgt = TARGET_CM.get(label)
            verdict = "" if tgt is None else f"mean <= {tgt:g} cm: {'met' if r['pos_mean_m'] * 100 <= tgt else 'NOT met'}"
            print(f"{label:18s} {r['frames']:6d} {r['ok']:5d} {r['pos_mean_m']:8.4f} {r['pos_rms_m']:8.4f} "
                  f"{r['pos_max_m']:8.4f} {r['head_mean_deg']:9.3f} {r['head_rms_deg']:8.3f} {r['head_max_deg']:8.3f} "
                  f"{r['ms_per_frame']:8.2f} {verdict}")
            print(f"{'  independent':18s} {ind['frames']:6d} {ind['ok']:5d} {ind['pos_mean_m']:8.4f} "
                  f"{ind['pos_rms_m']:8.4f} {ind['pos_max_m']:8.4f} {ind['head_mean_deg']:9.3f} "
                  f"{ind['head_rms_deg']:8.3f} {ind['head_max_deg']:8.3f} {ind['ms_per_frame']:8.2f}")
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
