"""Benchmark of registration and global optimization on a simulated floor.

On the simulated 5 x 5 m lawnmower (2.5 mm pixels, 320 x 240 frames, 1 % odometry drift,
noise sigma 5: the simulator's defaults, ``--seed 1``) the build runs to ``--until
optimize`` and this prints:

- links: candidates / accepted / rejected (registration and outlier rejections);
- registration pairs/s (report ``registration.pairs_per_s``, the stage on all cores);
- link error median / p95 vs ground truth, pose RMS / max (report ``ground_truth.*``);
- optimization seconds;
- chi-square calibration of the link covariances: the mean Mahalanobis^2 of the links'
  ground-truth errors (3 dof: ~3 when the covariance is right; it calibrates
  ``[register] covariance_inflation``). Printed in two conventions: the error as the plain
  difference of ``rel`` components in frame a's axes (what ``register_pair`` derives its
  covariance for), and in frame b's local coordinates (``Logmap(rel_gt^-1 rel)``, what the
  optimizer's BetweenFactorPose2 whitens with the same matrix). They coincide for links
  with dtheta ~ 0, not for lawnmower cross-lane links with dtheta ~ pi when the
  translation-heading covariance terms are large;
- the worst links vs ground truth (frames, kind, NCC, uniqueness);
- the corruption experiment: 5 % of the accepted links of ``W/register/links.csv``
  offset by 5 to 50 px in random directions; ``optimize_poses`` on the odometry priors with
  the clean and the corrupted sets: corrupted links rejected (should be all), good links
  rejected, pose change clean -> corrupted (px RMS, raw and after a rigid alignment);
- a peer: OpenCV ``findTransformECC`` (MOTION_EUCLIDEAN) on 200 sequential pairs from the
  odometry prior, beside ``register_pair`` on the same pairs, single-threaded: link error
  median / p95 and pairs/s.

``--scheduler threads|processes|sync``: overrides ``[register] scheduler`` (the dask
scheduler of the register stage; default: the configuration's).

``--area 20``: the large case, a 20 x 20 m lawnmower (10,005 frames, 1000 m of path;
simulating it takes ~5 min, or pass ``--log`` of an existing one) where revisits predicted
along the whole chain of sequential links fail; it prints pose error RMS / max, pairs/s,
feature-path pairs, candidates and rejections and the stage seconds. ``--single-round``
sets ``[register] progressive_revisits = false`` (the one-round revisits, for comparison).

Timings are wall clock on a possibly busy machine: figures, not assertions.

    python bench/bench_register.py [--out DIR] [--json FILE] [--seed 1] [--scheduler threads]
                                   [--corrupt-seeds 3] [--peer-pairs 200] [--log EXISTING_LOG]
                                   [--area 20] [--single-round]
"""

from __future__ import annotations

import argparse
import copy
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

PX = 0.0025


def _pct(x: np.ndarray, q: float) -> float:
    return float(np.percentile(x, q)) if len(x) else float("nan")


def gt_errors(links, gt: np.ndarray) -> dict:
    """Per link: pixel error (pipeline.evaluate.link_errors) and Mahalanobis^2 in two conventions."""
    from mapstore.grid import se2_between, se2_log, wrap_angle
    from pipeline.evaluate import link_errors

    a = np.array([lk.a for lk in links])
    b = np.array([lk.b for lk in links])
    rel = np.array([lk.rel for lk in links], float)
    cov = np.array([lk.cov for lk in links], float)
    rel_gt = se2_between(gt[a], gt[b])
    e_a = np.column_stack([rel[:, :2] - rel_gt[:, :2], wrap_angle(rel[:, 2] - rel_gt[:, 2])])
    e_b = se2_log(se2_between(rel_gt, rel))

    from pipeline.optimize import local_covariance

    def maha(e, c):
        return np.einsum("li,li->l", e, np.linalg.solve(c, e[..., None])[..., 0])

    # m_a: the error as numbers against Link.cov; m_b: what the optimizer whitens (Pose2
    # local coordinates against the covariance carried to them).
    return {"px": link_errors(links, gt, PX), "m_a": maha(e_a, cov), "m_b": maha(e_b, local_covariance(rel, cov)),
            "dtheta": np.abs(wrap_angle(rel_gt[:, 2]))}


def run_stage_build(log: Path, work: Path, scheduler: str | None, progressive: bool = True) -> dict:
    """``run_build(..., until="optimize")``; ``scheduler`` overrides ``[register] scheduler``,
    ``progressive`` sets ``[register] progressive_revisits``."""
    from pipeline.stages.build import run_build
    from pipeline.config import load_config

    cfg = load_config()
    if scheduler is not None:
        cfg["register"]["scheduler"] = scheduler
    cfg["register"]["progressive_revisits"] = progressive
    return run_build([log], work, cfg, until="optimize", quiet=True)


def corruption(priors, links_reg, gt, cfg_opt, seed: int, fraction: float = 0.05) -> dict:
    """Optimize with the clean and with a corrupted copy of the accepted links."""
    from pipeline.evaluate import absolute_trajectory_error, align_se2
    from pipeline.optimize import optimize_poses

    acc = [lk for lk in links_reg if lk.status == "accepted"]
    clean = copy.deepcopy(acc)
    bad = copy.deepcopy(acc)
    rng = np.random.default_rng(seed)
    n_bad = max(1, int(round(fraction * len(acc))))
    idx = rng.choice(len(acc), n_bad, replace=False)
    corrupted = np.zeros(len(acc), bool)
    corrupted[idx] = True
    for i in idx:
        mag = rng.uniform(5.0, 50.0) * PX
        ang = rng.uniform(0, 2 * np.pi)
        bad[i].rel = bad[i].rel + np.array([mag * np.cos(ang), mag * np.sin(ang), 0.0])
    r0 = optimize_poses(priors, clean, cfg_opt, PX)
    r1 = optimize_poses(priors, bad, cfg_opt, PX)
    rej0 = np.array([lk.status == "rejected" for lk in r0.links])
    rej1 = np.array([lk.status == "rejected" for lk in r1.links])
    d = np.linalg.norm(r1.poses[:, :2] - r0.poses[:, :2], axis=1) / PX
    rot, tr = align_se2(r1.poses[:, :2], r0.poses[:, :2])
    da = np.linalg.norm(r1.poses[:, :2] @ rot.T + tr - r0.poses[:, :2], axis=1) / PX
    missed = [(acc[i].a, acc[i].b) for i in np.flatnonzero(corrupted & ~rej1)]
    return {
        "seed": seed,
        "links": len(acc),
        "corrupted": int(corrupted.sum()),
        "corrupted_rejected": int((corrupted & rej1).sum()),
        "corrupted_missed": missed,
        "good_rejected": int((~corrupted & rej1).sum()),
        "good_rejected_clean_run": int(rej0.sum()),
        "pose_change_rms_px": float(np.sqrt(np.mean(d**2))),
        "pose_change_max_px": float(d.max()),
        "pose_change_aligned_rms_px": float(np.sqrt(np.mean(da**2))),
        "ate_clean_rms_px": absolute_trajectory_error(r0.poses, gt, PX)["rms_px"],
        "ate_corrupt_rms_px": absolute_trajectory_error(r1.poses, gt, PX)["rms_px"],
        "ate_corrupt_max_px": absolute_trajectory_error(r1.poses, gt, PX)["max_px"],
        "seconds_clean": r0.seconds,
        "seconds_corrupt": r1.seconds,
    }


def peer(store_path: Path, links_reg, gt, cfg: dict, n_pairs: int) -> dict:
    """ECC (OpenCV, MOTION_EUCLIDEAN) vs register_pair on the same sequential pairs from the odometry prior."""
    import cv2

    from mapstore.grid import frame_affine_to_rel, frame_to_frame_affine, se2_between
    from pipeline.evaluate import link_errors
    from pipeline.framestore import FrameStore
    from pipeline.links import Link
    from pipeline.registration import RegistrationParams, register_pair

    lf = FrameStore(store_path).logs[0]
    prior = lf.prior
    valid = lf.valid
    seq = sorted({(lk.a, lk.b) for lk in links_reg if lk.b == lk.a + 1})
    step = max(1, len(seq) // n_pairs)
    pairs = seq[::step][:n_pairs]
    need = sorted({f for p in pairs for f in p})
    imgs = {f: lf.image(f) for f in need}
    radius = {(lk.a, lk.b): float(lk.extra.get("radius_px") or 4.0) for lk in links_reg}
    params = RegistrationParams.from_config(cfg["register"])
    mask = valid.astype(np.uint8)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-6)

    ecc_links, ecc_fail = [], 0
    t0 = time.perf_counter()
    for a, b in pairs:
        prior_rel = se2_between(prior[a], prior[b])
        b_to_a = frame_to_frame_affine(prior_rel, imgs[b].shape, imgs[a].shape, PX)
        warp = cv2.invertAffineTransform(b_to_a).astype(np.float32)  # a pixel -> b pixel
        try:
            _, warp = cv2.findTransformECC(imgs[a], imgs[b], warp, cv2.MOTION_EUCLIDEAN, crit, mask, 5)
        except cv2.error:
            ecc_fail += 1
            continue
        rel = frame_affine_to_rel(cv2.invertAffineTransform(warp.astype(np.float64)), imgs[b].shape, imgs[a].shape, PX)
        ecc_links.append(Link(a, b, rel, np.eye(3), 0.0, 0.0, 0.0, 0, "ecc"))
    t_ecc = time.perf_counter() - t0

    ours, our_fail = [], 0
    t0 = time.perf_counter()
    for a, b in pairs:
        prior_rel = se2_between(prior[a], prior[b])
        r = register_pair(imgs[a], valid, imgs[b], valid, prior_rel, PX, radius.get((a, b), 4.0), 0.0, params)
        if not r.ok:
            our_fail += 1
            continue
        ours.append(Link(a, b, r.rel, r.cov, r.ncc, r.uniqueness, r.overlap, r.pixels, r.method))
    t_ours = time.perf_counter() - t0
    e_ecc = link_errors(ecc_links, gt, PX)
    e_ours = link_errors(ours, gt, PX)
    return {
        "pairs": len(pairs),
        "ecc": {"ok": len(ecc_links), "failed": ecc_fail, "median_px": _pct(e_ecc, 50), "p95_px": _pct(e_ecc, 95),
                "max_px": float(e_ecc.max()) if len(e_ecc) else float("nan"), "pairs_per_s": len(pairs) / t_ecc},
        "ours": {"ok": len(ours), "failed": our_fail, "median_px": _pct(e_ours, 50), "p95_px": _pct(e_ours, 95),
                 "max_px": float(e_ours.max()) if len(e_ours) else float("nan"), "pairs_per_s": len(pairs) / t_ours},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None, help="Directory for the log and work dir (default: a temp dir, removed).")
    ap.add_argument("--json", type=Path, default=None, help="Write the figures to this JSON file.")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--log", type=Path, default=None, help="Use this simulated log instead of simulating one.")
    ap.add_argument("--scheduler", choices=("threads", "processes", "sync"), default=None,
                    help="Override [register] scheduler (default: the configuration's).")
    ap.add_argument("--corrupt-seeds", type=int, default=3, help="Corruption experiments (different random corruptions).")
    ap.add_argument("--peer-pairs", type=int, default=200, help="Sequential pairs for the ECC comparison (0 = skip).")
    ap.add_argument("--worst", type=int, default=10, help="Worst links vs ground truth to list.")
    ap.add_argument("--area", type=float, default=None,
                    help="Side of the simulated square lawnmower (metres; default: the simulator's, 5); e.g. 20.")
    ap.add_argument("--single-round", action="store_true",
                    help="[register] progressive_revisits = false: revisits in one round along the whole chain.")
    args = ap.parse_args()

    from pipeline.config import load_config
    from pipeline.evaluate import ground_truth_at
    from pipeline.framestore import FrameStore
    from pipeline.links import read_links

    tmp = None
    if args.out is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench_register_")
        out = Path(tmp.name)
    else:
        out = args.out
        out.mkdir(parents=True, exist_ok=True)
    if args.scheduler is None:
        args.scheduler = load_config()["register"]["scheduler"]
    figures: dict = {"seed": args.seed, "scheduler": args.scheduler, "area_m": args.area or 5.0,
                     "progressive_revisits": not args.single_round}
    try:
        log = args.log
        if log is None:
            from pipeline.simulate.floor import simulate_floor

            log = out / "log"
            shutil.rmtree(log, ignore_errors=True)
            t0 = time.perf_counter()
            opts = {"seed": args.seed}
            if args.area is not None:
                opts["area"] = f"{args.area:g}x{args.area:g}"
            s = simulate_floor(log, load_config(), opts, quiet=True)
            side = "5x5" if args.area is None else f"{args.area:g}x{args.area:g}"
            print(f"simulated {side} m lawnmower, seed {args.seed}: {s['frames']} frames in {time.perf_counter() - t0:.1f} s",
                  flush=True)
        work = out / f"work_{args.scheduler}"
        shutil.rmtree(work, ignore_errors=True)
        rep = run_stage_build(log, work, args.scheduler, progressive=not args.single_round)
        L, R, O, G = rep["links"], rep["registration"], rep["optimization"], rep.get("ground_truth", {})
        figures["report"] = {k: rep[k] for k in ("stages", "links", "registration", "optimization", "ground_truth") if k in rep}
        print(f"\nbuild --until optimize ({args.scheduler} scheduler), {R['frames']} frames:")
        print(f"  links: {L['candidates']} candidates ({R['sequential_candidates']} sequential, {R['revisit_candidates']} revisit), "
              f"{L['accepted']} accepted, {L['rejected']} rejected ({L['rejected_registration']} by registration: "
              f"{R['rejection_reasons']}; {L['rejected_outliers']} as outliers)")
        print(f"  registration: {R['pairs_per_s']:.1f} pairs/s (stage {rep['stages']['register']['seconds']:.1f} s)   "
              f"[target >= 200]; feature path: {R['feature_path']} pairs")
        if "window_fit_seconds" in R:
            print(f"  progressive revisits: {R['passes']} windows, revisit search radius median "
                  f"{R['revisit_radius_px_median']:.1f} px / p95 {R['revisit_radius_px_p95']:.1f} px, window solves "
                  f"{R['window_fit_seconds']:.1f} s (iSAM2), {R['window_fit_dropped']} links left out of them")
        print(f"  link error vs ground truth: median {G.get('link_error_median_px', float('nan')):.4f} px, "
              f"p95 {G.get('link_error_p95_px', float('nan')):.4f} px   [target <= 0.02 / 0.05]")
        print(f"  pose error vs ground truth: RMS {G.get('pose_rms_px', float('nan')):.4f} px, "
              f"max {G.get('pose_max_px', float('nan')):.4f} px (odometry RMS {G.get('odometry_rms_px', float('nan')):.1f})"
              f"   [target <= 0.2 / 0.5]")
        print(f"  optimization: {O['seconds']:.2f} s ({O['iterations']} LM iterations, {O['passes']} solves), "
              f"residual RMS {O['residual_rms_px']:.4f} px")

        store_path = work / "ingest" / "frames.zarr"
        store = FrameStore(store_path)
        lf = store.logs[0]
        gt = ground_truth_at(lf.t, Path(lf.attrs["path"]) / "ground_truth.csv")
        links_reg = read_links(work / "register" / "links.csv")
        links_opt = read_links(work / "links.csv")
        acc = [lk for lk in links_reg if lk.status == "accepted"]
        e = gt_errors(acc, gt)
        seq = np.array([lk.b - lk.a <= load_config()["register"]["sequential_window"] for lk in acc])
        opp = e["dtheta"] > 2.5
        chi = {}
        print("\n  chi-square of link covariances (Mahalanobis^2 of ground-truth errors, 3 dof: mean ~3, median ~2.37, "
              "0.1 % above 16.27):")
        for name, sel in (("all accepted", np.ones(len(acc), bool)), ("sequential", seq),
                          ("revisit, other dtheta", ~seq & ~opp), ("revisit, dtheta~pi", ~seq & opp)):
            if not sel.any():
                continue
            row = {"n": int(sel.sum())}
            for conv in ("m_a", "m_b"):
                m = e[conv][sel]
                row[conv] = {"mean": float(m.mean()), "median": float(np.median(m)), "above_16.27": int((m > 16.27).sum())}
            row["px_median"], row["px_p95"] = _pct(e["px"][sel], 50), _pct(e["px"][sel], 95)
            chi[name] = row
            print(f"    {name:20} n={row['n']:5d}  frame-a convention: mean {row['m_a']['mean']:7.2f} median "
                  f"{row['m_a']['median']:5.2f} >16.27: {row['m_a']['above_16.27']:4d}   frame-b (optimizer) convention: mean "
                  f"{row['m_b']['mean']:7.2f} median {row['m_b']['median']:5.2f} >16.27: {row['m_b']['above_16.27']:4d}   "
                  f"error px median {row['px_median']:.4f} p95 {row['px_p95']:.4f}")
        figures["chi_square"] = chi
        rej_out = [lk for lk in links_opt if lk.reason.startswith("outlier")]
        n_opp = sum(abs(lk.rel[2]) > 2.5 for lk in rej_out)
        print(f"  outlier-rejected links: {len(rej_out)}, of which dtheta~pi: {n_opp}; their ground-truth errors: "
              f"{', '.join(f'{x:.3f}' for x in sorted(gt_errors(rej_out, gt)['px'])[-5:]) if rej_out else '-'} px (largest)")
        figures["outlier_rejected"] = [(lk.a, lk.b, round(float(lk.rel[2]), 3)) for lk in rej_out]

        order = np.argsort(-e["px"])[: args.worst]
        q = lf.group["quality"][...] if hasattr(lf, "group") else None
        cols = list(lf.group["quality"].attrs.get("columns", [])) if q is not None else []
        tf = cols.index("textured_fraction") if "textured_fraction" in cols else None
        print(f"\n  worst {len(order)} accepted links vs ground truth (status after optimization):")
        status_opt = {(lk.a, lk.b): lk.status for lk in links_opt}
        worst = []
        for i in order:
            lk = acc[i]
            kind = "sequential" if seq[i] else ("revisit dtheta~pi" if opp[i] else "revisit")
            tex = "" if tf is None else f" textured {q[lk.a, tf]:.2f}/{q[lk.b, tf]:.2f}"
            w = {"a": lk.a, "b": lk.b, "kind": kind, "error_px": float(e["px"][i]), "m_a": float(e["m_a"][i]),
                 "m_b": float(e["m_b"][i]), "ncc": lk.ncc, "uniqueness": lk.uniqueness, "overlap": lk.overlap,
                 "status_after_optimize": status_opt.get((lk.a, lk.b))}
            worst.append(w)
            print(f"    {lk.a:4d}-{lk.b:4d} {kind:18} error {w['error_px']:.3f} px  maha a/b {w['m_a']:7.1f}/{w['m_b']:7.1f}  "
                  f"ncc {lk.ncc:.3f} uniq {lk.uniqueness:.3f} overlap {lk.overlap:.2f}{tex}  -> {w['status_after_optimize']}")
        figures["worst_links"] = worst

        cfg_opt = load_config()["optimize"]
        priors = [x.prior for x in store.logs]
        runs = []
        print("\n  corruption experiment (5 % of accepted links offset 5-50 px; optimize_poses on the odometry priors):")
        for s in range(args.corrupt_seeds):
            r = corruption(priors, links_reg, gt, cfg_opt, seed=s)
            runs.append(r)
            print(f"    seed {s}: {r['corrupted']} of {r['links']} corrupted, rejected {r['corrupted_rejected']} "
                  f"(missed {r['corrupted_missed'] or 'none'}), good rejected {r['good_rejected']} (clean run "
                  f"{r['good_rejected_clean_run']}); pose change {r['pose_change_rms_px']:.4f} px RMS raw "
                  f"(max {r['pose_change_max_px']:.4f}), {r['pose_change_aligned_rms_px']:.4f} aligned "
                  f"[target <= 0.05]; ATE clean {r['ate_clean_rms_px']:.4f} / corrupt {r['ate_corrupt_rms_px']:.4f} px RMS; "
                  f"{r['seconds_corrupt']:.2f} s", flush=True)
        figures["corruption"] = runs

        if args.peer_pairs > 0:
            p = peer(store_path, links_reg, gt, load_config(), args.peer_pairs)
            figures["peer"] = p
            print(f"\n  peer on {p['pairs']} sequential pairs from the odometry prior (one thread each):")
            print(f"    {'method':32} {'ok':>4} {'median px':>10} {'p95 px':>8} {'max px':>8} {'pairs/s':>8}")
            for name, key in (("cv2.findTransformECC (EUCLIDEAN)", "ecc"), ("mosaicmap register_pair", "ours")):
                f = p[key]
                print(f"    {name:32} {f['ok']:4d} {f['median_px']:10.4f} {f['p95_px']:8.4f} {f['max_px']:8.4f} "
                      f"{f['pairs_per_s']:8.1f}")
        if args.json:
            args.json.write_text(json.dumps(figures, indent=2, default=float) + "\n")
            print(f"\nfigures -> {args.json}")
    finally:
        if tmp is not None:
            tmp.cleanup()


if __name__ == "__main__":
    main()
