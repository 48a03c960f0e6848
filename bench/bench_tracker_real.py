"""The floor tracker on real images: a tile of ``lscm_speckle_3x4`` left out of the map.

For a chosen tile (default: the first one, in file order, with the most grid neighbours;
``--tile NAME``; ``--all`` for every tile in turn):

1. write a tile configuration without it, ``mosaicmap import-tiles``, ``build --map`` (with
   ``examples/lscm_speckle.toml``) and ``export`` a bundle of the other 11 tiles (every
   level, so level 0 is in it); ``mosaicmap poses`` gives the map's poses of the 11. A full
   12-tile ``build --until optimize`` gives our own position of the left-out tile.
2. rectify the left-out tile as ingest would (``pipeline.camera.Rectifier`` with the
   configuration's interpolation, valid-mask erosion and flat field, at the map pixel size)
   and localize it with the vehicle-side API only (:func:`tracker.bundle_map.open_bundle`,
   :meth:`TrackerMap.floor_tracker`, :meth:`FloorTracker.fix`,
   :func:`tracker.reloc.build_index`, :class:`tracker.reloc.Relocalizer`):

   (a) prior = the tile's nominal stage position (``TileConfiguration.txt``) with a 1-sigma
       covering the stage error (measured: nominal minus the map's positions of the 11
       built tiles, and nominal minus Fiji's after a tile-0 alignment);
   (b) no prior: relocalization.

   Each is run with the configs/tracker.toml defaults and with the bench's
   :data:`FLOOR_PARAMS` (looser fit limits: lens distortion bends the strips); the tracker
   takes templates only where the map holds data around the prior (the tile is not in the
   map: only the ~10 % strips along its edges, where the neighbours overlap it, can match;
   :mod:`tracker.coverage`); relocalization with the default index and a dense one
   (:data:`RELOC_SETTINGS`).
3. print the fix (tile position x, y in tile-grid pixels, i.e. TileConfiguration's top-left
   corner convention, and heading), its status and quality, Fiji's registered position
   (``TileConfiguration.registered.txt``: the peer) brought into the map's frame through
   the 11 common tiles (a rigid fit, and a per-axis scale + shift fit), the differences,
   and the difference to our full 12-tile build (rigidly aligned through the 11 common
   tiles); time per fix (cold and warm tile cache) and relocalization time.

    python bench/bench_tracker_real.py [--tile A007] [--all] [--out DIR]

Exit code 0 when no ``ok`` fix of any run is further than ``--bound-px`` (2 px, the
tracker's wrong-ok bound) from our full build, 1 otherwise (a fix that is not ok is a
figure, not a failure). Units: tile pixels (1 px = 1 mm at the
import's nominal pixel size), headings in milliradians.
"""

from __future__ import annotations

import argparse
import csv
import json
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from tracker.bundle_map import open_bundle  # noqa: E402
from tracker.floor import Fix, FloorTracker, FloorTrackerParams  # noqa: E402
from tracker.reloc import Relocalizer, RelocParams, build_index  # noqa: E402

SHARED = REPO.parent / "shared"
LSCM = SHARED / "data" / "real" / "lscm_speckle_3x4"
CONFIG = REPO / "examples" / "lscm_speckle.toml"
PIXEL_SIZE = 0.001  # metres per tile pixel (the import's nominal scale, examples/README.md)
TILE_SHAPE = (1024, 1024)

# Bench-side tracker settings (every other value is the configs/tracker.toml default).
# The tiles carry lens distortion that bends every 10 % strip by ~2.7 px (examples/README.md):
# a rigid fit of templates spread over the four strips of the left-out tile leaves
# ~0.5-0.8 px RMS, corner templates up to ~3 px, so the consistency bounds are widened from
# 0.75 / 0.4 px to 1.5 / 1.0 px. The speckle is faint (texture score median ~7, 95th
# percentile ~34 (grey levels / px)^2), so min_texture 10 instead of 20, and 8 x 8 cells
# (16 templates) so that many cells fall in the ~100 px strips the map covers; the fit's own
# 1-sigma may reach 0.4 px (0.25 by default) as its residuals are larger.
FLOOR_PARAMS = FloorTrackerParams(grid_cells=(8, 8), n_templates=16, min_texture=10.0,
                                  max_residual_px=1.5, max_rms_px=1.0, max_sigma_px=0.4)
# Relocalization: the configs/tracker.toml defaults, and a denser index and query (the
# frame's strips are a third of it; speckle has many small corners) for comparison.
RELOC_SETTINGS = {"defaults": RelocParams(), "dense": RelocParams(features_per_tile=200, query_features=3000)}


# --- tile configurations -----------------------------------------------------------------


def read_tiles(path: Path) -> dict[str, tuple[float, float]]:
    """A TileConfiguration -> {file name: (x, y) top-left corner in pixels}, file order."""
    from pipeline.importers.tiles import read_tile_configuration

    return {Path(n).name: (x, y) for n, x, y in read_tile_configuration(path)}


def neighbour_counts(tiles: dict[str, tuple[float, float]], shape: tuple[int, int] = TILE_SHAPE,
                     min_fraction: float = 0.05) -> dict[str, int]:
    """Per tile, how many other tiles overlap it by at least ``min_fraction`` of its area."""
    names = list(tiles)
    xy = np.array([tiles[n] for n in names])
    h, w = shape
    ox = np.clip(w - np.abs(xy[:, None, 0] - xy[None, :, 0]), 0, None)
    oy = np.clip(h - np.abs(xy[:, None, 1] - xy[None, :, 1]), 0, None)
    frac = ox * oy / float(w * h)
    np.fill_diagonal(frac, 0.0)
    return {n: int(c) for n, c in zip(names, (frac >= min_fraction).sum(axis=1))}


def default_tile(tiles: dict[str, tuple[float, float]]) -> str:
    """The first tile (file order) with the most neighbours: an interior one."""
    counts = neighbour_counts(tiles)
    return max(tiles, key=lambda n: (counts[n], -list(tiles).index(n)))


def short(name: str) -> str:
    """``x100_..._A007_I.tif`` -> ``A007``."""
    parts = Path(name).stem.split("_")
    return parts[-2] if len(parts) >= 2 else Path(name).stem


def resolve_tile(tiles: dict[str, tuple[float, float]], key: str) -> str:
    """A tile by file name or short name (``A007``)."""
    for n in tiles:
        if key in (n, Path(n).stem, short(n)):
            return n
    raise SystemExit(f"no tile {key!r} in {LSCM / 'TileConfiguration.txt'} ({', '.join(short(n) for n in tiles)})")


def write_tile_configuration(path: Path, tiles: dict[str, tuple[float, float]], folder: Path) -> None:
    """A Fiji TileConfiguration of ``tiles`` with absolute image paths (so it may live anywhere)."""
    lines = ["# Define the number of dimensions we are working on", "dim = 2", "", "# Define the image coordinates"]
    lines += [f"{(folder / n).resolve()}; ; ({x!r}, {y!r})" for n, (x, y) in tiles.items()]
    path.write_text("\n".join(lines) + "\n")


# --- the pipeline (CLI) -------------------------------------------------------------------


def mosaicmap(*args, verbose: bool = True) -> float:
    """Run the CLI of this interpreter's environment; raise on failure; returns seconds."""
    cmd = [sys.executable, "-m", "pipeline.cli", *map(str, args)]
    t0 = time.perf_counter()
    r = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    dt = time.perf_counter() - t0
    if verbose:
        print(f"$ mosaicmap {shlex.join(map(str, args))}  ({dt:.1f} s)", flush=True)
        for line in (r.stdout + r.stderr).strip().splitlines():
            print("    " + line)
    if r.returncode != 0:
        raise RuntimeError(f"mosaicmap {args[0]} failed with exit code {r.returncode}:\n{r.stdout}\n{r.stderr}")
    return dt


def read_csv(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def positions_from_pose_csv(poses_csv: Path, log: Path) -> dict[str, np.ndarray]:
    """A poses CSV (``mosaicmap poses`` or ``W/poses.csv``: x, y, theta, frame) -> {tile name:
    (x_px, y_px, theta_rad)}: tile-grid top-left corner in pixels and heading."""
    from pipeline.importers.tiles import tile_positions_from_poses

    images = [Path(r["image"]).name for r in read_csv(log / "frames.csv")]
    rows = read_csv(poses_csv)
    poses = np.array([[float(r[k]) for k in ("x", "y", "theta")] for r in rows])
    xy = tile_positions_from_poses(poses, TILE_SHAPE, PIXEL_SIZE)
    return {images[int(r["frame"])]: np.array([xy[i, 0], xy[i, 1], poses[i, 2]]) for i, r in enumerate(rows)}


@dataclass
class MapBuild:
    """The map of the other tiles: paths, our positions of its tiles, timings (s)."""

    log: Path
    repo: Path
    bundle: Path
    positions: dict[str, np.ndarray]
    seconds: dict[str, float] = field(default_factory=dict)


def build_map_without(tile: str, nominal: dict, out: Path, verbose: bool = True) -> MapBuild:
    """Import, build, publish and export (every level) a map of every tile but ``tile``."""
    out.mkdir(parents=True, exist_ok=True)
    cfg = out / "TileConfiguration.txt"
    write_tile_configuration(cfg, {n: p for n, p in nominal.items() if n != tile}, LSCM)
    log, work, repo, bundle = out / "log", out / "work", out / "repo", out / "map.zip"
    for p in (log, work, repo):
        shutil.rmtree(p, ignore_errors=True)
    bundle.unlink(missing_ok=True)
    s = {"import": mosaicmap("import-tiles", cfg, log, "--pixel-size", PIXEL_SIZE, "--quiet", verbose=verbose)}
    s["build"] = mosaicmap("build", log, "--map", repo, "-w", work, "--config", CONFIG, "--quiet", verbose=verbose)
    s["export"] = mosaicmap("export", repo, bundle, "--levels", "", "--config", CONFIG, "--quiet", verbose=verbose)
    mosaicmap("poses", repo, "--out", out / "poses.csv", verbose=verbose)
    return MapBuild(log, repo, bundle, positions_from_pose_csv(out / "poses.csv", log), s)


def build_full(out: Path, verbose: bool = True) -> tuple[Path, dict[str, np.ndarray]]:
    """Our positions of all 12 tiles: import + ``build --until optimize``."""
    log, work = out / "full_log", out / "full_work"
    for p in (log, work):
        shutil.rmtree(p, ignore_errors=True)
    mosaicmap("import-tiles", LSCM / "TileConfiguration.txt", log, "--pixel-size", PIXEL_SIZE, "--quiet",
              verbose=verbose)
    mosaicmap("build", log, "-w", work, "--until", "optimize", "--config", CONFIG, "--quiet", verbose=verbose)
    return log, positions_from_pose_csv(work / "poses.csv", log)


# --- the live frame ------------------------------------------------------------------------


def rectified_tile(log: Path, name: str) -> tuple[np.ndarray, np.ndarray]:
    """The tile ``name`` of drive log ``log`` as ingest rectifies it (grey conversion, flat
    field, Rectifier at the map pixel size with the configured interpolation and valid-mask
    erosion), rounded to uint8 grey levels for the tracker; and its valid mask."""
    from pipeline.camera import Rectifier
    from pipeline.config import load_config
    from pipeline.drivelog import read_drive_log
    from pipeline.images import read_grey
    from pipeline.stages.ingest import _flat_field

    cfg = load_config(CONFIG)
    lg = read_drive_log(log)
    i = [Path(p).name for p in lg.frame_images].index(name)
    raw = read_grey(lg.image_path(i))
    flat, _ = _flat_field(lg, raw.shape, cfg, 1)
    ing = cfg["ingest"]
    rect = Rectifier(lg.camera, raw.shape, cfg["map"]["pixel_size_m"], interpolation=ing["interpolation"],
                     erode_px=ing["valid_mask_erode_px"], flat_field=flat)
    img = rect(raw)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), rect.valid.copy()


def tile_world_pose(x_px: float, y_px: float, theta: float = 0.0) -> np.ndarray:
    """World pose (metres, radians) of a tile whose top-left corner is at tile-grid (x_px, y_px)."""
    from pipeline.importers.tiles import tile_pose

    p = tile_pose(x_px, y_px, TILE_SHAPE, PIXEL_SIZE)
    p[2] = theta
    return p


def fix_position(fix: Fix) -> np.ndarray:
    """A fix's pose -> (x_px, y_px, theta): tile-grid top-left corner and heading."""
    from pipeline.importers.tiles import tile_positions_from_poses

    xy = tile_positions_from_poses(fix.pose[None, :], TILE_SHAPE, PIXEL_SIZE)[0]
    return np.array([xy[0], xy[1], fix.pose[2]])


# --- alignment of position sets --------------------------------------------------------------


def fit_transform(src: np.ndarray, dst: np.ndarray, kind: str):
    """Least-squares map of 2-D points ``src`` -> ``dst`` (N, 2): ``shift``, ``rigid``
    (rotation + shift) or ``scale`` (per-axis scale + shift, as in bench_real). Returns
    (function of (M, 2) points, residual RMS px over the N, parameters dict)."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    if kind == "shift":
        t = (dst - src).mean(axis=0)
        f = lambda p: np.asarray(p, float) + t  # noqa: E731
        params = {"shift": t.tolist()}
    elif kind == "rigid":
        ms, md = src.mean(0), dst.mean(0)
        a, b = src - ms, dst - md
        th = float(np.arctan2(np.sum(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.sum(a * b)))
        r = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
        f = lambda p: (np.asarray(p, float) - ms) @ r.T + md  # noqa: E731
        params = {"rotation_mrad": th * 1e3}
    elif kind == "scale":
        coef = [np.linalg.lstsq(np.column_stack([src[:, k], np.ones(len(src))]), dst[:, k], rcond=None)[0]
                for k in range(2)]
        def f(p):
            p = np.asarray(p, float)
            return np.column_stack([p[:, k] * coef[k][0] + coef[k][1] for k in range(2)])

        params = {"scale_x_pct": 100 * (coef[0][0] - 1), "scale_y_pct": 100 * (coef[1][0] - 1)}
    else:
        raise ValueError(kind)
    rms = float(np.sqrt(np.mean(np.sum((f(src) - dst) ** 2, axis=1))))
    return f, rms, params


def _position_mrad(pose: np.ndarray) -> list[float]:
    """A world pose -> [x_px, y_px, theta_mrad] (tile-grid corner), rounded for printing."""
    p = fix_position(Fix(np.asarray(pose, float), np.eye(3), "ok"))
    return [round(float(p[0]), 2), round(float(p[1]), 2), round(float(p[2]) * 1e3, 2)]


# --- localization --------------------------------------------------------------------------


@dataclass
class Run:
    """One localization of the left-out tile."""

    label: str
    fix: Fix
    seconds: float
    warm_seconds: float = float("nan")
    extra: dict = field(default_factory=dict)


def timed_fix(tracker: FloorTracker, frame, prior, sigma, valid, repeats: int) -> tuple[Fix, float, float]:
    """The fix, its first (cold cache) time and the median of ``repeats`` more (s)."""
    t0 = time.perf_counter()
    fix = tracker.fix(frame, prior, sigma, valid)
    cold = time.perf_counter() - t0
    warm = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        tracker.fix(frame, prior, sigma, valid)
        warm.append(time.perf_counter() - t0)
    return fix, cold, float(np.median(warm)) if warm else float("nan")


def stage_error(nominal: dict, peer: dict, built: MapBuild, tile: str) -> dict:
    """The stage's error as the prior sees it (pixels): nominal minus the map's positions of
    the built tiles (the map's gauge is the nominal position of its first tile), and
    nominal minus Fiji's after aligning Fiji's first tile to the nominal one; the heading
    spread of the map's tiles (rad)."""
    names = [n for n in built.positions]
    nom = np.array([nominal[n] for n in names])
    ours = np.array([built.positions[n][:2] for n in names])
    d_map = np.hypot(*(nom - ours).T)
    first = next(iter(nominal))
    allnames = list(nominal)
    pr = np.array([peer[n] for n in allnames]) - np.array(peer[first]) + np.array(nominal[first])
    d_peer = np.hypot(*(np.array([nominal[n] for n in allnames]) - pr).T)
    th = np.array([built.positions[n][2] for n in names])
    return {"map_rms_px": float(np.sqrt(np.mean(d_map ** 2))), "map_max_px": float(d_map.max()),
            "peer_rms_px": float(np.sqrt(np.mean(d_peer ** 2))), "peer_max_px": float(d_peer.max()),
            "peer_tile_px": float(d_peer[allnames.index(tile)]),
            "theta_max_rad": float(np.abs(th).max())}


def prior_sigma_for(err: dict) -> np.ndarray:
    """1-sigma (m, m, rad) covering the measured stage error: half the largest position error
    seen (nominal vs the map, nominal vs Fiji), so the tracker's 3-sigma search radius covers
    1.5x the worst case; heading: twice the map tiles' largest |theta|, at least 2 mrad (the
    stage does not rotate)."""
    s_px = 0.5 * max(err["map_max_px"], err["peer_max_px"])
    return np.array([s_px * PIXEL_SIZE, s_px * PIXEL_SIZE, max(0.002, 2.0 * err["theta_max_rad"])])


def localize(tile: str, nominal: dict, peer: dict, built: MapBuild, full_positions: dict, full_log: Path,
             repeats: int = 10) -> dict:
    """Runs (a) and (b); prints and returns the figures."""
    frame, valid = rectified_tile(full_log, tile)
    err = stage_error(nominal, peer, built, tile)
    sigma = prior_sigma_for(err)
    prior = tile_world_pose(*nominal[tile])
    print(f"\nstage error (nominal - ours over the map's {len(built.positions)} tiles): "
          f"RMS {err['map_rms_px']:.2f} px, max {err['map_max_px']:.2f} px; nominal - Fiji (tile-0-aligned, "
          f"12 tiles): RMS {err['peer_rms_px']:.2f} px, "
          f"max {err['peer_max_px']:.2f} px ({short(tile)}: {err['peer_tile_px']:.2f} px); map tiles' |theta| <= "
          f"{err['theta_max_rad'] * 1e3:.2f} mrad")
    print(f"prior: nominal ({nominal[tile][0]:.1f}, {nominal[tile][1]:.1f}) px, sigma {sigma[0] / PIXEL_SIZE:.2f} px, "
          f"{sigma[2] * 1e3:.1f} mrad")

    runs: list[Run] = []
    index_info = {}
    with open_bundle(built.bundle, insecure=True) as tmap:  # an unsigned bench bundle
        default, plain = tmap.floor_tracker(PIXEL_SIZE), tmap.floor_tracker(PIXEL_SIZE, FLOOR_PARAMS)
        # (a) the nominal prior, tracker defaults and bench settings.
        for label, trk, reps in (("prior, tracker defaults", default, repeats),
                                 ("prior, bench params", plain, repeats)):
            f, cold, warm = timed_fix(trk, frame, prior, sigma, valid, reps)
            runs.append(Run(label, f, cold, warm))
        # (b) no prior: relocalization, the proposals verified by the tracker.
        for name, rp in RELOC_SETTINGS.items():
            t0 = time.perf_counter()
            index = build_index(tmap.tiles, tmap.grid, rp)
            t_index = time.perf_counter() - t0
            index_info[name] = {"features": len(index), "seconds": t_index}
            print(f"relocalization index ({name}): {len(index)} ORB features ({rp.features_per_tile} per "
                  f"{rp.tile_px} px tile) in {t_index:.2f} s; {rp.query_features} query features")
            for label, trk in ((f"no prior, reloc {name}, bench params", plain),):
                reloc = Relocalizer(index, trk, rp)
                t0 = time.perf_counter()
                props = reloc.proposals(frame, valid)
                t_prop = time.perf_counter() - t0
                f = reloc.locate(frame, valid)
                extra = {"proposals": [(_position_mrad(p), n) for p, n in props],
                         "proposal_seconds": t_prop}
                runs.append(Run(label, f, reloc.last_seconds, extra=extra))

    # Common frame: our map's tile grid. Fiji and the full build come in through the 11 tiles.
    common = [n for n in built.positions if n != tile]
    ours11 = np.array([built.positions[n][:2] for n in common])
    peer11 = np.array([peer[n] for n in common])
    full11 = np.array([full_positions[n][:2] for n in common])
    to_map = {}
    for kind in ("shift", "rigid", "scale"):
        fp, rms_p, par_p = fit_transform(peer11, ours11, kind)
        to_map[f"fiji_{kind}"] = (fp(np.array([peer[tile]]))[0], rms_p, par_p)
    ff, rms_f, par_f = fit_transform(full11, ours11, "rigid")
    full_xy = ff(full_positions[tile][None, :2])[0]
    print(f"\nframes aligned on the {len(common)} common tiles (residual RMS of the fit over them):")
    for kind in ("shift", "rigid", "scale"):
        xy, rms, par = to_map[f"fiji_{kind}"]
        par_text = json.dumps({k: np.round(v, 4).tolist() for k, v in par.items()})
        print(f"  Fiji -> map, {kind:<5}: RMS {rms:.2f} px {par_text}"
              f" -> {short(tile)} at ({xy[0]:.2f}, {xy[1]:.2f})")
    print(f"  full 12-tile build -> map, rigid: RMS {rms_f:.2f} px -> {short(tile)} at ({full_xy[0]:.2f}, "
          f"{full_xy[1]:.2f}), theta {full_positions[tile][2] * 1e3:.2f} mrad")

    print(f"\n{short(tile)}: x, y = tile-grid top-left corner (px), theta (mrad); d_* = fix minus Fiji (rigid / "
          "per-axis-scale alignment) and minus our full build")
    print(f"{'run':<55} {'status':<11} {'x':>8} {'y':>8} {'theta':>6} {'ncc':>5} {'uniq':>5} {'in/tpl':>6} "
          f"{'rms':>5} {'d_rigid':>7} {'d_scale':>7} {'d_full':>6} {'ms':>7} {'warm':>6}  reasons")
    out_runs = []
    for r in runs:
        f = r.fix
        pos = fix_position(f) if f.ok else np.full(3, np.nan)
        d_r = float(np.hypot(*(pos[:2] - to_map["fiji_rigid"][0])))
        d_s = float(np.hypot(*(pos[:2] - to_map["fiji_scale"][0])))
        d_f = float(np.hypot(*(pos[:2] - full_xy)))
        print(f"{r.label:<55} {f.status:<11} {pos[0]:8.2f} {pos[1]:8.2f} {pos[2] * 1e3:6.2f} {f.ncc:5.2f} "
              f"{f.uniqueness:5.2f} {f.inliers:>2}/{f.templates:<3} {f.rms_px:5.2f} {d_r:7.2f} {d_s:7.2f} {d_f:6.2f} "
              f"{r.seconds * 1e3:7.1f} {r.warm_seconds * 1e3:6.1f}  {f.reasons}")
        if "proposals" in r.extra:
            print(f"{'':<4}proposals (x px, y px, theta mrad; RANSAC inliers): {r.extra['proposals']} "
                  f"in {r.extra['proposal_seconds'] * 1e3:.0f} ms")
        out_runs.append({"label": r.label, "status": f.status, "x_px": pos[0], "y_px": pos[1], "theta_rad": pos[2],
                         "ncc": f.ncc, "uniqueness": f.uniqueness, "inliers": f.inliers, "templates": f.templates,
                         "rms_px": f.rms_px, "d_fiji_rigid_px": d_r, "d_fiji_scale_px": d_s, "d_full_px": d_f,
                         "seconds": r.seconds, "warm_seconds": r.warm_seconds, "reasons": f.reasons, **r.extra})
    peer_xy = np.array(peer[tile])
    print(f"Fiji's registered position (its own frame): ({peer_xy[0]:.2f}, {peer_xy[1]:.2f}); nominal "
          f"({nominal[tile][0]:.1f}, {nominal[tile][1]:.1f})")
    return {"tile": tile, "stage_error": err, "prior_sigma_px": sigma[0] / PIXEL_SIZE, "prior_sigma_rad": sigma[2],
            "coverage_fraction": runs[1].fix.coverage,
            "fiji_fit_rms_px": {k.split("_")[1]: v[1] for k, v in to_map.items()},
            "fiji_scale_params": to_map["fiji_scale"][2],
            "full_fit_rms_px": rms_f, "reloc_index": index_info,
            "map_seconds": built.seconds, "runs": out_runs}


def run_tile(tile: str, nominal: dict, peer: dict, full: tuple[Path, dict], out: Path, verbose: bool = True) -> dict:
    """Build the map without ``tile`` and localize it (see the module docstring)."""
    counts = neighbour_counts(nominal)
    print(f"\n=== left-out tile {short(tile)} ({tile}, {counts[tile]} neighbours) ===")
    built = build_map_without(tile, nominal, out / short(tile), verbose=verbose)
    return localize(tile, nominal, peer, built, full[1], full[0])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tile", help="tile to leave out (file name or short name, e.g. A007); default: the "
                                   "first tile with the most neighbours")
    ap.add_argument("--all", action="store_true", help="leave out every tile in turn")
    ap.add_argument("--out", type=Path, help="keep the logs, maps and bundles here (default: a temporary directory)")
    ap.add_argument("--bound-px", type=float, default=2.0,
                    help="an ok fix further than this from our full build's position is wrong (px; the "
                         "tracker's wrong-ok bound)")
    ap.add_argument("--json", type=Path, help="write the figures to this JSON file")
    args = ap.parse_args(argv)
    if not LSCM.exists():
        print(f"real data {LSCM} absent")
        return 2
    nominal = read_tiles(LSCM / "TileConfiguration.txt")
    peer = read_tiles(LSCM / "TileConfiguration.registered.txt")
    tiles = list(nominal) if args.all else [resolve_tile(nominal, args.tile) if args.tile else default_tile(nominal)]
    tmp = None
    out = args.out
    if out is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench_tracker_real_")
        out = Path(tmp.name)
    try:
        full = build_full(out)
        results = [run_tile(t, nominal, peer, full, out, verbose=not args.all or t == tiles[0]) for t in tiles]
    finally:
        if tmp is not None:
            tmp.cleanup()
    ok, n_ok = True, 0
    print("\nsummary: fixes with the bench params (d_* px, warm fix / locate ms); "
          "prior = nominal stage position, reloc = no prior (defaults / dense index)")
    print(f"{'tile':<6} {'nb':>2} {'prior':<11} {'d_rigid':>7} {'d_scale':>7} {'d_full':>6} {'ms':>5}  "
          f"{'reloc defaults':<14} {'d_full':>6} {'ms':>4}  {'reloc dense':<11} {'d_full':>6} {'ms':>4}")
    counts = neighbour_counts(nominal)
    for res in results:
        by = {r["label"]: r for r in res["runs"]}
        a = by["prior, bench params"]
        b = by["no prior, reloc defaults, bench params"]
        c = by["no prior, reloc dense, bench params"]
        print(f"{short(res['tile']):<6} {counts[res['tile']]:>2} {a['status']:<11} {a['d_fiji_rigid_px']:7.2f} "
              f"{a['d_fiji_scale_px']:7.2f} {a['d_full_px']:6.2f} {a['warm_seconds'] * 1e3:5.1f}  {b['status']:<14} "
              f"{b['d_full_px']:6.2f} {b['seconds'] * 1e3:4.0f}  {c['status']:<11} {c['d_full_px']:6.2f} "
              f"{c['seconds'] * 1e3:4.0f}")
        wrong = [r["label"] for r in res["runs"] if r["status"] == "ok" and not r["d_full_px"] <= args.bound_px]
        if wrong:
            print(f"       ok but more than {args.bound_px} px from our full build: {wrong}")
        ok &= not wrong
        n_ok += a["status"] == "ok"
    print(f"fixes from the prior ok: {n_ok} of {len(results)} tile(s); wrong ok: {'none' if ok else 'some (above)'}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, default=float))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
