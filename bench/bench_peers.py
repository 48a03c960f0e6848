"""Peers: mosaicmap's tile-grid registration against ASHLAR and m2stitch, back to back.

Synthetic grids (``mosaicmap simulate tiles``: known true positions, a nominal prior, a
uniform stage error of +-E px per tile and axis, noise and per-tile gain) and, with
``--real``, the two real microscope grids of ../shared/data/real (no truth: compared with
Fiji's ``TileConfiguration.registered.txt``). For every grid each tool gets the same
nominal prior and the same bound on the stage error, and runs in its own child process
(one after the other, never two at once), computing tile positions only (no mosaic is
written) into a file. Per tool and grid it prints the child's whole-process wall and CPU
seconds (interpreter start, imports, reading the tiles included; CPU = user + system of the
child and its waited-for descendants, from ``wait4``), its peak RSS (the child's own
``VmHWM``), the tiles placed, the error against the truth after the best translation
(least squares over the inliers: the mean offset of the non-blank placed tiles within
max(2 px, 3 x their median distance) of their median offset, so that a few lost tiles do
not shift all others): RMS and max of
the 2-D error, tiles above 1 px and above 0.5 px (blank tiles apart), and the wall-time
ratio mosaicmap / peer. A tool that fails, is missing or exceeds ``--timeout`` is reported
as such (with the last line of its error output), and the bench goes on.

The tools and how they get the prior and the bound (E = stage error in px; two neighbours'
offset is off the nominal step by up to 2 E):

- **mosaicmap**: ``mosaicmap import-tiles CONFIG LOG --pixel-size 0.001 --stage-error E``
  then ``mosaicmap build LOG -w W --until optimize --report R`` with the defaults.
  ``--stage-error`` states the bound: the log's prior becomes an absolute one (a stage's
  positions: each tile's nominal position within +-E px, not a chain of steps whose errors
  add up), and a pair's search radius is ``search_sigmas (3) x sigma + search_floor_px``
  with sigma = E / 2 for the offset of two tiles. Revisit pairs (column neighbours in row
  order) get radii from what links hold (docs/registration.md).
  Positions: W/poses.csv through :func:`pipeline.importers.tiles.tile_positions_from_poses`;
  a tile that ingest rejected has none. The build report's per-stage seconds and link
  counts are printed. ``--mosaicmap-config FILE`` merges overrides.
- **ASHLAR** (``ashlar.reg.EdgeAligner``, the library behind the ``ashlar`` command): a
  reader of our own over the tile files (``_AshlarReader`` in :func:`child_ashlar`: nominal positions in
  pixels, pixel size 1 um, one channel, RGB averaged to grey), ``max_shift = 2E`` (um =
  px), ``filter_sigma = 0`` and ``alpha = 0.01`` (its command's defaults), no thumbnail
  (only for aligning further cycles), then ``run()``; positions = ``aligner.positions``
  ((y, x) order). Importing ``ashlar.reg`` starts a Java VM through pyjnius (BioFormats),
  even though this reader never uses it: a JRE must be installed.
- **m2stitch** (a Python MIST): ``m2stitch.stitch_images(images, rows, cols,
  position_initial_guess=nominal (y, x), overlap_diff_threshold=100 x 2E / tile size,
  row_col_transpose=False)``: it takes the grid indices, the prior and a bound on each
  pair's offset from the prior in percent of the tile size; other options at their
  defaults. Its positions are whole pixels (MIST's integer hill climbing). The tiles are
  given as float32 minus their mean, plus 1: m2stitch 0.7.2's NCC divides by the norms of
  the raw overlaps (not mean-subtracted), so on tiles with an offset (any camera's) it
  stays far below its 0.5 threshold and fails with "there is no good top pair" (0.05 on
  the simulated 8-bit tiles); exactly zero-mean tiles make its phase correlation 0 / 0.

Real grids: the same runs with ``--real-error`` as E (15 px: the real sets' neighbour
steps are within about +-20 px of the nominal step). For each tool the distance to Fiji's
positions after the same translation fit (median and RMS over tiles). wsi_brain_16bit_9x7: only
its first 54 tiles (rows 0-5) are in the files; Fiji's positions of 0001, 0037 and 0054
(right-most column, rows 0, 4, 5: background tiles) are failures, so they are left out of
the fit and of the "trusted" figures and printed apart (flagged); the grid's interior
(not on its border) is reported separately too.

    python bench/bench_peers.py [--quick] [--grid 5x5 --tile 512 --overlap 0.1 --error 15]
        [--bits 16 --value-range 700,2011 --order snake --blank-count 2 --hot-pixels 5]
        [--tools mosaicmap,ashlar,m2stitch] [--timeout 600] [--out DIR [--reuse]] [--json FILE]
    python bench/bench_peers.py --real [--real-error 15]

Without grid flags the default set below runs (``--quick``: its first two). Any of
``--grid/--tile/--overlap/--error`` (each repeatable) replaces the set by the product of
the values given, the others at 5x5, 512, 0.1, 15. Peers install with ``pip install -e
'.[bench]'``. Figures on a busy machine are not comparable: the load average is printed at
the start and the end.
"""

from __future__ import annotations

import argparse
import csv
import importlib.util
import itertools
import json
import math
import os
import shlex
import shutil
import signal
import sys
import tempfile
import time
import tomllib
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from runner import REPO, child_env, reusable, run_cli  # noqa: E402

SHARED = REPO.parent / "shared" / "data" / "real"
PIXEL_SIZE = 0.001  # metres per tile pixel given to import-tiles (as bench_real.py)
TOOLS = ("mosaicmap", "ashlar", "m2stitch")
TOOL_MODULES = {"mosaicmap": "pipeline", "ashlar": "ashlar", "m2stitch": "m2stitch"}
REFERENCE = {"grid": "5x5", "tile": 512, "overlap": 0.1, "error": 15.0}
# (grid, tile px, overlap, stage error px); quick = the first two.
DEFAULT_SET = [
    ("5x5", 512, 0.10, 15.0),
    ("5x5", 1024, 0.03, 15.0),
    ("5x5", 1024, 0.10, 15.0),
    ("5x5", 1024, 0.10, 40.0),
    ("10x10", 512, 0.10, 15.0),
    ("10x10", 1024, 0.10, 40.0),
    ("10x10", 1024, 0.03, 15.0),
]
# A wsi_brain-like grid (16-bit using 1/50 of the range, snake order, blank and hot pixels)
# in the full set.
HARD = {"bits": 16, "value_range": "700,2011", "order": "snake", "blank_count": 2, "hot_pixels": 5}
WSI_FIJI_FAILURES = ("C3-BrainSection0001.tif", "C3-BrainSection0037.tif", "C3-BrainSection0054.tif")
INLIER_PX = 2.0  # translation fit: inliers within max(this, 3 x median distance) of the median offset
MIN_PAIR_OVERLAP_PX = 8  # a neighbour pair overlapping less than this (truth) is hardly registrable


# --- grids ---------------------------------------------------------------------------------


@dataclass
class Grid:
    """One tile grid to run every tool on (positions in pixels, top-left, x right, y down)."""

    name: str
    folder: Path  # tiles and the prior's TileConfiguration.txt
    config: Path  # the prior
    files: list[str]
    nominal: np.ndarray  # (N, 2)
    colrow: np.ndarray  # (N, 2) grid column, row
    tile_hw: tuple[int, int]
    error_px: float  # E
    truth: np.ndarray | None = None  # (N, 2) synthetic grids
    peer: np.ndarray | None = None  # (N, 2) Fiji's registered positions (real grids)
    blank: np.ndarray | None = None  # (N,) bool: tiles without content (excluded from the fit)
    flagged: list[str] = field(default_factory=list)  # peer failures (real grids)
    info: dict = field(default_factory=dict)


def _read_config(path: Path) -> tuple[list[str], np.ndarray]:
    from pipeline.importers.tiles import read_tile_configuration

    t = read_tile_configuration(path)
    return [n for n, _, _ in t], np.array([(x, y) for _, x, y in t], float)


def _colrow(nominal: np.ndarray) -> np.ndarray:
    """Grid (column, row) of nominal positions: steps = median gap between distinct values."""
    out = np.zeros(nominal.shape, int)
    for k in range(2):
        v = nominal[:, k]
        u = np.unique(np.round(v, 3))
        gaps = np.diff(u)
        gaps = gaps[gaps > 1.0]
        step = float(np.median(gaps)) if gaps.size else 1.0
        out[:, k] = np.rint((v - v.min()) / step).astype(int)
    return out


def synthetic_cases(args) -> list[dict]:
    picked = any(getattr(args, k) for k in ("grid", "tile", "overlap", "error"))
    if picked:
        combos = itertools.product(args.grid or [REFERENCE["grid"]], args.tile or [REFERENCE["tile"]],
                                   args.overlap or [REFERENCE["overlap"]], args.error or [REFERENCE["error"]])
        cases = [dict(grid=g, tile=t, overlap=o, error=e) for g, t, o, e in combos]
    else:
        sel = DEFAULT_SET[:2] if args.quick else DEFAULT_SET
        cases = [dict(grid=g, tile=t, overlap=o, error=e) for g, t, o, e in sel]
        if not args.quick:
            cases.append(dict(grid="5x5", tile=512, overlap=0.1, error=15.0, **HARD))
    extras = {k: getattr(args, k) for k in ("bits", "value_range", "order", "blank_count", "hot_pixels",
                                             "noise", "gain", "seed")}
    for c in cases:
        for k, v in extras.items():
            if v is not None:
                c[k] = v
    return cases


def case_name(c: dict) -> str:
    s = f"{c['grid']} {c['tile']}px {100 * c['overlap']:g}% +-{c['error']:g}px"
    for k, fmt in (("bits", "{}bit"), ("value_range", "[{}]"), ("order", "{}"), ("blank_count", "{} blank"),
                   ("hot_pixels", "{} hot"), ("noise", "noise {}"), ("gain", "gain {}"), ("seed", "seed {}")):
        if c.get(k) is not None:
            s += " " + fmt.format(c[k])
    return s


def make_synthetic(c: dict, data: Path, reuse: bool) -> Grid:
    """Simulate (or reuse) the grid of case ``c`` under ``data``."""
    folder = data / ("sim_" + "_".join(f"{k}{v}" for k, v in sorted(c.items())).replace(",", "-").replace(" ", ""))
    marker = folder.with_name(folder.name + ".params.json")
    if not reusable(marker, c, reuse):
        shutil.rmtree(folder, ignore_errors=True)
        opts = ["--grid", c["grid"], "--tile", str(c["tile"]), "--overlap", str(c["overlap"]),
                "--stage-error", str(c["error"])]
        for k, flag in (("bits", "--bits"), ("value_range", "--value-range"), ("order", "--order"),
                        ("blank_count", "--blank-count"), ("hot_pixels", "--hot-pixels"), ("noise", "--noise"),
                        ("gain", "--gain"), ("seed", "--seed")):
            if c.get(k) is not None:
                opts += [flag, str(c[k])]
        t0 = time.perf_counter()
        run_cli("simulate", "tiles", folder, *opts, "--quiet")
        marker.write_text(json.dumps({"params": c, "seconds": time.perf_counter() - t0}))
    meta = json.loads((folder / "grid.json").read_text())
    files, nominal = _read_config(folder / "TileConfiguration.txt")
    tfiles, truth = _read_config(folder / "TileConfiguration.truth.txt")
    assert tfiles == files
    by_file = {t["file"]: t for t in meta["tiles"]}
    w, h = meta["tile_size"]
    g = Grid(case_name(c), folder, folder / "TileConfiguration.txt", files, nominal,
             np.array([(by_file[f]["col"], by_file[f]["row"]) for f in files]), (h, w), float(c["error"]),
             truth=truth, blank=np.array([by_file[f]["blank"] for f in files]))
    g.info = {"overlap_px": meta["overlap_px"], "step_px": meta["step_px"], "bits": meta["bits"],
              "value_range": meta["value_range"], "order": meta["order"], "blank_tiles": meta["blank_tiles"],
              "hot_pixels": meta["hot_pixels"], "noise_sigma": meta["noise_sigma"], "gain": meta["gain"],
              "min_true_pair_overlap_px": _min_pair_overlap(g.colrow, truth, (h, w))}
    return g


def _pairs(colrow: np.ndarray) -> list[tuple[int, int]]:
    """Grid-neighbour pairs (i, j): right and down neighbours."""
    at = {(int(c), int(r)): i for i, (c, r) in enumerate(colrow)}
    out = []
    for i, (c, r) in enumerate(colrow):
        for dc, dr in ((1, 0), (0, 1)):
            j = at.get((int(c) + dc, int(r) + dr))
            if j is not None:
                out.append((i, j))
    return out


def _min_pair_overlap(colrow: np.ndarray, pos: np.ndarray, hw: tuple[int, int]) -> list:
    """Per neighbour pair the overlap (px) along its step axis at ``pos``: [min, count < MIN]."""
    h, w = hw
    ov = []
    for i, j in _pairs(colrow):
        d = np.abs(pos[j] - pos[i])
        horizontal = colrow[j, 0] != colrow[i, 0]
        ov.append((w - d[0]) if horizontal else (h - d[1]))
    ov = np.array(ov)
    return [float(ov.min()), int((ov < MIN_PAIR_OVERLAP_PX).sum())]


def real_grids(error_px: float) -> list[Grid]:
    out = []
    for name in ("lscm_speckle_3x4", "wsi_brain_16bit_9x7"):
        d = SHARED / name
        if not d.exists():
            print(f"real data absent: {d}")
            continue
        files, nominal = _read_config(d / "TileConfiguration.txt")
        pfiles, ppos = _read_config(d / "TileConfiguration.registered.txt")
        pmap = dict(zip(pfiles, ppos))
        peer = np.array([pmap[f] for f in files])
        import tifffile

        shape = tifffile.imread(d / files[0]).shape[:2]
        g = Grid(name, d, d / "TileConfiguration.txt", files, nominal, _colrow(nominal), shape, error_px,
                 peer=peer, blank=np.zeros(len(files), bool))
        if name.startswith("wsi"):
            g.flagged = [f for f in WSI_FIJI_FAILURES if f in files]
        out.append(g)
    return out


# --- children: one tool, one grid ----------------------------------------------------------


def _load_grey(path: Path) -> np.ndarray:
    """A tile as a 2-D array in its stored type (RGB/RGBA averaged to grey in that type)."""
    import tifffile

    img = tifffile.imread(path)
    if img.ndim == 3:
        if img.shape[-1] in (3, 4):
            img = img[..., :3]
            img = np.rint(img.mean(axis=-1)).astype(img.dtype)
        else:
            img = img[0]
    return img


def child_mosaicmap(spec: dict) -> dict:
    from pipeline.cli import cli
    from pipeline.importers.tiles import tile_positions_from_poses

    work = Path(spec["work"])
    log, wd, report = work / "log", work / "w", work / "report.json"
    rc = cli.main(["import-tiles", spec["config"], str(log), "--pixel-size", str(PIXEL_SIZE),
                   "--stage-error", str(spec["bound_px"] / 2.0), "--quiet"],
                  prog_name="mosaicmap", standalone_mode=False)
    if rc:
        raise SystemExit(f"import-tiles exit code {rc}")
    rc = cli.main(["build", str(log), "-w", str(wd), "--until", "optimize", "--config", spec["mosaicmap_config"],
                   "--report", str(report), "--quiet"], prog_name="mosaicmap", standalone_mode=False)
    if rc:
        raise SystemExit(f"build exit code {rc}")
    with open(log / "frames.csv", newline="") as f:
        images = [Path(r["image"]).name for r in csv.DictReader(f)]
    with open(wd / "poses.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    poses = np.array([[float(r[k]) for k in ("t", "x", "y", "theta")] for r in rows])
    frames = [int(r["frame"]) for r in rows]
    h, w = spec["tile_hw"]
    xy = tile_positions_from_poses(poses, (h, w), PIXEL_SIZE) if len(poses) else np.zeros((0, 2))
    index = {f: i for i, f in enumerate(spec["files"])}
    pos = [None] * len(spec["files"])
    for fr, p in zip(frames, xy):
        pos[index[images[fr]]] = [float(p[0]), float(p[1])]
    rep = json.loads(report.read_text())
    return {"positions": pos, "stages": {k: v.get("seconds") for k, v in rep.get("stages", {}).items()},
            "links": rep.get("links", {})}


def child_ashlar(spec: dict) -> dict:
    import ashlar.reg as reg  # starts a Java VM (pyjnius + BioFormats) at import

    folder = Path(spec["folder"])
    nominal = np.array(spec["nominal"], float)
    first = _load_grey(folder / spec["files"][0])

    class Meta(reg.Metadata):
        """Nominal positions in pixels (pixel size 1 um), (y, x) order as ASHLAR's."""

        @property
        def _num_images(self):
            return len(spec["files"])

        @property
        def num_channels(self):
            return 1

        @property
        def pixel_size(self):
            return 1.0

        @property
        def pixel_dtype(self):
            return first.dtype

        def tile_position(self, i):
            return nominal[i, ::-1].copy()

        def tile_size(self, i):
            return np.array(first.shape[:2])

    class _AshlarReader(reg.Reader):
        def __init__(self):
            self.metadata = Meta()

        def read(self, series, c):
            return _load_grey(folder / spec["files"][series])

    aligner = reg.EdgeAligner(_AshlarReader(), channel=0, max_shift=spec["bound_px"], alpha=0.01,
                              filter_sigma=0.0, do_make_thumbnail=False, verbose=False)
    aligner.run()
    yx = np.asarray(aligner.positions, float)
    errors = np.array([e for _, e in aligner._cache.values()])
    return {"positions": yx[:, ::-1].tolist(),
            "pairs": int(len(errors)), "pairs_accepted": int(np.isfinite(errors).sum()),
            "max_error": float(aligner.max_error)}


def child_m2stitch(spec: dict) -> dict:
    import m2stitch

    folder = Path(spec["folder"])
    # float32 minus each tile's mean, plus 1: m2stitch 0.7.2's NCC divides by the norms of
    # the raw overlaps (not mean-subtracted), so with the values' offset it stays far below its
    # 0.5 threshold ("there is no good top pair"); the +1 keeps the DC term of its phase
    # correlation non-zero (0 / 0 there makes the whole correlation NaN).
    images = np.stack([_load_grey(folder / f).astype(np.float32) for f in spec["files"]])
    images -= images.mean(axis=(1, 2), keepdims=True) - np.float32(1.0)
    nominal = np.array(spec["nominal"], float)
    colrow = np.array(spec["colrow"], int)
    h, w = images.shape[1:]
    thr = min(100.0, 100.0 * spec["bound_px"] / min(h, w))
    grid, prop = m2stitch.stitch_images(images, rows=colrow[:, 1].tolist(), cols=colrow[:, 0].tolist(),
                                        position_initial_guess=nominal[:, ::-1], overlap_diff_threshold=thr,
                                        row_col_transpose=False)
    pos = np.stack([grid["x_pos"].to_numpy(float), grid["y_pos"].to_numpy(float)], axis=1)
    return {"positions": pos.tolist(), "overlap_diff_threshold_percent": thr,
            "repeatability": float(prop.get("repeatability", float("nan")))}


CHILDREN = {"mosaicmap": child_mosaicmap, "ashlar": child_ashlar, "m2stitch": child_m2stitch}


def child_main(spec_path: str) -> int:
    from peak_memory import hwm_kb

    spec = json.loads(Path(spec_path).read_text())
    result = CHILDREN[spec["tool"]](spec)
    Path(spec["out"]).write_text(json.dumps(result))
    print(json.dumps({"hwm_mb": hwm_kb() / 1024.0}))
    return 0


# --- the parent: timing a child ------------------------------------------------------------


def timed_child(spec: dict, work: Path, timeout: float) -> dict:
    """Run one tool in a child process; wall and CPU seconds, peak RSS, its result or failure."""
    spec_path = work / "spec.json"
    spec_path.write_text(json.dumps(spec))
    out_f, err_f = open(work / "stdout.txt", "w"), open(work / "stderr.txt", "w")
    import subprocess

    t0 = time.perf_counter()
    p = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--child", str(spec_path)],
                         stdout=out_f, stderr=err_f, cwd=REPO, env=child_env(), start_new_session=True)
    timed_out = False
    while True:
        pid, status, ru = os.wait4(p.pid, os.WNOHANG)
        if pid == p.pid:
            break
        if time.perf_counter() - t0 > timeout:
            timed_out = True
            os.killpg(p.pid, signal.SIGKILL)  # the child's own session (start_new_session)
            pid, status, ru = os.wait4(p.pid, 0)
            break
        time.sleep(0.02)
    wall = time.perf_counter() - t0
    p.returncode = os.waitstatus_to_exitcode(status)
    out_f.close()
    err_f.close()
    res = {"wall_s": wall, "cpu_s": ru.ru_utime + ru.ru_stime, "rss_mb": ru.ru_maxrss / 1024.0,
           "rss_source": "ru_maxrss", "exit": p.returncode}
    stdout = (work / "stdout.txt").read_text()
    for line in reversed(stdout.strip().splitlines()):
        try:
            res["rss_mb"] = float(json.loads(line)["hwm_mb"])
            res["rss_source"] = "VmHWM"
            break
        except (ValueError, KeyError, TypeError):
            continue
    if timed_out:
        res["status"] = f"timeout ({timeout:g} s)"
    elif p.returncode != 0 or not Path(spec["out"]).exists():
        tail = [ln for ln in (work / "stderr.txt").read_text().strip().splitlines() if ln.strip()]
        res["status"] = "failed"
        res["reason"] = (tail[-1] if tail else f"exit code {p.returncode}")[:300]
    else:
        res["status"] = "ok"
        res.update(json.loads(Path(spec["out"]).read_text()))
    return res


# --- figures -------------------------------------------------------------------------------


def _placed(pos_list, n: int) -> tuple[np.ndarray, np.ndarray]:
    pos = np.full((n, 2), np.nan)
    for i, p in enumerate(pos_list or []):
        if p is not None:
            pos[i] = p
    return pos, np.isfinite(pos).all(axis=1)


def best_translation(ref: np.ndarray, pos: np.ndarray, fit: np.ndarray) -> np.ndarray:
    """The translation ``pos - ref`` fitted over ``fit`` tiles: the least-squares (mean)
    offset of the inliers, the tiles within max(``INLIER_PX``, 3 x their median distance)
    of the per-axis median offset, so that a few failed tiles do not move every other one
    while errors spread over all tiles (a prior's, a scale's) all count."""
    d = pos[fit] - ref[fit]
    med = np.median(d, axis=0)
    dist = np.hypot(*(d - med).T)
    near = dist <= max(INLIER_PX, 3.0 * float(np.median(dist)))
    return d[near].mean(axis=0)


def error_vs(ref: np.ndarray, pos: np.ndarray, fit: np.ndarray, report: np.ndarray) -> dict:
    """Errors of ``pos`` against ``ref`` after :func:`best_translation` over ``fit`` tiles,
    evaluated over ``report`` tiles (both boolean masks)."""
    if not fit.any():
        return {"n": 0}
    shift = best_translation(ref, pos, fit)
    e = np.hypot(*(pos - shift - ref).T)
    er = e[report]
    if er.size == 0:
        return {"n": 0}
    return {"n": int(er.size), "rms": float(np.sqrt(np.mean(er**2))), "median": float(np.median(er)),
            "max": float(er.max()), "over_1": int((er > 1.0).sum()), "over_05": int((er > 0.5).sum()),
            "per_tile": e}


def _fmt(v, spec=".3f", none="-"):
    return none if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, spec)


def figures_synthetic(g: Grid, res: dict) -> dict:
    n = len(g.files)
    pos, ok = _placed(res.get("positions"), n)
    content = ~g.blank
    f = {"placed": int(ok.sum()), "tiles": n}
    e = error_vs(g.truth, pos, ok & content, ok & content)
    e.pop("per_tile", None)
    f.update(e)
    if g.blank.any():
        eb = error_vs(g.truth, pos, ok & content, ok & g.blank)
        f["blank_max"] = eb.get("max")
    return f


def figures_real(g: Grid, res: dict | None, pos: np.ndarray | None = None) -> dict:
    n = len(g.files)
    if pos is None:
        pos, ok = _placed(res.get("positions"), n)
    else:
        ok = np.isfinite(pos).all(axis=1)
    flagged = np.array([f in g.flagged for f in g.files])
    trusted = ok & ~flagged
    f = {"placed": int(ok.sum()), "tiles": n}
    e = error_vs(g.peer, pos, trusted, trusted)
    per = e.pop("per_tile", None)
    f["trusted"] = e
    if flagged.any() and per is not None:
        f["flagged"] = {name: _fmt(float(per[i]), ".1f") if ok[i] else "-" for i, name in enumerate(g.files)
                        if flagged[i]}
        c, r = g.colrow[:, 0], g.colrow[:, 1]
        interior = (c > c.min()) & (c < c.max()) & (r > r.min()) & (r < r.max())
        ei = error_vs(g.peer, pos, trusted & interior, trusted & interior)
        ei.pop("per_tile", None)
        f["interior"] = ei
    return f


# --- main ----------------------------------------------------------------------------------


def _toml_merge(base: dict, extra: dict) -> dict:
    for k, v in extra.items():
        if isinstance(v, dict) and isinstance(base.get(k), dict):
            _toml_merge(base[k], v)
        else:
            base[k] = v
    return base


def mosaicmap_override(error_px: float, extra: Path | None, path: Path) -> Path:
    from pipeline.config import dump_toml

    cfg: dict = {}
    if extra is not None:
        with open(extra, "rb") as f:
            cfg = _toml_merge(cfg, tomllib.load(f))
    path.write_text(dump_toml(cfg))
    return path


def run_grid(g: Grid, tools: list[str], work: Path, args) -> dict:
    out: dict = {}
    for tool in tools:
        if importlib.util.find_spec(TOOL_MODULES[tool]) is None:
            out[tool] = {"status": "not installed (pip install -e '.[bench]')"}
            print(f"  {tool:<9} not installed", flush=True)
            continue
        tw = work / tool
        shutil.rmtree(tw, ignore_errors=True)  # a build resumes from a kept work dir: always fresh
        tw.mkdir(parents=True)
        spec = {"tool": tool, "folder": str(g.folder), "config": str(g.config), "files": g.files,
                "nominal": g.nominal.tolist(), "colrow": g.colrow.tolist(), "tile_hw": list(g.tile_hw),
                "bound_px": 2.0 * g.error_px, "out": str(tw / "positions.json"), "work": str(tw),
                "mosaicmap_config": str(mosaicmap_override(g.error_px, args.mosaicmap_config, tw / "override.toml"))}
        r = timed_child(spec, tw, args.timeout)
        out[tool] = r
        line = f"  {tool:<9} {r['status']:<8} wall {r['wall_s']:7.1f} s  CPU {r['cpu_s']:7.1f} s  RSS {r['rss_mb']:6.0f} MB"
        if r.get("reason"):
            line += f"  ({r['reason']})"
        print(line, flush=True)
        if tool == "mosaicmap" and r["status"] == "ok":
            st = r.get("stages", {})
            print("            build stages: " + ", ".join(f"{k} {_fmt(v, '.1f')} s" for k, v in st.items())
                  + "; links: " + ", ".join(f"{k} {v}" for k, v in r.get("links", {}).items()), flush=True)
        if tool == "ashlar" and r["status"] == "ok":
            print(f"            pairs {r['pairs']}, accepted {r['pairs_accepted']} (error threshold "
                  f"{r['max_error']:.3f})", flush=True)
    return out


def _ratio(mm: dict, r: dict, tool: str) -> str:
    """mosaicmap's wall (CPU) seconds over the peer's, when both ran."""
    if tool == "mosaicmap" or mm.get("status") != "ok" or r.get("status") != "ok":
        return "-"
    return f"{mm['wall_s'] / r['wall_s']:.2f} ({mm['cpu_s'] / max(r['cpu_s'], 1e-9):.2f})"


def print_synthetic_table(rows: list[tuple[Grid, dict]]) -> None:
    print("\n| grid | tool | status | wall s | CPU s | peak RSS MB | placed | RMS px | max px | > 1 px | > 0.5 px "
          "| mosaicmap / tool: wall (CPU) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for g, res in rows:
        mm = res.get("mosaicmap", {})
        for tool, r in res.items():
            if "wall_s" not in r:
                print(f"| {g.name} | {tool} | {r['status']} | | | | | | | | | |")
                continue
            f = figures_synthetic(g, r) if r["status"] == "ok" else {}
            r["figures"] = f
            ratio = _ratio(mm, r, tool)
            blank = f" (blank max {_fmt(f.get('blank_max'), '.1f')})" if f.get("blank_max") is not None else ""
            print(f"| {g.name} | {tool} | {r['status']} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | {r['rss_mb']:.0f} | "
                  f"{f.get('placed', '-')}/{len(g.files)} | {_fmt(f.get('rms'))} | {_fmt(f.get('max'))}{blank} | "
                  f"{f.get('over_1', '-')} | {f.get('over_05', '-')} | {ratio} |")


def print_real_table(rows: list[tuple[Grid, dict]]) -> None:
    print("\n| grid | tool | status | wall s | CPU s | peak RSS MB | placed | vs Fiji: median / RMS px, tiles > 1 px "
          "| interior: median / RMS px | flagged (Fiji failures) px | mosaicmap / tool: wall (CPU) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for g, res in rows:
        nom = figures_real(g, None, pos=g.nominal.copy())
        _real_row(g, "nominal prior", None, nom, "-")
        mm = res.get("mosaicmap", {})
        for tool, r in res.items():
            if "wall_s" not in r:
                print(f"| {g.name} | {tool} | {r['status']} | | | | | | | | |")
                continue
            f = figures_real(g, r) if r["status"] == "ok" else {}
            r["figures"] = {k: v for k, v in f.items()}
            _real_row(g, tool, r, f, _ratio(mm, r, tool))


def _real_row(g: Grid, tool: str, r: dict | None, f: dict, ratio) -> None:
    t = f.get("trusted", {})
    i = f.get("interior", {})
    fl = ", ".join(f"{k.split('Section')[-1].split('.')[0]} {v}" for k, v in f.get("flagged", {}).items())
    timing = (f"{r['status']} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | {r['rss_mb']:.0f}" if r else "- | | | ")
    inter = f"{_fmt(i.get('median'), '.2f')} / {_fmt(i.get('rms'), '.2f')}" if i else "-"
    print(f"| {g.name} | {tool} | {timing} | {f.get('placed', '-')}/{len(g.files)} | "
          f"{_fmt(t.get('median'), '.2f')} / {_fmt(t.get('rms'), '.2f')}, {t.get('over_1', '-')} | {inter} | "
          f"{fl or '-'} | {ratio} |")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="the first two grids of the default set")
    ap.add_argument("--grid", action="append", help="COLSxROWS (repeatable)")
    ap.add_argument("--tile", action="append", type=int, help="tile size px (repeatable)")
    ap.add_argument("--overlap", action="append", type=float, help="overlap fraction (repeatable)")
    ap.add_argument("--error", action="append", type=float, help="stage error E px (repeatable)")
    ap.add_argument("--bits", type=int, help="8 or 16 (synthetic grids)")
    ap.add_argument("--value-range", help="LO,HI stored values of grey 0 and 255")
    ap.add_argument("--order", choices=("row", "snake"))
    ap.add_argument("--blank-count", type=int)
    ap.add_argument("--hot-pixels", type=int)
    ap.add_argument("--noise", type=float, help="noise sigma, grey levels (default: the simulator's)")
    ap.add_argument("--gain", type=float, help="per-tile gain spread (default: the simulator's)")
    ap.add_argument("--seed", type=int)
    ap.add_argument("--real", action="store_true", help="the real grids instead of synthetic ones")
    ap.add_argument("--real-error", type=float, default=15.0, help="stage error bound E (px) for the real grids")
    ap.add_argument("--tools", default=",".join(TOOLS), help="comma-separated subset of " + ",".join(TOOLS))
    ap.add_argument("--timeout", type=float, default=600.0, help="seconds per tool run")
    ap.add_argument("--mosaicmap-config", type=Path, help="further overrides merged into mosaicmap's config")
    ap.add_argument("--out", type=Path, help="keep grids and work directories here (default: a temp dir)")
    ap.add_argument("--reuse", action="store_true", help="reuse simulated grids kept in --out")
    ap.add_argument("--json", type=Path, help="write the figures here")
    args = ap.parse_args()
    if args.mosaicmap_config is not None:
        try:
            with open(args.mosaicmap_config, "rb") as f:
                tomllib.load(f)
        except (OSError, tomllib.TOMLDecodeError) as e:
            ap.error(f"--mosaicmap-config {args.mosaicmap_config}: {e}")
    tools = [t.strip() for t in args.tools.split(",") if t.strip()]
    bad = [t for t in tools if t not in TOOLS]
    if bad:
        ap.error(f"unknown tool {bad[0]!r} (known: {', '.join(TOOLS)})")

    print(f"bench_peers {datetime.now(timezone.utc).isoformat(timespec='seconds')}, "
          f"{os.cpu_count()} cores, load average {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    print("$ " + shlex.join([Path(sys.executable).name, *sys.argv]))
    versions = {}
    for t in tools:
        try:
            from importlib.metadata import version

            versions[t] = version({"mosaicmap": "mosaicmap", "ashlar": "ashlar", "m2stitch": "m2stitch"}[t])
        except Exception:
            versions[t] = "not installed"
    print("tools: " + ", ".join(f"{k} {v}" for k, v in versions.items()))

    root = args.out or Path(tempfile.mkdtemp(prefix="bench_peers_"))
    root.mkdir(parents=True, exist_ok=True)
    results: list[tuple[Grid, dict]] = []
    try:
        if args.real:
            grids = real_grids(args.real_error)
        else:
            grids = []
            for c in synthetic_cases(args):
                try:
                    grids.append(make_synthetic(c, root / "data", args.reuse))
                except RuntimeError as e:  # bad simulator options: say so, go on with the others
                    print(f"\n== {case_name(c)}: simulation failed, skipped: {str(e).strip().splitlines()[-1]}")
        for k, g in enumerate(grids):
            print(f"\n== {g.name}: {len(g.files)} tiles of {g.tile_hw[1]} x {g.tile_hw[0]} px, E = {g.error_px:g} px "
                  f"(bound 2E = {2 * g.error_px:g} px per pair), {g.folder}", flush=True)
            if g.info:
                print(f"   step {g.info['step_px']} px, overlap {g.info['overlap_px']} px, {g.info['bits']}-bit "
                      f"{g.info['value_range']}, {g.info['order']} order, noise {g.info['noise_sigma']:g}, gain "
                      f"+-{g.info['gain']:g}, blank {g.info['blank_tiles']}, hot pixels {g.info['hot_pixels']}; "
                      f"true neighbour overlap min {g.info['min_true_pair_overlap_px'][0]:.1f} px, "
                      f"{g.info['min_true_pair_overlap_px'][1]} pairs below {MIN_PAIR_OVERLAP_PX} px", flush=True)
            print(f"   mosaicmap: --stage-error {g.error_px:g} (pair search radius ~ 3 x {g.error_px / 2:g} + floor px)",
                  flush=True)
            results.append((g, run_grid(g, tools, root / "work" / f"grid{k}", args)))
    finally:
        if args.out is None:
            shutil.rmtree(root, ignore_errors=True)
    if args.real:
        print_real_table(results)
    else:
        print_synthetic_table(results)
    print(f"\nload average at the end: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    if args.json:
        dump = [{"grid": g.name, "folder": str(g.folder), "tiles": len(g.files), "info": g.info,
                 "tools": {t: {k: v for k, v in r.items() if k != "positions"} for t, r in res.items()}}
                for g, res in results]
        args.json.write_text(json.dumps(dump, indent=1, default=str))
    return 0


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--child":
        sys.exit(child_main(sys.argv[2]))
    sys.exit(main())
