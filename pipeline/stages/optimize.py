"""Stage ``optimize``: global pose optimization over the registered links.

Reads the frames store's odometry priors and ``register/links.csv``, runs
:func:`pipeline.optimize.optimize_poses`, and writes ``poses.csv`` (t, x, y, theta, then the
extension columns ``log_id``, ``frame`` (the row in that log's frames.csv) and the
marginal sigmas), ``links.csv`` (with residuals after
optimization), plots, and, when every log has a ``ground_truth.csv``, the ground-truth
figures for the report (the poses themselves never depend on ground truth).
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from pipeline.drivelog import POSE_COLUMNS
from pipeline.evaluate import absolute_trajectory_error, ground_truth_at, link_errors
from pipeline.framestore import FrameStore
from pipeline.geometry_gate import (
    Dropped,
    JumpParams,
    extent_growth_m,
    footprint_extent,
    frame_diagonal_m,
    speed_cap,
    spike_reasons,
    wild_unlinked,
    write_dropped,
)
from pipeline.fsutil import copy_file_atomic, write_text_atomic
from pipeline.anchor import MAP_FRAME
from pipeline.link_counts import link_counts
from pipeline.link_groups import lone_frames, unverified_overlaps
from pipeline.links import Link, components, read_links, write_links
from pipeline.allocator import lean_heap
from pipeline.odometry_model import is_stage, log_model
from pipeline.optimize import OptimizeResult, optimize_poses, sim_between
from pipeline.stages.register import read_prior
from pipeline.stages.stage import Stage, StageParams
from pipeline.stages.workspace import Workspace

# The simulator's truth of an unknown camera height variation (``--height-jitter``):
# ``t,height_m,scale`` per frame; read for the report's ground-truth figures only.
HEIGHT_TRUTH_FILE = "ground_truth_height.csv"

log = logging.getLogger(__name__)


def write_poses(path: Path, store: FrameStore, poses: np.ndarray, marginal_cov: np.ndarray | None,
                scales: np.ndarray | None = None) -> None:
    """Optimized poses, frame by frame in store order, in the drive log's pose convention.

    Extension columns: ``log_id``, ``frame`` (row in that log's frames.csv), when the
    marginals were computed ``sigma_x, sigma_y`` (metres) and ``sigma_theta`` (radians),
    and with ``[optimize] pose_model = "similarity2"`` ``scale``: the frame's true ground
    pixel size over the nominal one (= its camera height over the calibrated height; 1 =
    the calibrated height): frame pixels span ``pixel_size x scale`` metres on the floor.
    """
    extra = ("log_id", "frame") + (("sigma_x", "sigma_y", "sigma_theta") if marginal_cov is not None else ())
    extra += ("scale",) if scales is not None else ()
    lines = [",".join(POSE_COLUMNS + extra)]
    g = 0
    for lf in store.logs:
        log_id = lf.attrs["log_id"]
        for t, src in zip(lf.t.tolist(), lf.source_index.tolist()):
            x, y, th = poses[g].tolist()
            row = f"{t!r},{x!r},{y!r},{th!r},{log_id},{src}"
            if marginal_cov is not None:
                sx, sy, st = np.sqrt(np.maximum(np.diag(marginal_cov[g]), 0.0)).tolist()
                row += f",{sx:.6g},{sy:.6g},{st:.6g}"
            if scales is not None:
                row += f",{float(scales[g])!r}"
            lines.append(row)
            g += 1
    write_text_atomic(path, "\n".join(lines) + "\n")


def read_poses_table(path: Path) -> np.ndarray:
    """``poses.csv`` as written by :func:`write_poses`: a structured array with its columns
    (t, x, y, theta, log_id, frame and, when present, the sigmas and the scale), one row per
    frame; ``log_id`` as text (the type guess would turn a log id "001" into 1)."""
    return np.atleast_1d(np.genfromtxt(path, delimiter=",", names=True, dtype=None, encoding="utf-8",
                                       converters={"log_id": str}))


def _frame_ref(store: FrameStore, g: int) -> tuple[str, int]:
    """``(log id, row in its frames.csv)`` of the global frame index ``g``."""
    for lf in store.logs:
        if g < lf.count:
            return str(lf.attrs["log_id"]), int(lf.source_index[g])
        g -= lf.count
    raise IndexError(g)


def _unverified_overlaps(store: FrameStore, poses: np.ndarray, accepted: list, map_links: list,
                         registrable: np.ndarray, dropped: set[int], min_overlap: float) -> dict:
    """The report's figures of overlaps no link verifies (:mod:`pipeline.link_groups`), with
    one warning line when there are any: frames are grouped by accepted links (frames held
    by the published map form one group with it)."""
    n = len(poses)
    a = [lk.a for lk in accepted] + [n for lk in map_links if lk.status == "accepted"]
    b = [lk.b for lk in accepted] + [lk.b for lk in map_links if lk.status == "accepted"]
    groups = components(n + 1, a, b)[:n]
    sizes = np.concatenate([np.tile(np.array(lf.valid.shape[::-1], np.float64) * store.pixel_size, (lf.count, 1))
                            for lf in store.logs]) if store.logs else np.zeros((0, 2))
    candidates = registrable.copy()
    candidates[list(dropped)] = False
    mask, pairs = unverified_overlaps(poses, sizes, groups, candidates, min_overlap)
    frames = np.flatnonzero(mask)
    multi = np.unique(groups[candidates], return_counts=True)[1]
    lone = lone_frames(frames, groups)  # no accepted link, not held by the map
    out = {"frames_registrable": int(candidates.sum()), "link_groups": int((multi >= 2).sum()),
           "unverified_overlap_frames": int(len(frames)), "unverified_overlap_pairs": pairs,
           "unverified_overlap_lone_frames": int(len(lone)),
           "unverified_overlap": [_frame_name(store, int(g)) for g in frames[:200]]}
    if len(frames):
        alone = (f"; {len(lone)} of them without any accepted link (e.g. {_frame_name(store, int(lone[0]))}), "
                 f"each overlapping its neighbours" if len(lone) else "")
        log.warning("%d of %d textured frames overlap a frame that no chain of links ties them to (%d frame pairs, "
                    "%d link group%s of several frames%s): their alignment there rests on the prior alone and the "
                    "mosaic may show doubled edges (report: links.unverified_overlap; gate [publish] "
                    "max_unverified_overlap_fraction)", len(frames), int(candidates.sum()), pairs,
                    out["link_groups"], "" if out["link_groups"] == 1 else "s", alone)
    return out


def _frame_name(store: FrameStore, g: int) -> str:
    """``"<log id> frame <row in its frames.csv>"`` of the global frame index ``g``."""
    log_id, src = _frame_ref(store, g)
    return f"{log_id} frame {src}"


def check_geometry(store: FrameStore, poses: np.ndarray, prior: np.ndarray, linked: np.ndarray,
                   cfg_opt: dict) -> dict:
    """The report's ``geometry`` section (:mod:`pipeline.geometry_gate`): frames dropped for a
    wild prior (``dropped``: ``{log, frame, reason}``, the first 200; ``_dropped``: all of them
    as :class:`~pipeline.geometry_gate.Dropped`, popped by the caller), each log's speed cap
    (m/s), and the extents (metres, ``[xmin, ymin, xmax, ymax]``) of the linked frames and of
    the frames kept, for the publish gate. ``poses`` (N, 3) optimized, ``prior`` (N, 3) the
    prior the build used (register's ``prior.csv``), ``linked`` (N,) bool."""
    from pipeline.stages.register import prior_spike_masks

    params = JumpParams.from_config(cfg_opt)
    px = store.pixel_size
    t = np.concatenate([np.asarray(lf.t, float) for lf in store.logs])
    log_of = np.concatenate([np.full(lf.count, k) for k, lf in enumerate(store.logs)])
    caps = [speed_cap(np.asarray(lf.prior), np.asarray(lf.t), params) for lf in store.logs]
    diags = [frame_diagonal_m(lf.valid.shape, px) for lf in store.logs]
    spikes = np.concatenate(prior_spike_masks(store, cfg_opt)) & ~linked
    raw = np.vstack([np.asarray(lf.prior) for lf in store.logs])
    wild = {**wild_unlinked(poses, t, log_of, linked, caps, diags, params, spikes),
            **spike_reasons(raw, prior, spikes, log_of, caps)}
    dropped = [Dropped(g, *_frame_ref(store, g), reason) for g, reason in sorted(wild.items())]
    for d in dropped[:20]:
        log.warning("%s dropped: %s", d.name(), d.reason)
    if len(dropped) > 20:
        log.warning("... %d more frames dropped (report: geometry.dropped)", len(dropped) - 20)
    keep = np.ones(len(poses), bool)
    keep[[d.frame for d in dropped]] = False
    linked_extent = footprint_extent(poses, log_of, diags, linked & keep)
    extent = footprint_extent(poses, log_of, diags, keep)
    return {
        "frames_dropped": len(dropped),
        "dropped": [{"log": d.log_id, "frame": d.source, "reason": d.reason} for d in dropped[:200]],
        "speed_cap_m_s": {str(lf.attrs["log_id"]): cap for lf, cap in zip(store.logs, caps)},
        "frame_diagonal_m": max(diags, default=0.0),
        "linked_extent_m": linked_extent,
        "extent_m": extent,
        "extent_growth_m": None if linked_extent is None or extent is None else extent_growth_m(extent, linked_extent),
        "_dropped": dropped,
    }


def _ground_truth(store: FrameStore) -> np.ndarray | None:
    """Ground truth at every stored frame, or None unless every log has it."""
    parts = []
    for lf in store.logs:
        gt = Path(lf.attrs["path"]) / "ground_truth.csv"
        if not gt.exists():
            return None
        parts.append(ground_truth_at(lf.t, gt))
    return np.vstack(parts)


def _true_scales(store: FrameStore) -> np.ndarray | None:
    """Per-frame true scale (camera height / calibrated height) from every log's
    ``ground_truth_height.csv``, or None unless every log has one (evaluation only)."""
    parts = []
    for lf in store.logs:
        path = Path(lf.attrs["path"]) / HEIGHT_TRUTH_FILE
        if not path.exists():
            return None
        d = np.atleast_1d(np.genfromtxt(path, delimiter=",", names=True))
        parts.append(np.interp(np.asarray(lf.t, float), d["t"], d["scale"]))
    return np.concatenate(parts)


def sim_link_errors(links: list[Link], gt4: np.ndarray, pixel_size: float) -> np.ndarray:
    """:func:`pipeline.evaluate.link_errors` for similarity links: per link, the error (frame
    a's pixels) of where ``(rel, log_scale)`` puts the point of frame b that the truth
    ``gt4`` ((N, 4) x, y, theta, scale) puts at the midpoint of the two frame centres."""
    if not links:
        return np.zeros(0)
    a = np.array([lk.a for lk in links])
    b = np.array([lk.b for lk in links])
    tru = sim_between(gt4[a], gt4[b])
    est = np.array([[*lk.rel, 0.0 if lk.log_scale is None else lk.log_scale] for lk in links], float)

    def apply(r: np.ndarray, q: np.ndarray) -> np.ndarray:  # b nominal metres -> a nominal metres
        c, s, k = np.cos(r[:, 2]), np.sin(r[:, 2]), np.exp(r[:, 3])
        return r[:, :2] + k[:, None] * np.column_stack([c * q[:, 0] - s * q[:, 1], s * q[:, 0] + c * q[:, 1]])

    mid = tru[:, :2] / 2.0
    c, s, k = np.cos(tru[:, 2]), np.sin(tru[:, 2]), np.exp(tru[:, 3])
    d = (mid - tru[:, :2]) / k[:, None]
    q = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
    return np.linalg.norm(apply(est, q) - mid, axis=1) / pixel_size


def optimize_over_map(priors: list[np.ndarray], links: list[Link], map_links: list[Link], cfg_opt: dict,
                      pixel_size: float, models: list[np.ndarray] | None = None) -> OptimizeResult:
    """:func:`optimize_poses` with the published map as one more, fixed, pose.

    Without map links this is ``optimize_poses(priors, links)``. With them, a map node (the
    map frame's origin, held by the tight gauge prior) comes first and every map link is a
    link from it, so the robust kernel, the outlier passes and the residuals treat map links
    like any other; each log starts loosely at its odometry pose. The result has the map
    node removed and link indices restored (map links keep ``a = MAP_FRAME``).
    """
    if not map_links:
        return optimize_poses(priors, links, cfg_opt, pixel_size, models=models)
    shifted = [lk.with_ends(lk.a + 1, lk.b + 1) for lk in links]
    shifted += [lk.with_ends(0, lk.b + 1) for lk in map_links]
    res = optimize_poses([np.zeros((1, 3))] + list(priors), shifted, cfg_opt, pixel_size, hub=0,
                         models=None if models is None else [None] + list(models))
    back = [lk.with_ends(lk.a - 1, lk.b - 1) for lk in res.links[: len(links)]]
    back += [lk.with_ends(MAP_FRAME, lk.b - 1) for lk in res.links[len(links):]]
    marg = None if res.marginal_cov is None else res.marginal_cov[1:]
    return replace(res, poses=res.poses[1:], marginal_cov=marg, links=back,
                   scales=None if res.scales is None else res.scales[1:])


def hold_stage_axes(poses: np.ndarray, priors: np.ndarray, models: list[np.ndarray]) -> np.ndarray:
    """Poses (N, 3; metres, radians, map frame) turned about their centroid so that their
    mean heading is the priors' mean, when every log is a stage
    (:func:`pipeline.odometry_model.is_stage`); else ``poses`` as they are.

    A stage does not rotate, but the solve leaves the mosaic's rotation to the tiles'
    position priors (a stage's errors of several pixels: on a 5 x 5 grid of 1024 px tiles
    1e-4 rad, 0.2 px at the corners) and to their heading priors, each loose enough for the
    apparent rotations of lens distortion. Their mean is known far better than any one of
    them. The links' relative poses are unchanged (a rigid motion of the whole solution).
    """
    if not len(poses) or not all(is_stage(m) for m in models):
        return poses
    d = float(np.angle(np.mean(np.exp(1j * (poses[:, 2] - priors[:, 2])))))
    c = poses[:, :2].mean(axis=0)
    cs, sn = np.cos(-d), np.sin(-d)
    out = poses.copy()
    out[:, :2] = (poses[:, :2] - c) @ np.array([[cs, sn], [-sn, cs]]) + c
    out[:, 2] = poses[:, 2] - d
    return out


def run_optimize(ws: Workspace, params: StageParams) -> dict:
    """Stage entry: the register stage's links and prior to ``ws.poses`` (and links with
    residuals, dropped frames, plots); returns the report's sections."""
    t0 = time.perf_counter()
    cfg = params.cfg
    store = FrameStore(ws.frames_store)
    priors = [np.asarray(lf.prior) for lf in store.logs]
    used = read_prior(ws.register_prior, sum(len(p) for p in priors))
    if used is not None:  # the register stage's prior, corrected where it was biased
        priors = np.split(used, np.cumsum([len(p) for p in priors])[:-1])
    links = read_links(ws.register_links)
    map_path = ws.register_map_links
    map_links = read_links(map_path) if map_path.exists() else []
    # (before the optimizer rejects outliers; an array: 195,000 links on a 40 x 40 m floor)
    registered = np.fromiter((lk.status == "accepted" for lks in (links, map_links) for lk in lks), bool,
                             len(links) + len(map_links))
    tables = [lf.attrs.get("odometry_model") for lf in store.logs]
    used_models = ws.register_models
    if used_models.exists():  # the register stage's, grown where the prior proved noisier
        tables = json.loads(used_models.read_text()) or tables
    models = [log_model(cfg["optimize"], t) for t in tables]
    with lean_heap():  # (GTSAM's eliminations: see pipeline.allocator)
        res = optimize_over_map(priors, links, map_links, cfg["optimize"], store.pixel_size, models)
    if not map_links:
        res = replace(res, poses=hold_stage_axes(res.poses, np.vstack(priors), models))
    write_poses(ws.poses, store, res.poses, res.marginal_cov, res.scales)
    extra = ("iterations", "radius_px", "predicted_overlap", "peak_z", "peak_ncc", "rotation", "residual_px",
             "mahalanobis")
    write_links(ws.optimize_links, [lk for lk in res.links if lk.a != MAP_FRAME], extra)
    map_links = [lk for lk in res.links if lk.a == MAP_FRAME]
    if map_path.exists():
        write_links(ws.optimize_map_links, map_links, extra)
    accepted = [lk for lk in res.links if lk.status == "accepted" and lk.a != MAP_FRAME]
    log_of = np.concatenate([np.full(len(p), k) for k, p in enumerate(priors)])
    cross = {k: 0 for k in range(1, len(priors))}
    for lk in accepted:
        la, lb = int(log_of[lk.a]), int(log_of[lk.b])
        if la != lb:
            cross[max(la, lb)] = cross.get(max(la, lb), 0) + 1
    for k, n in cross.items():
        if n == 0:
            log.warning(
                "log %s has no accepted link to an earlier log: its poses rest on its odometry "
                "start alone (logs are assumed to share the site's odometry frame)", store.logs[k].attrs["log_id"])
    # Frames that hold texture and had a candidate pair but keep no accepted link: placed by
    # their prior alone where others are mapped (the publish gate max_unlinked_fraction).
    registrable = np.concatenate([lf.registrable for lf in store.logs])
    tried = np.zeros(len(registrable), bool)
    for lk in links:
        tried[lk.a] = tried[lk.b] = True
    linked = np.zeros(len(registrable), bool)
    for lk in accepted:
        linked[lk.a] = linked[lk.b] = True
    unlinked = np.flatnonzero(tried & registrable & ~linked)
    for lk in map_links:  # a map link holds its frame too (the wild-frame check below)
        if lk.status == "accepted":
            linked[lk.b] = True
    geometry = check_geometry(store, res.poses, np.vstack(priors), linked, cfg["optimize"])
    dropped = geometry.pop("_dropped")
    write_dropped(ws.dropped, dropped)
    overlaps = _unverified_overlaps(store, res.poses, accepted, map_links, registrable, {d.frame for d in dropped},
                                    cfg["optimize"]["unverified_overlap_min"])
    counts = link_counts(res.links, registered)  # the report's, the summary's and the plot's
    report: dict = {
        "links": {
            "frames_tried": int((tried & registrable).sum()),
            "frames_unlinked": len(unlinked),
            "unlinked": [_frame_name(store, int(g)) for g in unlinked[:200]],
            **counts,
            "cross_log": int(sum(cross.values())),
            **overlaps,
        },
        "geometry": geometry,
        "optimization": {
            "frames": int(res.poses.shape[0]),
            "residual_rms_px": res.residual_rms_px,
            "residual_max_px": max((lk.extra["residual_px"] for lk in accepted), default=0.0),
            "seconds": res.seconds,
            "iterations": res.iterations,
            "passes": res.passes,
            "link_covariance_scale": res.covariance_scale,
        },
    }
    if map_links:
        report["optimization"]["map_link_covariance_scale"] = res.map_covariance_scale
        report["optimization"]["map_error_sigma_px"] = res.map_error_sigma / store.pixel_size
    if res.scales is not None:
        report["optimization"].update(pose_model="similarity2", scale_min=float(res.scales.min()),
                                      scale_max=float(res.scales.max()))
    prior_all = np.vstack(priors)
    gt = _ground_truth(store)
    if gt is not None:
        ate = absolute_trajectory_error(res.poses, gt, store.pixel_size)
        ate_odo = absolute_trajectory_error(prior_all, gt, store.pixel_size)
        s_true = _true_scales(store) if res.scales is not None else None
        if res.scales is not None:
            gt4 = np.column_stack([gt, np.ones(len(gt)) if s_true is None else s_true])
            lerr = sim_link_errors(accepted, gt4, store.pixel_size)
        else:
            lerr = link_errors(accepted, gt, store.pixel_size)
        report["ground_truth"] = {
            "pose_rms_px": ate["rms_px"],
            "pose_max_px": ate["max_px"],
            "odometry_rms_px": ate_odo["rms_px"],
            "link_error_median_px": float(np.median(lerr)) if lerr.size else None,
            "link_error_p95_px": float(np.percentile(lerr, 95)) if lerr.size else None,
        }
        if s_true is not None:
            ds = res.scales - s_true
            report["ground_truth"]["scale_rms_error"] = float(np.sqrt(np.mean(ds**2)))
            report["ground_truth"]["scale_max_error"] = float(np.abs(ds).max())
    from pipeline.plots import plot_link_residuals, plot_trajectories

    plot_trajectories(ws.plot("trajectory"), prior_all[:, :2], res.poses[:, :2],
                      None if gt is None else _aligned(gt, res.poses), res.links, counts=counts)
    plot_link_residuals(ws.plot("residuals"), res.links)
    report["optimization"]["stage_seconds"] = time.perf_counter() - t0
    return report


def _aligned(gt: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Ground-truth positions moved into the optimized frame (for the plot)."""
    from pipeline.evaluate import align_se2

    r, t = align_se2(gt[:, :2], poses[:, :2])
    return gt[:, :2] @ r.T + t


def copy_results(ws: Workspace) -> None:
    """The optimized trajectory and links also go to WORKDIR/poses.csv and WORKDIR/links.csv."""
    for src, dst in ((ws.poses, ws.result_poses), (ws.optimize_links, ws.result_links)):
        copy_file_atomic(src, dst)


STAGE = Stage("optimize", run_optimize, params_tables=("optimize",), reads_base=True, after=copy_results)
