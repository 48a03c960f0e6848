"""Benchmark on the real image sets of ../shared/data/real (see examples/README.md).

1. Microscope tiles (lscm_speckle_3x4): ``import-tiles`` (with Fiji's registered positions as
   the peer), ``build --until optimize`` with ``examples/lscm_speckle.toml``, then per tile our
   position (pixels, :func:`pipeline.importers.tiles.tile_positions_from_poses`), the peer's,
   the nominal one, and ours - peer after removing the common translation (both are defined
   up to a shift: aligned by their means, and by tile 0); RMS / max of that difference; our
   links' residuals after optimization; and the peer's *implied* link residuals: for each of
   our accepted links, our measured offset minus the peer's position difference.

   Offsets of a link are compared as *translation-equivalent offsets at the overlap's
   centre* (the midpoint of the two tile centres): a rigid link's small rotation (which the
   lens distortion puts into every 10 % strip) moves the tile centres by rotation x lever
   arm, ~1-3 px here, but not the overlap where the link was measured. Both this figure
   and the pipeline's ``residual_px`` (at frame b's centre) are printed.

2. Whole-slide brain section (wsi_brain_16bit_9x7, 63 16-bit tiles, snake order):
   ``import-tiles`` from the folder (``--grid 9x7 --order snake-rows --first top-right
   --step 460``), ``build --map REPO`` with the defaults (published when its gates pass);
   per tile our position against Fiji's ``TileConfiguration.registered.txt`` after a
   translation fit (median offset over the linked tiles Fiji did not misplace): the
   *interior* (registrable tiles whose four grid neighbours are registrable too) median /
   max, the linked tiles', Fiji's three misplaced background tiles (0001, 0037, 0054)
   flagged apart, the tiles placed by their prior with ingest's reason, and the registrable
   tiles left without a link (none expected).

3. Drone (seneca_drone): ``import-geotagged``, ``build --until optimize`` with
   ``examples/seneca_drone.toml``; frames accepted by ingest (rejections with reasons),
   candidate pairs, accepted links, their residuals after optimization (median, p95, max;
   the issue requires none above 2 px), and the frames without any accepted link, with
   the rejection reasons of their candidate links.

    python bench/bench_real.py [--only lscm|brain|drone] [--out DIR] [--keep]

Exit code 0 when every check holds (tiles: RMS vs peer within ``--peer-rms-bound`` after
mean alignment; brain: published, every registrable tile linked, interior median <= 1 px;
drone: no accepted link above 2 px), 1 otherwise.
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
import subprocess
import sys
import tempfile
import time
from collections import Counter, defaultdict
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
LSCM = SHARED / "data" / "real" / "lscm_speckle_3x4"
DRONE = SHARED / "data" / "real" / "seneca_drone" / "images"
BRAIN = SHARED / "data" / "real" / "wsi_brain_16bit_9x7"
BRAIN_IMPORT = ("--grid", "9x7", "--order", "snake-rows", "--first", "top-right", "--step", "460",
                "--glob", "C3-BrainSection*.tif")
# Fiji's misplaced right-column background tiles (BRAIN/SOURCE.md): flagged, not compared.
BRAIN_FIJI_FAILURES = ("C3-BrainSection0001.tif", "C3-BrainSection0037.tif", "C3-BrainSection0054.tif")
LSCM_PIXEL_SIZE = 0.001  # nominal 1 mm per tile pixel (see examples/lscm_speckle.toml)
MAX_LINK_RESIDUAL_PX = 2.0


def mosaicmap(*args: str) -> None:
    """Run the CLI of this interpreter's environment; raise on a non-zero exit code."""
    cmd = [sys.executable, "-m", "pipeline.cli", *map(str, args)]
    print("$ mosaicmap " + " ".join(map(str, args)), flush=True)
    r = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    for line in (r.stdout + r.stderr).strip().splitlines():
        print("  " + line)
    if r.returncode != 0:
        raise SystemExit(f"mosaicmap {args[0]} failed with exit code {r.returncode}")


def read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def read_poses(workdir: Path) -> tuple[np.ndarray, list[int]]:
    """W/poses.csv -> (N, 4) t, x, y, theta and the frames.csv row of each pose."""
    rows = read_csv(workdir / "poses.csv")
    return (np.array([[float(r[k]) for k in ("t", "x", "y", "theta")] for r in rows]),
            [int(r["frame"]) for r in rows])


def _rot(th: float) -> np.ndarray:
    c, s = np.cos(th), np.sin(th)
    return np.array([[c, -s], [s, c]])


def mid_offset(rel: np.ndarray) -> np.ndarray:
    """Translation-equivalent offset (a's frame, metres) of a rigid ``rel`` at the centres' midpoint."""
    t = np.asarray(rel[:2], float)
    m = t / 2.0
    return m - _rot(rel[2]).T @ (m - t)


def between(pa: np.ndarray, pb: np.ndarray) -> np.ndarray:
    d = _rot(pa[2]).T @ (pb[:2] - pa[:2])
    return np.array([d[0], d[1], pb[2] - pa[2]])


def stats(v) -> str:
    v = np.asarray(v, float)
    if v.size == 0:
        return "none"
    return (f"median {np.median(v):.3f}, p95 {np.percentile(v, 95):.3f}, max {v.max():.3f}, "
            f"RMS {np.sqrt(np.mean(v ** 2)):.3f} px (n={v.size})")


# --- microscope tiles ------------------------------------------------------------------


def lscm_compare(log: Path, workdir: Path, tile_config: Path, peer_config: Path) -> dict:
    """The tile comparison (figures dict); prints the tables."""
    from pipeline.importers.tiles import read_tile_configuration, tile_positions_from_poses

    P = LSCM_PIXEL_SIZE
    poses, frame_rows = read_poses(workdir)
    images = [Path(r["image"]).name for r in read_csv(log / "frames.csv")]
    names = [images[i] for i in frame_rows]
    nominal = {n: (x, y) for n, x, y in read_tile_configuration(tile_config)}
    peer = {n: (x, y) for n, x, y in read_tile_configuration(peer_config)}
    ours = tile_positions_from_poses(poses, (1024, 1024), P)
    nom = np.array([nominal[n] for n in names])
    pr = np.array([peer[n] for n in names])
    d_mean = (ours - ours.mean(0)) - (pr - pr.mean(0))
    d_first = (ours - ours[0]) - (pr - pr[0])
    n_mean = np.hypot(*d_mean.T)
    n_first = np.hypot(*d_first.T)
    print("\nper tile (pixels; top-left corner as in TileConfiguration; diff = ours - peer after "
          "removing the mean shift, [after aligning tile 0])")
    print(f"{'#':>2} {'tile':<8} {'ours x':>9} {'ours y':>9} {'peer x':>9} {'peer y':>9} {'nom x':>7} "
          f"{'nom y':>7} {'diff x':>7} {'diff y':>7} {'|diff|':>6} {'[tile 0]':>8} {'theta mrad':>10}")
    for i, n in enumerate(names):
        short = n.split("_")[-2]
        print(f"{i:>2} {short:<8} {ours[i, 0]:9.2f} {ours[i, 1]:9.2f} {pr[i, 0]:9.2f} {pr[i, 1]:9.2f} "
              f"{nom[i, 0]:7.0f} {nom[i, 1]:7.0f} {d_mean[i, 0]:7.2f} {d_mean[i, 1]:7.2f} {n_mean[i]:6.2f} "
              f"{n_first[i]:8.2f} {poses[i, 3] * 1e3:10.3f}")
    rms_mean = float(np.sqrt(np.mean(n_mean ** 2)))
    rms_first = float(np.sqrt(np.mean(n_first ** 2)))
    dn = (nom - nom.mean(0)) - (pr - pr.mean(0))
    rms_nom = float(np.sqrt(np.mean(np.sum(dn ** 2, axis=1))))
    print(f"ours - peer: RMS {rms_mean:.2f} px, max {n_mean.max():.2f} px (mean-aligned); "
          f"RMS {rms_first:.2f} px, max {n_first.max():.2f} px (tile-0-aligned)")
    print(f"nominal - peer (mean-aligned): RMS {rms_nom:.2f} px, max {np.hypot(*dn.T).max():.2f} px")
    # A per-axis scale between the two mosaics (what a distortion-dependent definition of
    # the strip offset produces): ours = s * peer + t, per axis, least squares.
    sc, fit = [], np.empty_like(ours)
    for k in range(2):
        A = np.column_stack([pr[:, k], np.ones(len(pr))])
        coef = np.linalg.lstsq(A, ours[:, k], rcond=None)[0]
        sc.append(coef[0])
        fit[:, k] = A @ coef
    n_scale = np.hypot(*(ours - fit).T)
    rms_scale = float(np.sqrt(np.mean(n_scale ** 2)))
    print(f"ours vs peer after a per-axis scale (x {100 * (sc[0] - 1):+.3f} %, y {100 * (sc[1] - 1):+.3f} %) "
          f"and shift: RMS {rms_scale:.2f} px, max {n_scale.max():.2f} px")

    # Links: our residuals, the peer's and the nominal grid's implied residuals.
    links = read_csv(workdir / "links.csv")
    acc = [lk for lk in links if lk["status"] == "accepted"]
    print(f"\nlinks: {len(links)} candidates, {len(acc)} accepted "
          f"({Counter(lk['reason'].split(' (')[0] for lk in links if lk['status'] != 'accepted') or 'none rejected'})")
    print("per accepted link (pixels; offsets are image column/row of tile b minus tile a at the "
          "overlap centre):")
    print(f"{'a':>2} {'b':>2} {'kind':<6} {'meas dx':>8} {'meas dy':>8} {'rot mrad':>8} {'peer dx':>8} "
          f"{'peer dy':>8} {'res@b':>6} {'ours@ov':>7} {'peer@ov':>7} {'nom@ov':>7} {'ncc':>5} {'uniq':>5}")
    res_b, res_ours, res_peer, res_nom = [], [], [], []
    by_kind: dict[str, list] = defaultdict(list)
    for lk in acc:
        a, b = int(lk["a"]), int(lk["b"])
        rel = np.array([float(lk["dx"]), float(lk["dy"]), float(lk["dtheta"])])
        m = mid_offset(rel) / P * np.array([1.0, -1.0])  # metres (y up) -> pixels (rows down)
        e = mid_offset(between(poses[a, 1:], poses[b, 1:])) / P * np.array([1.0, -1.0])
        pd = pr[b] - pr[a]
        nd = nom[b] - nom[a]
        kind = "row" if abs(nd[0]) > abs(nd[1]) else "column"
        r_b = float(lk["residual_px"])
        r_o, r_p, r_n = np.hypot(*(m - e)), np.hypot(*(m - pd)), np.hypot(*(m - nd))
        res_b.append(r_b), res_ours.append(r_o), res_peer.append(r_p), res_nom.append(r_n)
        by_kind[kind].append((m - pd))
        print(f"{a:>2} {b:>2} {kind:<6} {m[0]:8.2f} {m[1]:8.2f} {rel[2] * 1e3:8.2f} {pd[0]:8.2f} {pd[1]:8.2f} "
              f"{r_b:6.2f} {r_o:7.2f} {r_p:7.2f} {r_n:7.2f} {float(lk['ncc']):5.2f} {float(lk['uniqueness']):5.2f}")
    print(f"our residuals at b's centre (pipeline residual_px): {stats(res_b)}")
    print(f"our residuals at the overlap centre:                {stats(res_ours)}")
    print(f"peer's implied residuals at the overlap centre:     {stats(res_peer)}")
    print(f"nominal grid's implied residuals:                   {stats(res_nom)}")
    for kind, v in by_kind.items():
        v = np.array(v)
        print(f"  measured - peer, {kind} links: mean ({v[:, 0].mean():+.2f}, {v[:, 1].mean():+.2f}) px, "
              f"sd ({v[:, 0].std():.2f}, {v[:, 1].std():.2f}) px")
    return {
        "tiles": len(names), "rms_px": rms_mean, "max_px": float(n_mean.max()),
        "rms_first_px": rms_first, "scale_x": float(sc[0]), "scale_y": float(sc[1]),
        "rms_scaled_px": rms_scale, "max_scaled_px": float(n_scale.max()), "max_first_px": float(n_first.max()), "nominal_rms_px": rms_nom,
        "links": len(links), "accepted": len(acc),
        "residual_b_max_px": max(res_b, default=0.0), "residual_overlap_max_px": max(res_ours, default=0.0),
        "residual_overlap_rms_px": float(np.sqrt(np.mean(np.square(res_ours)))) if res_ours else 0.0,
        "peer_implied_median_px": float(np.median(res_peer)) if res_peer else None,
    }


def run_lscm(out: Path) -> dict:
    log, work = out / "lscm_log", out / "lscm_work"
    for p in (log, work):
        shutil.rmtree(p, ignore_errors=True)
    t0 = time.perf_counter()
    mosaicmap("import-tiles", LSCM / "TileConfiguration.txt", log, "--pixel-size", LSCM_PIXEL_SIZE,
              "--peer", LSCM / "TileConfiguration.registered.txt", "--quiet")
    mosaicmap("build", log, "-w", work, "--until", "optimize", "--config", REPO / "examples" / "lscm_speckle.toml",
              "--report", out / "lscm_report.json", "--quiet")
    print(f"import + build: {time.perf_counter() - t0:.1f} s")
    return lscm_compare(log, work, LSCM / "TileConfiguration.txt", LSCM / "TileConfiguration.registered.txt")


# --- whole-slide brain section -------------------------------------------------------------


def brain_compare(log: Path, workdir: Path, peer_config: Path = BRAIN / "TileConfiguration.registered.txt") -> dict:
    """wsi_brain against Fiji (figures dict); prints the table. Positions in pixels."""
    from pipeline.importers.tiles import read_tile_configuration, tile_positions_from_poses

    poses, frame_rows = read_poses(workdir)
    images = [Path(r["image"]).name for r in read_csv(log / "frames.csv")]
    names = [images[i] for i in frame_rows]
    ours = tile_positions_from_poses(poses, (512, 512), LSCM_PIXEL_SIZE)
    odo = read_csv(log / "odometry.csv")
    nominal = tile_positions_from_poses(np.array([[float(odo[i][k]) for k in ("x", "y", "theta")]
                                                  for i in frame_rows]), (512, 512), LSCM_PIXEL_SIZE)
    cell = {i: (int(round(y / 460.0)), int(round(x / 460.0))) for i, (x, y) in enumerate(nominal - nominal.min(0))}
    at = {c: i for i, c in cell.items()}
    manifest = json.loads((workdir / "ingest" / "manifest.json").read_text())["counts"]["ingest"]
    prior_reason = {Path(r["image"]).name: r["reason"] for r in manifest.get("placed_by_prior", [])}
    linked = Counter()
    for lk in read_csv(workdir / "links.csv"):
        if lk["status"] == "accepted":
            linked[int(lk["a"])] += 1
            linked[int(lk["b"])] += 1
    peer = {n: (x, y) for n, x, y in read_tile_configuration(peer_config)}
    common = [i for i, n in enumerate(names) if n in peer]
    fit = [i for i in common if names[i] not in BRAIN_FIJI_FAILURES and linked[i] > 0]
    shift = np.median(np.array([np.subtract(ours[i], peer[names[i]]) for i in fit]), axis=0)
    dist = {i: float(np.hypot(*(np.subtract(ours[i], peer[names[i]]) - shift))) for i in common}
    registrable = {i for i, n in enumerate(names) if n not in prior_reason}
    interior = [i for i in fit if i in registrable and all(
        at.get((cell[i][0] + dr, cell[i][1] + dc)) in registrable for dr, dc in ((0, 1), (0, -1), (1, 0), (-1, 0)))]
    unlinked = [names[i] for i in sorted(registrable) if linked[i] == 0]
    print(f"\nper tile: distance to Fiji after the translation fit ({shift[0]:+.2f}, {shift[1]:+.2f}) px")
    for r in range(max(c[0] for c in cell.values()) + 1):
        row = []
        for c in range(max(c[1] for c in cell.values()) + 1):
            i = at.get((r, c))
            if i is None:
                row.append(f"{'':>13}")
                continue
            tag = "F" if names[i] in BRAIN_FIJI_FAILURES else ("p" if names[i] in prior_reason else " ")
            d = f"{dist[i]:6.2f}" if i in dist else "    - "
            row.append(f"{names[i][-8:-4]}{tag}{d}{'*' if i in interior else ' '} ")
        print(" ".join(row))
    print("(F: Fiji misplaced it; p: placed by its prior; *: interior; -: not in Fiji's file)")
    for n, why in prior_reason.items():
        print(f"  placed by its prior: {n}: {why}")
    for n in BRAIN_FIJI_FAILURES:
        i = names.index(n) if n in names else None
        if i is not None and i in dist:
            print(f"  Fiji misplaced {n}: ours {dist[i]:.1f} px from Fiji's (not compared)")
    vi = np.array([dist[i] for i in interior])
    vf = np.array([dist[i] for i in fit])
    print(f"interior tiles ({len(vi)}): median {np.median(vi):.2f} px, max {vi.max():.2f}; "
          f"all linked tiles Fiji placed ({len(vf)}): median {np.median(vf):.2f}, max {vf.max():.2f}")
    print(f"registrable tiles without an accepted link: {len(unlinked)} {unlinked}")
    return {"tiles": len(names), "registrable": len(registrable), "placed_by_prior": len(prior_reason),
            "unlinked_registrable": len(unlinked), "interior_tiles": len(vi),
            "interior_median_px": float(np.median(vi)), "interior_max_px": float(vi.max()),
            "linked_median_px": float(np.median(vf)), "linked_max_px": float(vf.max())}


def run_brain(out: Path) -> dict:
    log, work, repo = out / "brain_log", out / "brain_work", out / "brain_map"
    for p in (log, work, repo):
        shutil.rmtree(p, ignore_errors=True)
    t0 = time.perf_counter()
    mosaicmap("import-tiles", BRAIN, log, "--pixel-size", LSCM_PIXEL_SIZE, *BRAIN_IMPORT, "--quiet")
    mosaicmap("build", log, "-w", work, "--map", repo, "--report", out / "brain_report.json", "--quiet")
    print(f"import + build + publish: {time.perf_counter() - t0:.1f} s")
    f = brain_compare(log, work)
    f["published"] = bool(json.loads((out / "brain_report.json").read_text()).get("publish"))
    return f


# --- drone -------------------------------------------------------------------------------


def drone_summary(log: Path, workdir: Path, max_res: float = MAX_LINK_RESIDUAL_PX) -> dict:
    manifest = json.loads((workdir / "ingest" / "manifest.json").read_text())["counts"]["ingest"]
    images = [r["image"] for r in read_csv(log / "frames.csv")]
    poses, frame_rows = read_poses(workdir)
    print(f"\ningest: {manifest['frames_accepted']} of {manifest['frames_total']} frames accepted")
    for r in manifest["rejected"]:
        print(f"  rejected {r['image']}: {r['reason']}")
    reg = read_csv(workdir / "register" / "links.csv")
    links = read_csv(workdir / "links.csv")
    acc = [lk for lk in links if lk["status"] == "accepted"]
    reg_ok = sum(lk["status"] == "accepted" for lk in reg)
    feat = sum(lk["method"] == "features" for lk in reg)
    print(f"candidate pairs: {len(reg)} ({feat} through the feature path); registered: {reg_ok}; "
          f"accepted after optimization: {len(acc)} ({reg_ok - len(acc)} rejected as outliers)")
    reasons = Counter(lk["reason"].split(" (")[0].split(":")[0] for lk in links if lk["status"] != "accepted")
    for r, c in reasons.most_common():
        print(f"  rejected {c:4d}: {r}")
    res = np.array([float(lk["residual_px"]) for lk in acc])
    print(f"accepted link residuals after optimization: {stats(res)}")
    # A link that no loop closes (a bridge of the link graph) fits exactly whatever its
    # error: only the links on loops tell how well the map agrees with itself.
    from pipeline.links import on_cycles

    ends = np.array([[int(lk["a"]), int(lk["b"])] for lk in acc], np.int64).reshape(-1, 2)
    loop = on_cycles(len(poses), ends[:, 0], ends[:, 1]) if len(acc) else np.zeros(0, bool)
    print(f"accepted links on loops: {int(loop.sum())} of {len(acc)}; their residuals: {stats(res[loop])}")
    over = [lk for lk in acc if float(lk["residual_px"]) > max_res]
    print(f"accepted links above {max_res} px: {len(over)}")
    for lk in over[:20]:
        print(f"  {lk['a']}-{lk['b']}: {float(lk['residual_px']):.2f} px, Mahalanobis {float(lk['mahalanobis']):.1f}")
    linked = {int(lk[k]) for lk in acc for k in ("a", "b")}
    orphans = [g for g in range(len(poses)) if g not in linked]
    print(f"frames without an accepted link: {len(orphans)} of {len(poses)}")
    for g in orphans:
        why = Counter(lk["reason"].split(" (")[0] for lk in links if int(lk["a"]) == g or int(lk["b"]) == g)
        text = "; ".join(f"{c} x {r}" for r, c in why.most_common()) or "no candidate pair"
        print(f"  {g:3d} {images[frame_rows[g]]}: {text}")
    return {
        "frames_total": manifest["frames_total"], "frames_accepted": manifest["frames_accepted"],
        "candidates": len(reg), "registered": reg_ok, "accepted": len(acc),
        "residual_median_px": float(np.median(res)) if res.size else None,
        "residual_p95_px": float(np.percentile(res, 95)) if res.size else None,
        "residual_max_px": float(res.max()) if res.size else None,
        "above_bound": len(over), "unregistered_frames": len(orphans),
        "on_loops": int(loop.sum()),
        "loop_residual_median_px": float(np.median(res[loop])) if loop.any() else None,
        "loop_residual_p95_px": float(np.percentile(res[loop], 95)) if loop.any() else None,
    }


def run_drone(out: Path) -> dict:
    log, work = out / "drone_log", out / "drone_work"
    for p in (log, work):
        shutil.rmtree(p, ignore_errors=True)
    t0 = time.perf_counter()
    mosaicmap("import-geotagged", DRONE, log, "--quiet")
    mosaicmap("build", log, "-w", work, "--until", "optimize", "--config", REPO / "examples" / "seneca_drone.toml",
              "--report", out / "drone_report.json", "--quiet")
    print(f"import + build: {time.perf_counter() - t0:.1f} s")
    return drone_summary(log, work)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", choices=("lscm", "brain", "drone"))
    ap.add_argument("--out", type=Path, help="keep logs and work directories here (default: a temp dir)")
    ap.add_argument("--peer-rms-bound", type=float, default=3.0,
                    help="tiles: bound on the RMS vs peer after mean alignment (px)")
    args = ap.parse_args()
    if not SHARED.exists():
        print(f"real data absent: {SHARED}")
        return 0
    out = args.out or Path(tempfile.mkdtemp(prefix="bench_real_"))
    out.mkdir(parents=True, exist_ok=True)
    ok = True
    figures = {}
    try:
        if args.only in (None, "lscm"):
            print("== lscm_speckle_3x4 (microscope tiles) ==")
            f = figures["lscm"] = run_lscm(out)
            ok &= f["rms_px"] <= args.peer_rms_bound
        if args.only in (None, "brain"):
            print("\n== wsi_brain_16bit_9x7 (16-bit whole-slide tiles) ==")
            f = figures["brain"] = run_brain(out)
            ok &= f["published"] and f["unlinked_registrable"] == 0 and f["interior_median_px"] <= 1.0
        if args.only in (None, "drone"):
            print("\n== seneca_drone ==")
            f = figures["drone"] = run_drone(out)
            ok &= f["above_bound"] == 0
    finally:
        if args.out is None:
            shutil.rmtree(out, ignore_errors=True)
    print("\nfigures: " + json.dumps(figures))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
