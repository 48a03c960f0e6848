"""Stage ``orp``: route panoramas (ORP, Yagi et al. (2005)) from the omni logs' horizon lines.

Input: the horizon files ingest writes per omni log, ``WORKDIR/ingest/horizons/<k:03d>.npz``
(``lines`` (N, A) float32 grey levels, ``t`` (N,) s, ``frame`` (N,) row in frames.csv,
``odometry`` (N, 3) dead-reckoned x, y, theta at the frame times, ``meta`` JSON with
``log_id, path, sha256, route_id, samples_per_degree, horizon_band_deg, oversample, camera``).
The files are grouped by route id (``[orp] default_route_id`` when a log has none); per route:

1. *Reference*: the first run (ingest order); over a published map holding the route, the
   stored route (its poses fixed, its row spacing kept whatever ``[orp] spacing_m`` says now;
   the runs must be sampled at its ``samples_per_degree`` and ``horizon_band_deg``, else
   BadInput). A run driving less than ``2 x coarse_spacing_m`` is skipped with a warning
   (``runs_skipped``); the reference or only run that short is BadInput.
2. *Registration* (:mod:`pipeline.orp_register`): each other run against the reference,
   coarse (along-track offset and heading by correlating horizon lines) then fine (every
   ``decimate_m`` of path a frame localized on the reference's ORP with
   :class:`tracker.orp.ORPLocalizer`, gated); a run that ends near its start also has its last
   ``loop_window_m`` registered to its first (loop closure).
3. *GTSAM* (:func:`pipeline.stages.optimize.optimize_over_map`, the floor's optimizer): one
   Pose2 per kept frame; odometry factors with the ``[optimize]`` error model; each accepted
   fix a robust BetweenFactor from the reference frame nearest its path position to the run's
   frame (fixes on a stored route: links from the fixed map node); gauge as the floor build:
   the reference run's first frame at its odometry pose, every other run loosely at its
   odometry start, so a floor map and a route built from the same logs share the world frame.
4. *Merge*: one ORP at ``spacing_m`` along the optimized reference path
   (:func:`tracker.orp.build_orp` geometry; over a stored route its rows and poses); then
   *extension* (``[orp] extend``, :func:`route_extension`): at each end, the linked run that
   continues farthest beyond it (passing within ``extend_tolerance_m`` of the end pose, the
   same way) adds its rows there (its optimized poses, its lines scaled to the end row); then
   the other runs' lines, rolled to the reference heading, gain/offset-normalized to the
   reference row, are averaged in where they pass within ``lateral_tolerance_m`` of the
   (extended) path. Stored rows keep their poses and path lengths (rows prepended on a refresh
   get negative path lengths: ``s0_m`` may be < 0); a first build starts at ``s0_m = 0``. A
   row no run fed (frames more than ``merge_max_gap_m`` apart) takes the reference's line
   interpolated across the gap (counted: ``rows_interpolated``, a warning above 5 %).

Output: ``WORKDIR/orp/<route_id>.npz`` (``lines`` uint8 (M, A), ``poses`` float32 (M, 3) world
frame, ``s0_m``, ``spacing_m``, ``samples_per_degree``, ``horizon_band_deg``, ``meta`` JSON:
sources, runs, registration, figures) and ``WORKDIR/orp/runs.csv`` (per kept frame: route,
run, frame, optimized pose). Ground truth (``ground_truth.csv`` of every log) is read for the
report's figures only.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from mapstore.grid import se2_between, wrap_angle
from mapstore.routes import RouteRecord, check_route_id
from pipeline.errors import BadInput
from pipeline.links import Link
from pipeline.orp_register import (
    Coarse,
    Fix,
    coarse_register,
    interpolate_corrections,
    keep_every,
    localize_run,
    match_rows,
    path_pose_at,
    project_on_path,
    resample_rows,
    roll_lines,
    route_pose_at,
    signatures,
)
from pipeline.stages.stage import Stage, StageParams
from pipeline.stages.workspace import Workspace
from tracker.orp import ORP, ORPLocalizer, ORPParams, build_orp, path_length

log = logging.getLogger(__name__)

# The GTSAM optimizer (pipeline.optimize.optimize_poses) states link residuals and its
# odometry-gate messages in "pixels" of a size it is given; routes have no map pixel, so it
# is given 1 mm: its residuals and messages read in millimetres. It weights nothing (the
# factors' noise is [orp] fix_sigma_m / [optimize]'s odometry model, in metres).
RESIDUAL_UNIT_M = 0.001
# A route whose rows filled by interpolation across frame gaps (rows_interpolated) exceed
# this share of its rows is reported in the log as a warning.
INTERPOLATED_WARN_FRACTION = 0.05


@dataclass(eq=False)
class Run:
    """One omni log's horizon lines (the horizon lines file contract) and what the stage derives.

    Attributes:
        k: the log's number in the ingest (file ``<k:03d>.npz``).
        lines: (N, A) float32 grey levels; t: (N,) frame times (s); frame: (N,) rows in frames.csv.
        odometry: (N, 3) dead-reckoned poses at the frame times (metres, radians, odometry frame).
        meta: the file's metadata (log_id, path, sha256, route_id, sampling, camera).
        s: (N,) odometry path length (metres); kept: indices of the frames in the graph.
        dead_reckoning: the file's odometry when ``odometry`` was replaced by the floor
            build's optimized poses (:func:`floor_priors`), else None.
    """

    k: int
    lines: np.ndarray
    t: np.ndarray
    frame: np.ndarray
    odometry: np.ndarray
    meta: dict
    s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    kept: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    dead_reckoning: np.ndarray | None = None

    @property
    def log_id(self) -> str:
        return str(self.meta.get("log_id", f"log{self.k:03d}"))


def read_runs(ws: Workspace) -> list[Run]:
    """Every horizon file of the ingest (``ws.horizons_dir``: ``<k:03d>.npz``, read and
    checked by :func:`pipeline.omni_ingest.read_horizons`), in log order (empty when no log
    is omni)."""
    from pipeline.omni_ingest import read_horizons

    d = ws.horizons_dir
    runs = []
    for path in sorted(d.glob("[0-9][0-9][0-9].npz")) if d.is_dir() else []:
        h = read_horizons(path)
        runs.append(Run(int(path.stem), np.asarray(h["lines"], np.float32), np.asarray(h["t"], np.float64),
                        np.asarray(h["frame"], np.int64), np.asarray(h["odometry"], np.float64), h["meta"]))
    return runs


def floor_priors(ws: Workspace, runs: list[Run]) -> int:
    """Replace each run's odometry by the floor build's optimized poses of the same frames
    (``WORKDIR/optimize/poses.csv``: rows ``log_id, frame``), frames the floor store dropped
    or the optimize stage dropped (``optimize/dropped.csv``, :mod:`pipeline.geometry_gate`)
    carried by their odometry (:func:`pipeline.orp_register.interpolate_corrections`); the
    dead-reckoned poses are kept as ``Run.dead_reckoning``.
    Returns the runs changed (0 when the build has no floor poses)."""
    from pipeline.stages.optimize import read_poses_table

    path = ws.poses
    if not path.is_file():
        return 0
    from pipeline.geometry_gate import dropped_mask

    data = read_poses_table(path)
    data = data[~dropped_mask(ws.dropped, len(data))]  # a wild prior: carried like the rest
    ids = np.asarray([str(v) for v in data["log_id"]])
    changed = 0
    for r in runs:
        sel = ids == r.log_id
        if not sel.any():
            continue
        where = {int(f): i for i, f in enumerate(r.frame.tolist())}
        rows = [(where[int(f)], j) for j, f in zip(np.flatnonzero(sel), data["frame"][sel]) if int(f) in where]
        if len(rows) < 2:
            continue
        rows.sort()
        idx = np.array([a for a, _ in rows])
        opt = np.column_stack([data["x"], data["y"], data["theta"]])[[b for _, b in rows]]
        r.dead_reckoning = r.odometry
        r.odometry = interpolate_corrections(r.odometry, idx, opt)
        changed += 1
    return changed


def route_of(run: Run, cfg_orp: dict) -> str:
    rid = run.meta.get("route_id") or cfg_orp["default_route_id"]
    try:
        return check_route_id(str(rid))
    except ValueError as e:
        raise BadInput(run.meta.get("path", f"log {run.k}"), f"[route] id: {e}") from None


def orp_params(cfg: dict) -> ORPParams:
    """The localizer's parameters: ``[tracker.orp]`` with the build's row spacing."""
    return ORPParams.from_dict({**cfg["tracker"]["orp"], "spacing_m": cfg["orp"]["spacing_m"]})


def _fix_link(a: int, b: int, rel: np.ndarray, fix: Fix, cfg_orp: dict) -> Link:
    sm, sr = float(cfg_orp["fix_sigma_m"]), float(cfg_orp["fix_sigma_rad"])
    return Link(a, b, np.asarray(rel, float), np.diag([sm**2, sm**2, sr**2]), fix.ncc, 0.0, fix.valid_fraction,
                0, "orp")


def _register(ref_orp: ORP, run_lines: np.ndarray, run_odo: np.ndarray, run_s: np.ndarray, kept: np.ndarray,
              params: ORPParams, cfg_orp: dict, loc: ORPLocalizer | None = None) -> tuple[Coarse, list[Fix]]:
    """Coarse then fine registration of a run's kept frames (indices ``kept`` into its lines
    ``(N, A)``, odometry ``(N, 3)`` and path lengths ``(N,)``) on the reference ``ref_orp``
    (``loc``: its localizer, when already made)."""
    spd = params.samples_per_degree
    cs = float(cfg_orp["coarse_spacing_m"])
    ref_c = build_orp(ref_orp.lines.astype(np.float32), ref_orp.poses, cs, spd)
    run_c = build_orp(run_lines, run_odo, cs, spd)
    # the run's first coarse_window_m only: the prior of the first fix (tracking carries the
    # rest), and a run whose path length differs from the reference's (driven offset around
    # curves) keeps its along-track offset there
    run_c.lines = run_c.lines[: max(2, int(round(float(cfg_orp["coarse_window_m"]) / cs)) + 1)]
    hc = int(cfg_orp["highpass_cycles"])
    coarse = coarse_register(signatures(ref_c.lines, hc), signatures(run_c.lines, hc), ref_c.lines.shape[1], cs,
                             float(cfg_orp["max_offset_m"]))
    coarse.offset_m += ref_orp.s0  # both coarse ORPs start at s = 0 at their first frame
    if coarse.ncc < float(cfg_orp["coarse_min_ncc"]):
        return coarse, []
    loc = loc or ORPLocalizer(ref_orp, params)
    fixes = localize_run(loc, run_lines[kept], run_odo[kept], run_s[kept] - run_s[0], coarse,
                         min_ncc=float(cfg_orp["fix_min_ncc"]), min_valid=float(cfg_orp["fix_min_valid"]),
                         gate_m=float(cfg_orp["fix_gate_m"]), gate_rad=math.radians(float(cfg_orp["fix_gate_deg"])),
                         reset_m=float(cfg_orp["reset_m"]))
    return coarse, fixes


def _nearest_kept(s_kept: np.ndarray, s: float) -> int:
    return int(np.argmin(np.abs(s_kept - s)))


def _loop_closure(run: Run, params: ORPParams, cfg_orp: dict) -> list[tuple[int, int, np.ndarray, np.ndarray, float, float]]:
    """Loop closures of a run that ends within ``loop_max_gap_m`` of its start (odometry):
    ``(kept index a, kept index b, rel (3,), cov (3, 3) in a's axes, ncc, valid fraction)``.

    Two kinds: (1) the frames of its last ``loop_window_m`` localized on the ORP of its first
    ``loop_window_m`` (:func:`_register`; only where the run drove past its start: eq. 5 needs
    the route on both sides of a pose); (2) the junction: its last frame matched against the
    rows of that ORP by correlation alone (:func:`pipeline.orp_register.match_rows`): along-track
    position and heading, lateral left loose (``loop_sigma_lateral_m``), so a loop that ends
    where it began still closes in heading and along the path.
    """
    w = float(cfg_orp["loop_window_m"])
    odo, s = run.odometry, run.s
    if s[-1] < 3.0 * w or math.hypot(*(odo[-1, :2] - odo[0, :2])) > float(cfg_orp["loop_max_gap_m"]):
        return []
    first = np.flatnonzero(s <= w)
    last = np.flatnonzero(s >= s[-1] - w)
    if len(first) < 3 or len(last) < 3:
        return []
    kept_last = np.asarray([i for i in run.kept if i >= last[0]], int) - last[0]
    first_orp = build_orp(run.lines[first], odo[first], params.spacing_m, params.samples_per_degree)
    coarse, fixes = _register(first_orp, run.lines[last], odo[last], s[last], kept_last, params, cfg_orp)
    s_kept = s[run.kept]
    sm, sr = float(cfg_orp["fix_sigma_m"]), float(cfg_orp["fix_sigma_rad"])
    out = []
    for f in fixes:
        if not f.accepted:
            continue
        ja = _nearest_kept(s_kept, f.s)
        if s_kept[ja] > w:
            continue
        jb = int(np.searchsorted(run.kept, last[0] + kept_last[f.index]))
        out.append((ja, jb, se2_between(odo[run.kept[ja]], f.pose), np.diag([sm**2, sm**2, sr**2]), f.ncc,
                    f.valid_fraction))
    m = match_rows(first_orp, run.lines[-1], int(cfg_orp["highpass_cycles"]))
    if m.ncc >= float(cfg_orp["loop_min_ncc"]):
        est = route_pose_at(first_orp, m.s)
        est[2] = wrap_angle(est[2] + m.dtheta)
        ja = _nearest_kept(s_kept, m.s)
        along = float(cfg_orp["loop_sigma_along_m"]) if m.interior else max(float(cfg_orp["loop_sigma_along_m"]),
                                                                              params.spacing_m)
        cov = np.diag([along**2, float(cfg_orp["loop_sigma_lateral_m"]) ** 2,
                       math.radians(float(cfg_orp["loop_sigma_deg"])) ** 2])
        out.append((ja, len(run.kept) - 1, se2_between(odo[run.kept[ja]], est), cov, m.ncc, 1.0))
    return out


def _ground_truth(run: Run) -> np.ndarray | None:
    from pipeline.evaluate import ground_truth_at

    p = Path(str(run.meta.get("path", ""))) / "ground_truth.csv"
    return ground_truth_at(run.t, p) if p.is_file() else None


def _gt_figures(est: list[np.ndarray], gt: list[np.ndarray]) -> dict:
    """Route pose errors after one rigid alignment (metres, degrees)."""
    from pipeline.evaluate import align_se2

    e, g = np.vstack(est), np.vstack(gt)
    r, t = align_se2(e[:, :2], g[:, :2])
    d = np.linalg.norm(e[:, :2] @ r.T + t - g[:, :2], axis=1)
    rot = math.atan2(r[1, 0], r[0, 0])
    h = np.degrees(wrap_angle(e[:, 2] + rot - g[:, 2]))
    return {"pose_rms_m": float(np.sqrt(np.mean(d**2))), "pose_max_m": float(d.max()),
            "heading_rms_deg": float(np.sqrt(np.mean(h**2)))}


def _check_stored_sampling(route_id: str, runs: list[Run], stored: RouteRecord) -> None:
    """A refresh needs the runs' horizon lines sampled as the stored route's: else one line
    :class:`BadInput` naming the ``[tracker.orp]`` key and both values."""
    for key in ("samples_per_degree", "horizon_band_deg"):
        want = float(getattr(stored, key))
        for r in runs:
            have = float(r.meta.get(key, want))
            if abs(have - want) > 1e-9:
                raise BadInput(f"route {route_id}", f"[tracker.orp] {key}: the stored route has {want:g}, the horizon "
                               f"lines of {r.log_id} have {have:g}: ingest with {key} = {want:g} to refresh it")


def _drop_short_runs(route_id: str, runs: list[Run], cfg_orp: dict, stored: RouteRecord | None) -> list[dict]:
    """Remove from ``runs`` (in place) the runs that drive less than ``2 x [orp]
    coarse_spacing_m`` (metres of odometry path: too short for the coarse registration) and
    return ``{"log_id", "path_m", "reason"}`` per run removed. The reference run (a first
    build's first) or the only run left: :class:`BadInput` naming its log."""
    min_m = 2.0 * float(cfg_orp["coarse_spacing_m"])
    skipped = []
    for i, r in enumerate(list(runs)):
        length = float(r.s[-1]) if len(r.s) else 0.0
        if length >= min_m:
            continue
        what = (f"drives {length:.3f} m: too short for a route panorama (at least 2 x [orp] coarse_spacing_m "
                f"= {min_m:g} m)")
        if (stored is None and i == 0) or len(runs) == 1:
            raise BadInput(r.meta.get("path", r.log_id), f"{what}; route {route_id}")
        log.warning("orp %s: %s %s: skipped", route_id, r.log_id, what)
        runs.remove(r)
        skipped.append({"log_id": r.log_id, "path_m": length, "reason": what})
    return skipped


def build_route(route_id: str, runs: list[Run], cfg: dict, stored: RouteRecord | None = None) -> dict:
    """Register, optimize and merge the runs of one route (module docstring). Returns
    ``{"record": RouteRecord (version 0; the new runs' sources with version None),
    "figures": the report's per-route figures, "kept_poses": [(run, optimized poses (K, 3) of
    its kept frames, world frame)]}``.

    A refresh (``stored`` given) keeps the stored route's row spacing (``[orp] spacing_m``
    applies to first builds only) and needs the runs sampled as it was (else
    :class:`BadInput`). Runs shorter than ``2 x [orp] coarse_spacing_m`` are skipped with a
    warning (``figures["skipped"]``); the reference or only run that short is
    :class:`BadInput`; a run whose registration fails (``ValueError``) is left out of the
    merge like one that does not register."""
    from pipeline.stages.optimize import optimize_over_map

    cfg_orp = cfg["orp"]
    params = orp_params(cfg)
    spd = params.samples_per_degree
    runs = list(runs)
    for r in runs:
        r.s = path_length(r.odometry)
        r.kept = keep_every(r.s, float(cfg_orp["decimate_m"]))
        if abs(float(r.meta.get("samples_per_degree", spd)) - spd) > 1e-9 or r.lines.shape[1] != round(360 * spd):
            raise BadInput(r.meta.get("path", f"log {r.k}"), f"horizon lines sampled at {r.meta.get('samples_per_degree')}"
                           f" samples/degree, [tracker.orp] says {spd:g}: rerun ingest")
    if stored is not None:
        _check_stored_sampling(route_id, runs, stored)
        params = replace(params, spacing_m=float(stored.spacing_m))  # the stored rows' spacing, not [orp]'s
    skipped = _drop_short_runs(route_id, runs, cfg_orp, stored)
    # --- the reference ---
    if stored is not None:
        ref_orp = ORP.from_record(stored)
        registered = list(runs)
    else:
        ref = runs[0]
        ref_orp = build_orp(ref.lines, ref.odometry, params.spacing_m, spd)
        registered = runs[1:]
    loc = ORPLocalizer(ref_orp, params)
    offsets = np.cumsum([0] + [len(r.kept) for r in runs])
    links: list[Link] = []
    map_links: list[Link] = []
    reg_info = []
    linked: list[Run] = []  # runs with accepted fixes: the others stay out of the merge
    tried = accepted = 0
    nccs = []
    for r in registered:
        error = None
        try:
            coarse, fixes = _register(ref_orp, r.lines, r.odometry, r.s, r.kept, params, cfg_orp, loc=loc)
        except ValueError as e:  # e.g. too little overlap with the reference for the coarse search
            error = str(e)
            log.warning("orp %s: %s could not be registered (%s): left out of the merge", route_id, r.log_id, e)
            coarse, fixes = Coarse(0.0, 0.0, -1.0, 0), []
        idx = runs.index(r)
        n_ok = 0
        for f in fixes:
            tried += 1
            if not f.accepted:
                continue
            accepted += 1
            n_ok += 1
            nccs.append(f.ncc)
            b = int(offsets[idx] + f.index)
            if stored is not None:
                map_links.append(_fix_link(0, b, f.pose, f, cfg_orp))
            else:
                s_kept = runs[0].s[runs[0].kept]
                ja = _nearest_kept(s_kept, f.s)
                rel = se2_between(runs[0].odometry[runs[0].kept[ja]], f.pose)
                links.append(_fix_link(int(offsets[0] + ja), b, rel, f, cfg_orp))
        if n_ok:
            linked.append(r)
        reg_info.append({"log_id": r.log_id, "coarse_offset_m": coarse.offset_m,
                         "coarse_heading_deg": math.degrees(coarse.dtheta), "coarse_ncc": coarse.ncc,
                         "fixes_tried": len(fixes), "fixes_accepted": n_ok, **({"error": error} if error else {})})
        if not n_ok and error is None:
            log.warning("orp %s: %s did not register to the reference (coarse NCC %.2f, no accepted fix): "
                        "left out of the merge", route_id, r.log_id, coarse.ncc)
    loops = 0
    for idx, r in enumerate(runs):
        for ja, jb, rel, cov, ncc, valid in _loop_closure(r, params, cfg_orp):
            links.append(Link(int(offsets[idx] + ja), int(offsets[idx] + jb), np.asarray(rel, float), cov, ncc, 0.0,
                              valid, 0, "orp-loop"))
            loops += 1
    # --- GTSAM ---
    cfg_opt = dict(cfg["optimize"])
    cfg_opt.update(pose_model="pose2", robust_kernel=cfg_orp["robust_kernel"],
                   robust_kernel_k=float(cfg_orp["robust_kernel_k"]), marginals_max_frames=0)
    if cfg_opt["robust_kernel"] == "none" or any(k <= cfg_opt["robust_kernel_k"] for k in cfg_opt["robust_anneal_k"]):
        cfg_opt["robust_anneal_k"] = []
    priors = [r.odometry[r.kept] for r in runs]
    res = optimize_over_map(priors, links, map_links, cfg_opt, RESIDUAL_UNIT_M)
    kept_poses = [res.poses[offsets[i]:offsets[i + 1]] for i in range(len(runs))]
    all_links = res.links
    rejected_opt = sum(lk.status != "accepted" for lk in all_links)
    full = [interpolate_corrections(r.odometry, r.kept, kp) for r, kp in zip(runs, kept_poses)]
    # --- merge ---
    orp_lines, orp_poses, s0, fed, extensions, n_interp = _merge(runs, full, ref_orp if stored is not None else None,
                                                                 stored, params, cfg_orp, linked)
    if n_interp > INTERPOLATED_WARN_FRACTION * len(orp_lines):
        log.warning("orp %s: %d of %d rows (%.0f %%) had no frames within [orp] merge_max_gap_m = %g m: interpolated "
                    "from the reference's farther frames", route_id, n_interp, len(orp_lines),
                    100.0 * n_interp / max(len(orp_lines), 1), float(cfg_orp["merge_max_gap_m"]))
    extended = {side: params.spacing_m * sum(len(x.lines) for x in extensions if x.side == side)
                for side in ("start", "end")}
    sources = [{"log_id": r.log_id, "path": r.meta.get("path"), "sha256": r.meta.get("sha256"),
                "frames": int(len(r.lines)), "version": None} for r in runs]
    if stored is not None:
        sources = [dict(s) for s in stored.sources] + sources
    figures = {
        "runs": len(runs), "rows": int(len(orp_lines)), "length_m": float(params.spacing_m * max(len(orp_lines) - 1, 0)),
        "registration": {"fixes_tried": tried, "fixes_accepted": accepted,
                         "fixes_rejected_optimizer": int(rejected_opt),
                         "ncc_median": float(np.median(nccs)) if nccs else None, "loop_closures": loops,
                         "reference": "stored route" if stored is not None else runs[0].log_id,
                         "runs": reg_info},
        "rows_fed": fed,
        "rows_interpolated": int(n_interp),
        "skipped": skipped,
        "extended_m": extended,
        "extensions": [x.summary() for x in extensions],
        "optimization": {"frames": int(res.poses.shape[0]), "seconds": res.seconds, "iterations": res.iterations},
    }
    gts = [_ground_truth(r) for r in runs]
    if all(g is not None for g in gts):
        figures["ground_truth"] = _gt_figures([kp for kp in kept_poses], [g[r.kept] for g, r in zip(gts, runs)])
        figures["ground_truth"]["odometry_rms_m"] = _gt_figures(
            [(r.odometry if r.dead_reckoning is None else r.dead_reckoning)[r.kept] for r in runs],
                                                                [g[r.kept] for g, r in zip(gts, runs)])["pose_rms_m"]
    band = float(stored.horizon_band_deg) if stored is not None else params.horizon_band_deg
    record = RouteRecord(orp_lines, orp_poses, s0, params.spacing_m, spd, band, 0, sources,
                         {"runs": len(runs) + (int(stored.meta.get("runs", 1)) if stored is not None else 0),
                          "registration": {k: v for k, v in figures["registration"].items() if k != "runs"}})
    return {"record": record, "figures": figures, "kept_poses": list(zip(runs, kept_poses))}


@dataclass(eq=False)
class Extension:
    """Rows a run adds beyond one end of a route (:func:`route_extension`).

    Attributes:
        side: ``"start"`` (rows prepended) or ``"end"`` (rows appended).
        run: the run they come from.
        lines: ``(K, A)`` float64 grey levels, scaled by the gain/offset fitting the run's line
            at the junction to the route's end row; ordered by increasing route path length.
        poses: ``(K, 3)`` the run's optimized poses at the rows (metres, radians, world frame).
        used: ``(N,)`` bool: the run's frames between the junction and the last row (left out
            of the averaging pass, their lines are the rows).
        gap_m: distance (metres) of the run's path from the route's end pose at the junction;
            heading_deg: the run's heading there minus the end pose's (degrees); ncc: the
            junction lines' correlation.
    """

    side: str
    run: Run
    lines: np.ndarray
    poses: np.ndarray
    used: np.ndarray
    gap_m: float
    heading_deg: float
    ncc: float

    def summary(self) -> dict:
        return {"side": self.side, "log_id": self.run.log_id, "rows": int(len(self.lines)),
                "gap_m": self.gap_m, "heading_deg": self.heading_deg, "ncc": self.ncc}


def _gain_offset(line: np.ndarray, ref: np.ndarray) -> tuple[float, float, float]:
    """Least-squares ``(gain, offset, ncc)`` with ``gain * line + offset ~ ref`` (``(A,)`` each)."""
    a, b = line - line.mean(), ref - ref.mean()
    var = float((a * a).sum())
    gain = float((a * b).sum()) / max(var, 1e-9)
    ncc = float((a * b).sum()) / math.sqrt(max(var * float((b * b).sum()), 1e-18))
    return gain, float(ref.mean() - gain * line.mean()), ncc


def _distance_to_path(path: np.ndarray, s_path: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(s (N,), distance (N,))``: the foot points' path lengths of positions ``xy (N, 2)``
    on the polyline ``path (M, 3)`` (vertices at ``s_path``) and their distances (metres;
    beyond an end, the distance to that end, not only its lateral part)."""
    s, _, _ = project_on_path(path, s_path, xy)
    fx, fy = np.interp(s, s_path, path[:, 0]), np.interp(s, s_path, path[:, 1])
    return s, np.hypot(xy[:, 0] - fx, xy[:, 1] - fy)


def route_extension(side: str, path: np.ndarray, s_path: np.ndarray, end_line: np.ndarray, full: np.ndarray,
                    lines: np.ndarray, spacing_m: float, cfg_orp: dict) -> Extension | None:
    """The rows a run adds beyond the ``side`` end of a route, or None.

    ``path (M, 3)``: the route poses (metres, radians, world frame) at path lengths
    ``s_path (M,)``; ``end_line (A,)``: the route's row at that end; ``full (N, 3)``: the
    run's optimized poses, ``lines (N, A)`` its horizon lines. The junction is the point of
    the run's path nearest the end pose: within ``extend_tolerance_m``, heading within
    ``extend_max_heading_deg``, travelling the route's way, lines correlating at
    ``merge_min_ncc``. Rows every ``spacing_m`` of the run's path beyond it, until its frames
    are more than ``merge_max_gap_m`` apart, it ends, or it comes back within
    ``lateral_tolerance_m`` of the route farther than ``extend_margin_m`` from that end.
    ``Extension.run`` is left None (the caller sets it)."""
    tol = float(cfg_orp["extend_tolerance_m"])
    end, nxt = (path[-1], path[-2]) if side == "end" else (path[0], path[1])
    s_r = path_length(full)
    inc = np.concatenate([[True], np.diff(s_r) > 1e-6])
    s_i, f_i, l_i = s_r[inc], np.asarray(full, float)[inc], np.asarray(lines, np.float64)[inc]
    if len(s_i) < 2:
        return None
    s_a = float(project_on_path(f_i, s_i, end[None, :2])[0][0])
    p_a = path_pose_at(f_i, s_i, s_a)
    gap = float(np.hypot(*(p_a[:2] - end[:2])))
    dh = float(wrap_angle(p_a[2] - end[2]))
    if gap > tol or abs(dh) > math.radians(float(cfg_orp["extend_max_heading_deg"])):
        return None
    sign = 1.0 if side == "end" else -1.0
    t_route = sign * (end[:2] - nxt[:2])
    q = path_pose_at(f_i, s_i, np.array([s_a - spacing_m, s_a + spacing_m]))
    if float(np.dot(t_route, q[1, :2] - q[0, :2])) <= 0.0:
        return None  # the run drives the other way
    room = (s_i[-1] - s_a) if side == "end" else (s_a - s_i[0])
    k = np.arange(1, int(math.floor(room / spacing_m + 1e-9)) + 1)
    if not len(k):
        return None
    s_k = s_a + sign * spacing_m * k
    poses = path_pose_at(f_i, s_i, s_k)
    vals, ok = resample_rows(s_i, l_i, s_k, float(cfg_orp["merge_max_gap_m"]))
    sp, dist = _distance_to_path(path, s_path, poses[:, :2])
    margin = float(cfg_orp["extend_margin_m"])
    far = (sp < s_path[-1] - margin) if side == "end" else (sp > s_path[0] + margin)
    stop = ~ok | ((dist <= float(cfg_orp["lateral_tolerance_m"])) & far)
    n = int(np.argmax(stop)) if stop.any() else len(k)
    if n * spacing_m < float(cfg_orp["extend_min_m"]) - 1e-9:
        return None
    line_a = resample_rows(s_i, l_i, np.array([s_a]), np.inf)[0]
    gain, offset, ncc = _gain_offset(roll_lines(line_a, np.array([dh]))[0], np.asarray(end_line, np.float64))
    if ncc < float(cfg_orp["merge_min_ncc"]) or gain <= 0.0:
        return None
    vals, poses = gain * vals[:n] + offset, poses[:n]
    lo, hi = (s_a, s_a + n * spacing_m) if side == "end" else (s_a - n * spacing_m, s_a)
    used = (s_r >= lo - 1e-9) & (s_r <= hi + 1e-9)
    if side == "start":
        vals, poses = vals[::-1], poses[::-1]
    return Extension(side, None, vals, poses, used, gap, math.degrees(dh), ncc)


def _merge(runs: list[Run], full: list[np.ndarray], stored_orp: ORP | None, stored: RouteRecord | None,
           params: ORPParams, cfg_orp: dict, linked: list[Run]) -> tuple[np.ndarray, np.ndarray, float, dict, list, int]:
    """The merged route: (lines uint8 (M, A), poses float32 (M, 3), s0 (metres), rows fed per
    log, the :class:`Extension` s applied, rows interpolated).

    Rows are ``spacing_m`` apart: the stored route's on a refresh, ``params.spacing_m`` on a
    first build. A row no run fed (its frames more than ``merge_max_gap_m`` apart, e.g. 15 cm
    at 1.5 m/s and 10 Hz) takes the reference's line interpolated between its frames around
    it however far apart (the stored line on a refresh with ``stored_weight = 0``); their
    number is the last value returned.

    The base rows (the stored route's, or the reference run's on its optimized path) are
    extended at each end by the linked run reaching farthest beyond it
    (:func:`route_extension`; ``[orp] extend``), then every other linked run's lines are
    averaged in where they pass within ``lateral_tolerance_m`` of the (extended) path. On a
    refresh the stored rows keep their path lengths (``s0`` goes below the stored one, maybe
    below 0, by the rows prepended); a first build starts at ``s0 = 0``."""
    gap = float(cfg_orp["merge_max_gap_m"])
    if stored_orp is not None:
        geo = stored_orp
        h = float(stored_orp.spacing_m)  # a refresh keeps the stored rows' spacing
        base = stored.lines.astype(np.float64)
        fallback = base.copy()
        acc = base * float(cfg_orp["stored_weight"])
        cnt = np.full(len(base), float(cfg_orp["stored_weight"]))
        merged = list(runs)
        fed = {"stored": int(len(base))}
    else:
        ref = runs[0]
        h = float(params.spacing_m)
        geo = build_orp(ref.lines, full[0], h, params.samples_per_degree)
        s_ref = path_length(full[0])
        inc = np.concatenate([[True], np.diff(s_ref) > 1e-6])
        base, ok = resample_rows(s_ref[inc], ref.lines[inc].astype(np.float64), geo.s, gap)
        fallback = resample_rows(s_ref[inc], ref.lines[inc].astype(np.float64), geo.s, np.inf)[0]
        ok[0] = ok[-1] = True
        acc, cnt = base * ok[:, None], ok.astype(np.float64)
        merged = runs[1:]
        fed = {ref.log_id: int(ok.sum())}
    path = geo.poses.astype(np.float64)
    s0 = float(geo.s0)
    s_path = s0 + h * np.arange(len(path))
    applied: list[Extension] = []
    used: dict[int, np.ndarray] = {}
    if cfg_orp["extend"] and len(path) >= 2:
        end_lines = {"end": _current(acc, cnt, fallback)[-1], "start": _current(acc, cnt, fallback)[0]}
        for side in ("end", "start"):  # the start sees the end's rows (a loop closing on them)
            best = None
            for r in merged:
                if r not in linked:
                    continue
                i = runs.index(r)
                x = route_extension(side, path, s_path, end_lines[side], full[i], r.lines, h, cfg_orp)
                if x is not None and (best is None or len(x.lines) > len(best.lines)):
                    x.run, best = r, x
            if best is None:
                continue
            n = len(best.lines)
            if side == "end":
                path, acc, cnt = np.vstack([path, best.poses]), np.vstack([acc, best.lines]), np.r_[cnt, np.ones(n)]
                fallback = np.vstack([fallback, best.lines])
            else:
                path, acc, cnt = np.vstack([best.poses, path]), np.vstack([best.lines, acc]), np.r_[np.ones(n), cnt]
                fallback = np.vstack([best.lines, fallback])
                s0 -= n * h
            s_path = s0 + h * np.arange(len(path))
            applied.append(best)
            k = runs.index(best.run)
            used[k] = used.get(k, np.zeros(len(best.used), bool)) | best.used
            fed[best.run.log_id] = fed.get(best.run.log_id, 0) + n
    tol, min_ncc = float(cfg_orp["lateral_tolerance_m"]), float(cfg_orp["merge_min_ncc"])
    for r in merged:
        i = runs.index(r)
        if r not in linked:
            continue
        s, lat, th = project_on_path(path, s_path, full[i][:, :2])
        near = (np.abs(lat) <= tol) & (s > s_path[0]) & (s < s_path[-1])
        if i in used:
            near &= ~used[i]
        rolled = roll_lines(r.lines, wrap_angle(full[i][:, 2] - th))
        ref_at = resample_rows(s_path, _current(acc, cnt, fallback), s, np.inf)[0]
        # gain/offset to the reference row (least squares), and the correlation it reaches
        mr, mo = rolled.mean(1, keepdims=True), ref_at.mean(1, keepdims=True)
        a_, b_ = rolled - mr, ref_at - mo
        var = (a_ * a_).sum(1)
        gain = (a_ * b_).sum(1) / np.maximum(var, 1e-9)
        ncc = (a_ * b_).sum(1) / np.sqrt(np.maximum(var * (b_ * b_).sum(1), 1e-18))
        normed = gain[:, None] * a_ + mo
        use = near & (ncc >= min_ncc) & (gain > 0)
        order = np.argsort(s[use], kind="stable")
        su, lu = s[use][order], normed[use][order]
        inc = np.concatenate([[True], np.diff(su) > 1e-6]) if len(su) else np.zeros(0, bool)
        vals, ok = resample_rows(su[inc], lu[inc], s_path, gap)
        acc[ok] += vals[ok]
        cnt[ok] += 1.0
        fed[r.log_id] = fed.get(r.log_id, 0) + int(ok.sum())
    lines = np.clip(np.rint(_current(acc, cnt, fallback)), 0, 255).astype(np.uint8)
    if stored_orp is None:
        s0 = 0.0  # a first build's rows start at path length 0
    return lines, path.astype(np.float32), float(s0), fed, applied, int((cnt <= 0).sum())


def _current(acc: np.ndarray, cnt: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """The merged rows so far ``(M, A)``: the average ``acc / cnt`` where a run fed the row
    (``cnt > 0``), else ``fallback`` (the reference's line interpolated without a gap limit)."""
    return np.where((cnt > 0)[:, None], acc / np.maximum(cnt, 1e-9)[:, None], fallback)


def write_route_file(path: Path, record: RouteRecord, figures: dict) -> None:
    """``<route_id>.npz`` of the stage (the record and its figures as JSON)."""
    meta = {"sources": record.sources, "meta": record.meta, "figures": figures}
    np.savez(path, lines=record.lines, poses=record.poses, s0_m=np.float64(record.s0_m),
             spacing_m=np.float64(record.spacing_m), samples_per_degree=np.float64(record.samples_per_degree),
             horizon_band_deg=np.float64(record.horizon_band_deg), meta=np.array(json.dumps(meta)))


def read_route_file(path: Path) -> tuple[RouteRecord, dict]:
    """``(record, figures)`` of a ``<route_id>.npz`` the stage wrote."""
    with np.load(path, allow_pickle=False) as z:
        meta = json.loads(str(z["meta"][()]))
        rec = RouteRecord(z["lines"], z["poses"], float(z["s0_m"]), float(z["spacing_m"]),
                          float(z["samples_per_degree"]), float(z["horizon_band_deg"]), 0, meta["sources"],
                          meta["meta"])
    return rec, meta["figures"]


def stored_routes(base: dict | None) -> dict[str, RouteRecord]:
    """The routes of the published version a build extends (empty without one)."""
    if base is None:
        return {}
    import zarr

    from mapstore.repository import MapRepository
    from mapstore.routes import list_routes, read_route

    root = zarr.open_group(MapRepository.open(base["url"]).readonly(base["snapshot"]).store, mode="r")
    return {rid: read_route(root, rid) for rid in list_routes(root)}


def run_orp(ws: Workspace, params: StageParams) -> dict:
    """Stage entry: one ORP per route (``ws.route_file``), refreshing the routes stored in
    the version the build reads them from (``params.build.route_base``); returns the report's
    ``orp`` section."""
    t0 = time.perf_counter()
    cfg, base = params.cfg, params.build.route_base
    runs = read_runs(ws)
    if not runs:
        return {}
    groups: dict[str, list[Run]] = {}
    for r in runs:
        groups.setdefault(route_of(r, cfg["orp"]), []).append(r)
    stored = stored_routes(base)
    n_floor = floor_priors(ws, runs) if cfg["orp"]["floor_poses"] else 0
    section: dict = {"priors": "floor" if n_floor == len(runs) else ("odometry" if not n_floor else "mixed"),
                     "routes": [], "runs": 0, "runs_skipped": 0, "rows": 0, "rows_interpolated": 0, "length_m": 0.0,
                     "registration": {"fixes_tried": 0, "fixes_accepted": 0, "ncc_median": None, "loop_closures": 0}}
    nccs, gts, rows_csv = [], [], ["route,log_id,frame,t,x,y,theta"]
    nbytes = 0
    for rid, group in groups.items():
        out = build_route(rid, group, cfg, stored.get(rid))
        rec, fig = out["record"], out["figures"]
        write_route_file(ws.route_file(rid), rec, fig)
        for run, kp in out["kept_poses"]:
            for j, p in zip(run.kept, kp):
                x, y, th = (float(v) for v in p)
                rows_csv.append(f"{rid},{run.log_id},{int(run.frame[j])},{float(run.t[j])!r},{x!r},{y!r},{th!r}")
        nbytes += _compressed_bytes(rec)
        section["routes"].append({"id": rid, "runs": fig["runs"], "rows": fig["rows"], "length_m": fig["length_m"],
                                  "rows_fed": fig["rows_fed"], "rows_interpolated": fig["rows_interpolated"],
                                  "skipped": fig["skipped"], "spacing_m": rec.spacing_m,
                                  "extended_m": fig["extended_m"],
                                  "extensions": fig["extensions"], "registration": fig["registration"],
                                  "refreshed": rid in stored, **({"ground_truth": fig["ground_truth"]}
                                                                  if "ground_truth" in fig else {})})
        section["runs"] += fig["runs"]
        section["runs_skipped"] += len(fig["skipped"])
        section["rows"] += fig["rows"]
        section["rows_interpolated"] += fig["rows_interpolated"]
        section["length_m"] += fig["length_m"]
        reg = fig["registration"]
        for k in ("fixes_tried", "fixes_accepted", "loop_closures"):
            section["registration"][k] += reg[k]
        if reg["ncc_median"] is not None:
            nccs.append(reg["ncc_median"])
        if "ground_truth" in fig:
            gts.append(fig["ground_truth"])
    ws.route_runs.write_text("\n".join(rows_csv) + "\n")
    section["registration"]["ncc_median"] = float(np.median(nccs)) if nccs else None
    section["bytes_per_km"] = nbytes / max(section["length_m"], 1e-9) * 1000.0
    if gts:
        section["ground_truth"] = {
            "pose_rms_m": float(np.sqrt(np.mean([g["pose_rms_m"] ** 2 for g in gts]))),
            "pose_max_m": max(g["pose_max_m"] for g in gts),
            "heading_rms_deg": float(np.sqrt(np.mean([g["heading_rms_deg"] ** 2 for g in gts]))),
        }
    section["seconds"] = time.perf_counter() - t0
    return {"orp": section}


def _compressed_bytes(rec: RouteRecord) -> int:
    """Bytes of the route as stored (zstd chunks of :func:`mapstore.routes.write_route`)."""
    import zarr

    from mapstore.routes import write_route

    chunks: dict = {}
    root = zarr.open_group(zarr.storage.MemoryStore(store_dict=chunks), mode="w")
    write_route(root, "r", rec)
    return int(sum(len(v.to_bytes()) for k, v in chunks.items() if "/c/" in k or k.endswith("/c")))


# Added to the build when a log is omni (pipeline.stages.build: after optimize with [orp] floor_poses,
# else after ingest); feeds publish only.
STAGE = Stage("orp", run_orp, params_tables=("orp", "optimize", "tracker.orp"), reads_base=True, side=True)
