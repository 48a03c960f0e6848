"""Global pose optimization with GTSAM: the ``optimize`` stage's computation.

One ``Pose2`` per frame (frames numbered globally, log after log, as in
:mod:`pipeline.links`). Factors:

- odometry: a ``BetweenFactorPose2`` between consecutive frames of a log, measuring the
  relative prior pose (:func:`mapstore.grid.se2_between`), with a diagonal noise from the
  error gradient: ``sigma_xy = max(alpha d, floor)``, ``sigma_theta = max(h d, floor)``
  where ``d`` is the length of the increment;
- registration: a ``BetweenFactorPose2`` per accepted link, noise
  ``Gaussian.Covariance`` of the link's covariance carried to Pose2 local coordinates
  (:func:`local_covariance`), wrapped in the configured robust kernel;
- gauge: a tight prior on the first frame of log 0 at its odometry pose, a loose prior on
  the first frame of every other log (the logs share the site's odometry frame).

Levenberg-Marquardt from the odometry poses, then outlier rejection: links whose
Mahalanobis distance (residual in Pose2 local coordinates, the link's own covariance)
exceeds ``outlier_chi2``, or whose residual in pixels exceeds ``outlier_max_residual_px``,
are rejected and the graph is optimized again. On a floor of at least 4 x ``block_frames``
frames every solve is the same Levenberg-Marquardt iteration with each step's linear system
solved exactly by blocks of the floor (:mod:`pipeline.blocked_lm`): the elimination of the
whole floor, whose memory grows faster than the floor, never happens (a 40 x 40 m floor's
optimize alone: peak 955 -> 669 MiB for 1.42x the CPU, the same poses to 1e-7 px).

Pose model (``pose_model``): ``"pose2"`` (default) as above; ``"similarity2"`` for cameras
whose height varies unknown to the log: one ``Similarity2`` per frame, ``(x, y, theta,
s)`` with ``s`` the frame's scale (true ground size of a rectified pixel / the nominal pixel
size = camera height / calibrated height; a frame pixel at vehicle offset ``q`` (nominal
metres) lies at ``(x, y) + s R(theta) q``). Links carry the relative scale
(:class:`pipeline.links.Link` ``log_scale``, 4 x 4 covariance; a rigid link gets a loose
scale sigma of 1); odometry factors measure scale 1 with ``scale_sigma_per_frame`` (log
scale per frame step); every frame gets a weak prior at scale 1 (``scale_prior_sigma``,
log scale; it keeps frames without links determined). Links are invariant to a global
similarity, so the map's scale is then set by the odometry's distances, whose systematic
error exceeds the calibration's: after each solve the map is rescaled about the first frame
so that the frames' mean log scale is 0 (the calibrated height is the mean height). Map
links (``hub``) are rigid and skip that rescaling.

Outlier scheme (``outlier_policy``):

- ``"worst_per_cluster"`` (default): the links above the threshold are grouped into
  clusters (links sharing a frame, or frames at most ``outlier_cluster_frames`` apart in a
  log, are in one cluster); per pass only the worst link of each cluster is rejected. An
  outlier that is not fully neutralised by the robust kernel bends the poses near it, and
  its good neighbours then exceed the threshold too; rejecting only the worst per cluster
  never throws those away, while separate outliers anywhere in the map still go in one
  pass. From pass ``max_outlier_passes`` on, every link still above the threshold goes,
  pass after pass until the re-solve leaves none above it (at most ``max_outlier_passes``
  more passes), so no accepted link is left above it.
- ``"all"``: every link above the threshold goes in each pass.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numpy as np

from mapstore.grid import se2_between, se2_compose, se2_inverse, se2_log, wrap_angle
from pipeline.allocator import trim_heap
from pipeline.blocked_lm import BlockSystem, blocks_per_side, levenberg_marquardt
from pipeline.candidates import odometry_sigmas
from pipeline.odometry_model import absolute_sigmas, default_model
from pipeline.schema import settings
from pipeline.schema_floor import OptimizeConfig
from pipeline.links import Link, components, link_arrays, on_cycles

log = logging.getLogger(__name__)

__all__ = ["OptimizeResult", "optimize_poses", "link_residuals", "IncrementalPoses", "pose_model",
           "sim_between", "sim_link_residuals"]

POSE_MODELS = ("pose2", "similarity2")


def _opt(cfg_opt: dict) -> OptimizeConfig:
    """The ``[optimize]`` table as its schema's dataclass (checked: a missing, unknown,
    mistyped or out-of-range key is a ValueError naming it)."""
    return settings(OptimizeConfig, cfg_opt)


def pose_model(cfg_opt: dict) -> str:
    """``[optimize] pose_model`` (one of :data:`POSE_MODELS`, lower case)."""
    return _opt(cfg_opt).pose_model.lower()


@dataclass
class OptimizeResult:
    """What :func:`optimize_poses` returns.

    Attributes:
        poses: (N, 3) optimized poses (x, y, theta) in the site (= log 0 odometry) frame.
        marginal_cov: (N, 3, 3) marginal covariances (m^2, m rad, rad^2) or None when the
            graph has more than ``marginals_max_frames`` frames.
        links: the input links; status/reason updated, ``extra["residual_px"]`` (translation
            residual norm in pixels) and ``extra["mahalanobis"]`` set on every link.
        residual_rms_px: RMS of ``residual_px`` over the accepted links (0 without links).
        seconds: wall time of the optimization (graph, solves, outlier passes, residuals;
            the marginals are timed separately in ``marginals_seconds``).
        iterations: LM iterations summed over all passes.
        rejected: links rejected here (links rejected before the call do not count).
        passes: LM solves run (robustness stages + re-optimizations after rejections).
        marginals_seconds: wall time of the marginal covariances.
        scales: (N,) frame scales with ``pose_model = "similarity2"`` (see the module
            docstring), None with Pose2.
        covariance_scale: the factor the links' covariances were calibrated by
            (``[optimize] calibrate_link_covariance``; 1 = left as registered).
        map_covariance_scale: the same for the links from ``hub`` (the published map),
            calibrated on their own (1 without a hub) where their covariance proved too
            pessimistic; where too optimistic, instead:
        map_error_sigma: the map's error (metres per axis) added to the map links'
            translation covariance (0 = none).
    """

    poses: np.ndarray
    marginal_cov: np.ndarray | None
    links: list[Link]
    residual_rms_px: float
    seconds: float
    iterations: int
    rejected: int
    passes: int = 1
    marginals_seconds: float = 0.0
    scales: np.ndarray | None = None
    covariance_scale: float = 1.0
    map_covariance_scale: float = 1.0
    map_error_sigma: float = 0.0


def local_covariance(rel: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """A link's covariance in Pose2 local coordinates (what GTSAM's BetweenFactor whitens).

    ``Link.cov`` is the covariance of ``rel``'s components as numbers (translation in frame
    a's axes); GTSAM's error ``Logmap(⊖rel ⊕ between)`` has its translation in the frame of
    ``rel`` (frame b's axes): rotate by ``R(dtheta)^T``. For lanes driven in opposite
    directions (dtheta ~ pi) this flips the sign of the translation-heading correlations.
    """
    rel = np.asarray(rel, float)
    c, s = np.cos(rel[..., 2]), np.sin(rel[..., 2])
    j = np.zeros(rel.shape[:-1] + (3, 3))
    j[..., 0, 0], j[..., 0, 1], j[..., 1, 0], j[..., 1, 1], j[..., 2, 2] = c, s, -s, c, 1.0
    return j @ np.asarray(cov, float) @ np.swapaxes(j, -1, -2)


def link_residuals(poses: np.ndarray, links: list[Link]) -> tuple[np.ndarray, np.ndarray]:
    """Residuals of links against poses.

    Returns ``(r, m)``: (L, 3) residuals in Pose2 local coordinates,
    ``Logmap(⊖rel ⊕ (⊖pose_a ⊕ pose_b))`` (what GTSAM's BetweenFactor whitens), and (L,)
    Mahalanobis distances squared ``r^T cov^-1 r`` with each link's covariance.
    """
    if not links:
        return np.zeros((0, 3)), np.zeros(0)
    return _pose2_residuals(poses, *link_arrays(links))


def _pose2_residuals(poses: np.ndarray, a: np.ndarray, b: np.ndarray, rel: np.ndarray,
                     cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`link_residuals` of links given as arrays (:func:`pipeline.links.link_arrays`)."""
    r = se2_log(se2_between(rel, se2_between(poses[a], poses[b])))
    m = np.einsum("li,li->l", r, np.linalg.solve(local_covariance(rel, cov), r[..., None])[..., 0])
    return r, m


def sim_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Relative similarity of frames ``b`` in ``a`` from (..., 4) ``(x, y, theta, s)``.

    Returns (..., 4) ``(dx, dy, dtheta, log(s_b / s_a))`` with ``(dx, dy) = R_a^T (t_b -
    t_a) / s_a``: b's centre in a's nominal metres (a's pixels x the pixel size), what a
    similarity link measures.
    """
    a, b = np.asarray(a, float), np.asarray(b, float)
    rel = se2_between(a[..., :3], b[..., :3])
    rel[..., :2] /= a[..., 3:4]
    return np.concatenate([rel, np.log(b[..., 3:4] / a[..., 3:4])], axis=-1)


def _sim_link_arrays(links: list[Link]) -> tuple[np.ndarray, np.ndarray]:
    """(L, 4) measurements ``(rel, log_scale)`` and (L, 4, 4) covariances; a rigid link gets
    log scale 0 with sigma 1 (no information) and no cross terms."""
    meas = np.zeros((len(links), 4))
    cov = np.zeros((len(links), 4, 4))
    for i, lk in enumerate(links):
        meas[i, :3] = lk.rel
        if lk.log_scale is not None and lk.cov4 is not None:
            meas[i, 3] = lk.log_scale
            cov[i] = lk.cov4
        else:
            cov[i, :3, :3] = lk.cov
            cov[i, 3, 3] = 1.0
    return meas, cov


def sim_local_covariance(meas: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """Covariance (..., 4, 4) of similarity measurements ``(dx, dy, dtheta, log s)`` carried to
    GTSAM's Similarity2 local coordinates (``Logmap(meas^-1 x)``: translation in b's axes
    divided by the relative scale, then rotation, log scale)."""
    meas = np.asarray(meas, float)
    c, s = np.cos(meas[..., 2]), np.sin(meas[..., 2])
    k = np.exp(-meas[..., 3])
    j = np.zeros(meas.shape[:-1] + (4, 4))
    j[..., 0, 0], j[..., 0, 1], j[..., 1, 0], j[..., 1, 1] = c * k, s * k, -s * k, c * k
    j[..., 2, 2] = j[..., 3, 3] = 1.0
    return j @ np.asarray(cov, float) @ np.swapaxes(j, -1, -2)


def sim_link_residuals(poses: np.ndarray, links: list[Link]) -> tuple[np.ndarray, np.ndarray]:
    """Similarity analogue of :func:`link_residuals` for (N, 4) ``(x, y, theta, s)`` poses.

    Returns ``(r, m)``: (L, 4) residuals ``meas^-1 (⊖pose_a ⊕ pose_b)`` in the local
    coordinates of :func:`sim_local_covariance` (to first order GTSAM's Logmap) and (L,)
    Mahalanobis distances squared.
    """
    if not links:
        return np.zeros((0, 4)), np.zeros(0)
    a = np.array([lk.a for lk in links])
    b = np.array([lk.b for lk in links])
    meas, cov = _sim_link_arrays(links)
    est = sim_between(poses[a], poses[b])
    m_pose = np.column_stack([meas[:, :3], np.exp(meas[:, 3])])
    e_pose = np.column_stack([est[:, :3], np.exp(est[:, 3])])
    r = sim_between(m_pose, e_pose)
    r[:, 2] = wrap_angle(r[:, 2])
    lc = sim_local_covariance(meas, cov)
    m = np.einsum("li,li->l", r, np.linalg.solve(lc, r[..., None])[..., 0])
    return r, m


def _to_sim2(gtsam, p: np.ndarray):
    """``(x, y, theta, s)`` -> gtsam.Similarity2 (whose matrix is ``[R t; 0 1/s]``: t = (x, y) / s)."""
    return gtsam.Similarity2(gtsam.Rot2(float(p[2])), np.array([p[0], p[1]], float) / p[3], float(p[3]))


def _extract_sim2(gtsam, values, n: int, key) -> np.ndarray:
    """(n, 4) ``(x, y, theta, s)`` of Similarity2 values ``key(0..n-1)``."""
    out = np.empty((n, 4))
    for i in range(n):
        g = values.atSimilarity2(key(i))
        sc = g.scale()
        out[i, :2] = g.translation() * sc
        out[i, 2] = g.rotation().theta()
        out[i, 3] = sc
    return out


def _sim_normalize(gtsam, values, n: int, key):
    """Rescale the map about frame 0 so that the frames' mean log scale is 0 (links are
    invariant to it; see the module docstring). Returns new values."""
    p = _extract_sim2(gtsam, values, n, key)
    k = float(np.exp(-np.mean(np.log(p[:, 3]))))
    p[:, :2] = p[0, :2] + k * (p[:, :2] - p[0, :2])
    p[:, 3] *= k
    out = gtsam.Values()
    for i in range(n):
        out.insert(key(i), _to_sim2(gtsam, p[i]))
    return out


def _check(priors: list[np.ndarray], links: list[Link]) -> int:
    n = 0
    for k, p in enumerate(priors):
        p = np.asarray(p)
        if p.ndim != 2 or p.shape[1] != 3 or not np.all(np.isfinite(p)):
            raise ValueError(f"prior of log {k}: need a finite (N, 3) array, got shape {p.shape}")
        n += len(p)
    if n == 0:
        raise ValueError("no frames to optimize")
    if not links:
        return n
    try:  # (no per-link temporaries: a 40 x 40 m floor has 185,000 links)
        a, b, rel, cov = link_arrays(links)
    except ValueError:  # (malformed rel/cov, reported below: the ends are plain integers whatever the rest)
        a, b = np.array([lk.a for lk in links]), np.array([lk.b for lk in links])
        rel = cov = None
    ab = np.column_stack([a, b])
    bad = np.flatnonzero((ab < 0).any(axis=1) | (ab >= n).any(axis=1) | (ab[:, 0] == ab[:, 1]))
    if len(bad):
        i = int(bad[0])
        raise ValueError(f"link {i}: frames ({links[i].a}, {links[i].b}) invalid for {n} frames")
    if rel is None or rel.shape != (len(links), 3) or cov.shape != (len(links), 3, 3):
        raise ValueError("links: every rel must have 3 values and every cov 3x3")
    # Only accepted links enter the graph; rejected ones may carry NaN (never registered).
    used = np.array([lk.status == "accepted" for lk in links])
    ok = ~used | (np.isfinite(rel).all(axis=1) & np.isfinite(cov).all(axis=(1, 2)))
    check = ok & used
    ok[check] = np.linalg.eigvalsh(0.5 * (cov[check] + cov[check].transpose(0, 2, 1)))[:, 0] > 0
    bad = np.flatnonzero(~ok)
    if len(bad):
        i = int(bad[0])
        raise ValueError(
            f"link {i} ({links[i].a}-{links[i].b}): rel/cov not finite or covariance not positive definite"
        )
    return n


def _base_graph(gtsam, priors: list[np.ndarray], cfg: dict, similarity: bool = False,
                models: list[np.ndarray] | None = None):
    """Odometry and gauge factors, and the odometry initial values: one Pose2 per frame, or
    with ``similarity`` one Similarity2 (odometry at scale 1 with ``scale_sigma_per_frame``,
    gauge priors with ``scale_prior_sigma`` on the scale, and a weak scale-1 prior on every
    frame)."""
    X = gtsam.symbol_shorthand.X
    graph = gtsam.NonlinearFactorGraph()
    init = gtsam.Values()
    if similarity:
        o = _opt(cfg)
        s_step, s_prior = o.scale_sigma_per_frame, o.scale_prior_sigma
        weak = gtsam.noiseModel.Diagonal.Sigmas(np.array([1.0e3, 1.0e3, 1.0e3, s_prior]))
        value = lambda q: _to_sim2(gtsam, np.r_[q, 1.0])  # noqa: E731
        extra, extra_step = [s_prior], [s_step]
        prior_factor, between_factor = gtsam.PriorFactorSimilarity2, gtsam.BetweenFactorSimilarity2
    else:
        value = lambda q: gtsam.Pose2(*q)  # noqa: E731
        extra, extra_step = [], []
        prior_factor, between_factor = gtsam.PriorFactorPose2, gtsam.BetweenFactorPose2
    start = 0
    first = True
    for k, p in enumerate(priors):
        model = default_model(cfg) if models is None or models[k] is None else np.asarray(models[k], float)
        alpha, floor_m, hs, floor_r = model[:4]
        absolute = absolute_sigmas(model)
        p = np.asarray(p, dtype=float)
        n = len(p)
        if n == 0:
            continue
        for i in range(n):
            v = value(p[i])
            init.insert(X(start + i), v)
            if similarity:
                graph.add(prior_factor(X(start + i), v, weak))
        if absolute is not None:
            # Every pose has its own prior (a stage, GPS): they also fix the gauge.
            s = np.array([absolute[0], absolute[0], absolute[1], *extra], float)
            noise = gtsam.noiseModel.Diagonal.Sigmas(s)
            for i in range(n):
                graph.add(prior_factor(X(start + i), value(p[i]), noise))
            first = False
            start += n
            continue
        if first:
            s = np.array([cfg["anchor_sigma_m"], cfg["anchor_sigma_m"], cfg["anchor_sigma_rad"], *extra], float)
            first = False
        else:
            s = np.array([cfg["log_start_sigma_m"], cfg["log_start_sigma_m"], cfg["log_start_sigma_rad"], *extra], float)
        graph.add(prior_factor(X(start), value(p[0]), gtsam.noiseModel.Diagonal.Sigmas(s)))
        if n > 1:
            inc = se2_between(p[:-1], p[1:])
            d = np.hypot(inc[:, 0], inc[:, 1])
            sxy = np.maximum(alpha * d, floor_m)
            sth = np.maximum(hs * d, floor_r)
            for i in range(n - 1):
                noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([sxy[i], sxy[i], sth[i], *extra_step]))
                graph.add(between_factor(X(start + i), X(start + i + 1), value(inc[i]), noise))
        start += n
    return graph, init


def _odometry_gate(priors: list[np.ndarray], links: list[Link], cfg: dict, pixel_size: float,
                   models: list[np.ndarray] | None = None) -> int:
    """Reject links between frames of one log that odometry contradicts beyond reason.

    Over a short stretch dead reckoning is precise (error gradient x distance + floor:
    1.5 mm over 10 cm at 1 %), and there a wrong link that happens to be the only one
    bridging a gap in the chain would otherwise win against the odometry (its sigma is a
    hundred times smaller) and mask the good revisit links around it. Over long stretches
    the gate widens with the odometry's uncertainty and leaves the decision to the robust
    optimization. ``odometry_gate_sigmas`` = 0 turns it off. Returns the links rejected.
    """
    gate = _opt(cfg).odometry_gate_sigmas
    if gate <= 0:
        return 0
    rejected = 0
    prior_all = np.vstack(priors)
    log_of = np.repeat(np.arange(len(priors)), [len(p) for p in priors])
    # Distance travelled since each log's start (metres, from the odometry).
    path = np.concatenate([np.r_[0.0, np.cumsum(np.hypot(*np.diff(p[:, :2], axis=0).T))] for p in priors if len(p)])
    for lk in links:
        if lk.status != "accepted" or log_of[lk.a] != log_of[lk.b]:
            continue
        d = abs(path[lk.b] - path[lk.a])
        odo = se2_between(prior_all[lk.a], prior_all[lk.b])
        model = None if models is None else models[log_of[lk.a]]
        sig_t, sig_h = (float(v) for v in odometry_sigmas(d, cfg, model))
        # A heading error also moves b: lever arm = the distance between the frames.
        sig_t = float(np.hypot(sig_t, sig_h * np.hypot(odo[0], odo[1])))
        dt = float(np.hypot(*(np.asarray(lk.rel[:2]) - odo[:2])))
        dh = abs(float(wrap_angle(lk.rel[2] - odo[2])))
        if dt > gate * sig_t or dh > gate * sig_h:
            lk.status = "rejected"
            lk.reason = (f"outlier: disagrees with odometry by {dt / pixel_size:.1f} px, {dh:.4f} rad "
                         f"(gate {gate:g} sigma = {gate * sig_t / pixel_size:.1f} px, {gate * sig_h:.4f} rad)")
            rejected += 1
    return rejected


# The prior's sigmas in the calibration solve (see optimize_poses), times.
_WEAK = 1.0e3
# Median of chi-square with 1, 2, 3 degrees of freedom.
_CHI2_MEDIAN = {1: 0.4549, 2: 1.3863, 3: 2.3660}


def cycle_rank(links: list[Link]) -> int:
    """Independent loops of the graph the links form (links - frames + components): how
    many links are redundant, i.e. can disagree with the others."""
    if not links:
        return 0
    n, ends = _link_ends(links)
    labels = components(n, ends[:, 0], ends[:, 1])
    return len(links) - n + len(np.unique(labels))


def _link_ends(links: list[Link]) -> tuple[int, np.ndarray]:
    """The links' frames numbered ``0..n-1`` in order of their global index: ``(n, (L, 2) ends)``."""
    nodes, inv = np.unique(np.array([[lk.a, lk.b] for lk in links], int), return_inverse=True)
    return len(nodes), inv.reshape(-1, 2)


def calibration_scale(m: np.ndarray, links: list[Link], tolerance: float, min_loops: int = 4) -> float:
    """The factor on every link covariance that brings the links' squared Mahalanobis
    distances ``m`` to what chi-square predicts for their degrees of freedom, or 1 when
    they are within a factor ``tolerance`` of it either way, or when the links hold fewer than
    ``min_loops`` independent loops (links in a tree fit exactly and say nothing of their
    noise). Only links on a loop count: a bridge of the graph (a link whose removal parts
    its two frames) is fitted exactly whatever its noise, and a graph of many bridges (a
    drone flight's strips joined by a few links) once had the median at zero and every
    covariance shrunk a million times, after which the outlier passes cut every loop. A
    loop link's expected share of its chi-square is the loops per loop link (its residual
    is what the loops leave), so their median is compared with chi-square's median times
    that share."""
    return float(calibration_scales(m, links, np.zeros(len(m), np.int64), tolerance, min_loops)[0]) if len(m) else 1.0


def calibration_scales(m: np.ndarray, links: list[Link], group: np.ndarray, tolerance: float,
                       min_loops: int = 4) -> np.ndarray:
    """:func:`calibration_scale` for each group of links (``group``: (L,) int, 0..G-1): the
    loops are the whole graph's, each group's median its own loop links' (a group without
    ``min_loops`` loop links keeps 1). Returns (G,) factors.

    Links of different origins carry different unmodelled errors: a night's links to each
    other only its frames' noise, its links to the published map also the map's own errors
    (its poses, its blending), which their registration covariance does not hold."""
    return _banded(calibration_medians(m, links, group, min_loops)[0], tolerance)


def calibration_medians(m: np.ndarray, links: list[Link], group: np.ndarray,
                        min_loops: int = 4) -> tuple[np.ndarray, float]:
    """Per group (``group``: (L,) int, 0..G-1), the median over its links on a loop of their
    squared Mahalanobis distances ``m`` relative to what chi-square predicts for them (1 =
    as their covariance says; NaN where the graph has fewer than ``min_loops`` loops or the
    group fewer than ``min_loops`` loop links), and the loops per loop link (a loop link's
    expected share of its chi-square; 0 without loops). See :func:`calibration_scale`."""
    group = np.asarray(group, np.int64)
    out = np.full(int(group.max()) + 1 if len(group) else 1, np.nan)
    if len(m) == 0:
        return out, 0.0
    loops = cycle_rank(links)
    if loops < min_loops:
        return out, 0.0
    n, ends = _link_ends(links)
    cyc = on_cycles(n, ends[:, 0], ends[:, 1])
    share = loops / int(cyc.sum())
    # (a link that keeps the prior's rotation, extra "rotation" = "prior", measures 2)
    dof = np.array([2 if lk.extra.get("rotation") == "prior" else 3 for lk in links])
    ratio = np.asarray(m, float) / (np.array([_CHI2_MEDIAN[int(d)] for d in dof]) * share)
    for g in range(len(out)):
        sel = cyc & (group == g)
        if np.count_nonzero(sel) >= min_loops:
            out[g] = float(np.median(ratio[sel]))
    return out, share


def _banded(medians: np.ndarray, tolerance: float) -> np.ndarray:
    """The covariance factors of :func:`calibration_medians`' medians: 1 where a median is
    within a factor ``tolerance`` of 1 either way or not measured."""
    out = np.ones(len(medians))
    for g, k in enumerate(medians):
        # Both ways: too pessimistic covariances let the prior bend the links; too optimistic
        # ones (a lens's distortion makes the overlaps of microscope tiles disagree by tenths
        # of a pixel at hundredths-of-a-pixel noise sigmas) had the outlier passes reject good
        # links by the dozen. The median is robust to a minority of wrong links, which stay far
        # out after the scaling. (The scale is reported; the publish gates judge the result.)
        if not np.isfinite(k) or k <= 0 or 1.0 / tolerance < k < tolerance:
            continue
        out[g] = float(min(max(k, 1e-6), 1e6))
    return out


def added_variance(r: np.ndarray, local_cov: np.ndarray, share: float) -> float:
    """The variance ``v`` (per translation axis, m^2) to add to links' translation covariance
    so that the median of their squared translation residuals, each over ``share x (its own
    variance per axis + v)``, is chi-square(2)'s median (2 ln 2); 0 when it already is below.

    For links that measure against something with errors of its own, absolute in size and
    not in their covariance (the published map: its poses, its blending): a factor on their
    covariance would loosen the most precise ones most. ``r``: (L, 3) residuals in local
    coordinates (:func:`link_residuals`, at a solution on loops); ``local_cov``: (L, 3, 3)
    their covariances there; ``share``: a loop link's expected share of its chi-square (the
    loops per loop link, as in :func:`calibration_scale`)."""
    r = np.asarray(r, float).reshape(-1, 3)
    if not len(r) or not share > 0:
        return 0.0
    e2 = r[:, 0] ** 2 + r[:, 1] ** 2
    c = 0.5 * (np.asarray(local_cov)[:, 0, 0] + np.asarray(local_cov)[:, 1, 1])
    target = 2.0 * math.log(2.0)

    def med(v: float) -> float:
        return float(np.median(e2 / (share * (c + v))))

    if not med(0.0) > target:
        return 0.0
    lo, hi = 0.0, float(e2.max() / share)
    for _ in range(60):  # bisection: the median falls as v grows
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if med(mid) > target else (lo, mid)
    return hi


def _lm_params(gtsam, cfg: dict):
    o = _opt(cfg)
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(o.max_iterations)
    params.setRelativeErrorTol(o.relative_error_tol)
    params.setAbsoluteErrorTol(o.absolute_error_tol)
    params.setOrderingType(o.ordering.upper())
    return params


def _clusters(links: list[Link], idx: np.ndarray, span: int, log_of: np.ndarray, hub: int | None = None) -> list[np.ndarray]:
    """Group links ``idx`` whose frames coincide or lie at most ``span`` frames apart in a log.

    The ``hub`` frame (the published map, which every map link touches) joins no cluster.
    """
    parent = {int(i): int(i) for i in idx}

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    # Frame -> links touching it (dilated by span within the same log).
    owner: dict[int, int] = {}
    for i in idx:
        lk = links[int(i)]
        for f in (lk.a, lk.b):
            if f == hub:
                continue
            for g in range(f - span, f + span + 1):
                if g < 0 or g >= len(log_of) or log_of[g] != log_of[f]:
                    continue
                j = owner.get(g)
                if j is None:
                    owner[g] = int(i)
                else:
                    ri, rj = find(int(i)), find(j)
                    if ri != rj:
                        parent[ri] = rj
    groups: dict[int, list[int]] = {}
    for i in idx:
        groups.setdefault(find(int(i)), []).append(int(i))
    return [np.array(g) for g in groups.values()]


def _stage_scales(cfg: dict) -> list[float]:
    """Kernel scales (whitened units) of the successive solves; 0 = plain Gaussian."""
    o = _opt(cfg)
    kind, k = o.robust_kernel.lower(), o.robust_kernel_k
    if kind == "none":
        return [0.0]
    anneal = list(o.robust_anneal_k)  # decreasing (the schema's rule)
    if any(a <= k for a in anneal):
        raise ValueError("[optimize] robust_anneal_k: scales must decrease and stay above robust_kernel_k")
    return [0.0, *anneal, k]


@dataclass
class _LinkGraph:
    """The pieces every solve of :func:`optimize_poses` shares: the odometry and gauge graph,
    the accepted links' measurements and noises, and how to solve and measure.

    ``active``: (A,) indices (into ``links``) of the links that entered the graph,
    ``act_links`` those links (``act_links[j] is links[active[j]]``). A factor's GTSAM
    value and noise model are made from its link's measurement and covariance when the
    factor is (:meth:`factors`, a chunk of links at a time) and live only in the graph: as
    dicts of GTSAM noise models and of small arrays they held ~110 MB on a 40 x 40 m floor's
    195,000 links through every solve, for ~0.6 s to make them afresh per graph; as arrays
    of measurements and local covariances ~19 MB. ``normalize``: rescale similarity
    solutions about the first frame (see the module docstring)."""

    gtsam: object
    n: int
    sim: bool
    normalize: bool
    kind: str
    base_graph: object
    links: list[Link]
    active: np.ndarray
    act_links: list[Link]
    between: object
    block_frames: int = 0
    split: BlockSystem | None = None  # the last solve's graph split by blocks, kept for re-solves

    def noise_rows(self, js) -> tuple[np.ndarray, np.ndarray]:
        """The measurements and local covariances of the active links ``js``: (J, 3) ``x, y,
        theta`` (metres, radians) and (J, 3, 3), or with similarity links (J, 4) ``x, y,
        theta, s`` and (J, 4, 4) (:func:`local_covariance`, :func:`sim_local_covariance`),
        from the links' current covariances."""
        lks = [self.act_links[j] for j in js]
        if self.sim:
            m4, c4 = _sim_link_arrays(lks)
            m4, c4 = m4.reshape(-1, 4), c4.reshape(-1, 4, 4)
            return np.column_stack([m4[:, :3], np.exp(m4[:, 3])]), sim_local_covariance(m4, c4)
        _, _, rel, cov = link_arrays(lks)
        rel, cov = rel.reshape(-1, 3), cov.reshape(-1, 3, 3)
        return rel, local_covariance(rel, cov)

    def factors(self, js, robust=None, chunk: int = 4096):
        """``(j, factor)`` for each active link ``j`` of ``js`` (``links[active[j]]``): the
        between factor of its measurement with its Gaussian noise, wrapped in the ``robust``
        kernel (an mEstimator) when given; the noises made ``chunk`` links at a time."""
        gtsam = self.gtsam
        X = gtsam.symbol_shorthand.X
        Noise = gtsam.noiseModel.Gaussian.Covariance
        Robust = gtsam.noiseModel.Robust.Create
        js = list(js)
        for s in range(0, len(js), chunk):
            part = js[s: s + chunk]
            meas, local = self.noise_rows(part)
            for j, m, c in zip(part, meas, local):
                value = _to_sim2(gtsam, m) if self.sim else gtsam.Pose2(m[0], m[1], m[2])
                noise = Noise(c) if robust is None else Robust(robust, Noise(c))
                lk = self.act_links[j]
                yield j, self.between(X(lk.a), X(lk.b), value, noise)

    def mahalanobis(self, vals, lks: list[Link]) -> np.ndarray:
        """(L,) squared Mahalanobis distances of ``lks`` at the solution ``vals``."""
        if self.sim:
            return sim_link_residuals(_extract_sim2(self.gtsam, vals, self.n, self.gtsam.symbol_shorthand.X), lks)[1]
        return link_residuals(self.gtsam.utilities.extractPose2(vals), lks)[1]

    def solve(self, graph, vals, lm_params, keep: bool = False):
        """Levenberg-Marquardt from ``vals``: (solution, iterations). GTSAM's optimizer, or on a
        floor of more than one block (``block_frames``: :func:`pipeline.blocked_lm.blocks_per_side`)
        the same iteration with its linear systems solved by blocks of the floor. ``keep``:
        the graph's split by blocks is kept for the next solve with ``keep`` (the same graph,
        less the factors taken out by :meth:`remove`), else dropped."""
        gtsam = self.gtsam
        per_side = blocks_per_side(self.n, self.block_frames)
        system = self.split if keep else None
        self.split = None
        if per_side > 1 and system is None:
            xy = (_extract_sim2(gtsam, vals, self.n, gtsam.symbol_shorthand.X) if self.sim
                  else gtsam.utilities.extractPose2(vals))[:, :2]
            system = BlockSystem.split(gtsam, graph, xy, per_side, 4 if self.sim else 3)
        if system is not None:
            out, its = levenberg_marquardt(system, vals, lm_params)
            self.split = system if keep else None
            del system
        else:
            opt = gtsam.LevenbergMarquardtOptimizer(graph, vals, lm_params)
            out = opt.optimize()
            its = int(opt.iterations())
            del opt
        trim_heap()  # (the solve's freed eliminations: see pipeline.allocator.trim_heap)
        return (_sim_normalize(gtsam, out, self.n, gtsam.symbol_shorthand.X) if self.normalize else out), its

    def remove(self, graph, i: int) -> None:
        """Take factor ``i`` out of ``graph`` (and out of its kept split by blocks)."""
        graph.remove(i)
        if self.split is not None:
            self.split.remove(i)

    def build(self, scale: float):
        """The base graph plus every active link under the robust kernel of ``scale``
        (whitened units; 0 = Gaussian): (graph, (len(links),) factor index of each link in
        it, -1 for a link not in it)."""
        gtsam = self.gtsam
        graph = gtsam.NonlinearFactorGraph(self.base_graph)
        factor_of = np.full(len(self.links), -1, np.int64)
        est = None
        if scale > 0:
            est = (gtsam.noiseModel.mEstimator.Cauchy.Create(scale) if self.kind == "cauchy"
                   else gtsam.noiseModel.mEstimator.Huber.Create(scale))
        active = self.active
        for j, f in self.factors(range(len(active)), est):
            factor_of[active[j]] = graph.size()
            graph.add(f)
        return graph, factor_of


@dataclass
class _Solves:
    """LM parameters of the three kinds of solve, and the running tally of solves."""

    final: object  # the final kernel's solve
    stage: object  # the stages before it only provide starting points: a looser tolerance
    resolve: object  # re-solves after rejections: a few steps from the warm start
    iterations: int = 0
    passes: int = 0

    def run(self, lg: _LinkGraph, graph, vals, lm_params, keep: bool = False):
        """``lg.solve``, counted."""
        out, its = lg.solve(graph, vals, lm_params, keep)
        self.iterations += its
        self.passes += 1
        return out


def _solve_params(gtsam, cfg_opt: dict, o: OptimizeConfig) -> _Solves:
    params = _lm_params(gtsam, cfg_opt)
    # The stages before the final kernel only provide starting points: a looser tolerance.
    stage_params = _lm_params(gtsam, cfg_opt)
    stage_params.setRelativeErrorTol(o.stage_relative_error_tol)
    # After removing outliers the robust kernel had already down-weighted, the optimum
    # moves little: a few steps from the warm start suffice (each is a full elimination).
    resolve_params = _lm_params(gtsam, cfg_opt)
    resolve_params.setMaxIterations(o.resolve_max_iterations)
    return _Solves(params, stage_params, resolve_params)


def _link_graph(gtsam, n: int, links: list[Link], sim: bool, hub: int | None, base_graph,
                kind: str, block_frames: int = 0) -> _LinkGraph:
    """The accepted links, to be made into factors (:meth:`_LinkGraph.factors`)."""
    active = np.array([i for i, lk in enumerate(links) if lk.status == "accepted"], np.int64)
    act_links = [links[i] for i in active.tolist()]
    between = gtsam.BetweenFactorSimilarity2 if sim else gtsam.BetweenFactorPose2
    return _LinkGraph(gtsam, n, sim, sim and hub is None, kind, base_graph, links, active, act_links, between,
                      block_frames)


def _calibrate_covariances(lg: _LinkGraph, solves: _Solves, init, priors: list[np.ndarray], cfg_opt: dict,
                           o: OptimizeConfig, models: list[np.ndarray] | None, hub: int | None = None
                           ) -> tuple[float, float, float]:
    """Scale the links' covariances (``links[i].cov``, in place)
    by what their loops say; returns the factors (1 = left as registered) of the links
    between frames and of the links from ``hub`` (the published map; 1 without one), each
    group calibrated on its own, and the variance (m^2 per axis) added to the map links'
    translation (:func:`added_variance`: the map's own errors are absolute) wherever their
    median exceeds chi-square's, instead of a factor (0 when none)."""
    gtsam, links, active = lg.gtsam, lg.links, lg.active
    group_of = np.array([int(hub is not None and links[i].a == hub) for i in active.tolist()], np.int64)
    scales = np.ones(2)
    # Link covariances come from a noise model (independent pixel noise, smoothed); on
    # real images (noise, shading, distortion, focus) their scale can be off by a large
    # factor, and against the prior's sigmas that decides who wins. The links' own
    # loops tell the real scale: solved with the prior a thousand times weaker (so
    # that it cannot bend the links to its liking), their Mahalanobis distances are
    # compared with chi-square's, and the covariances scaled to match.
    weak = None if models is None else [None if m is None else np.asarray(m, float) * _WEAK for m in models]
    if weak is None:
        weak = [default_model(cfg_opt) * _WEAK for _ in priors]
    for m in weak:
        if m is not None:
            m[4] = 1.0 if m[4] >= 1.0 else 0.0  # (the kind flag is not a sigma)
    weak_graph, _ = _base_graph(gtsam, priors, cfg_opt, similarity=lg.sim, models=weak)
    # Gaussian solves, each without the links the last one found far out (beyond the
    # outlier gate at the scale found so far): a few wrong links, which a Gaussian solve
    # spreads over their neighbours, must not pass for everyone's noise. (A robust
    # kernel instead puts each of few loops' disagreement on one link, and the median
    # then sees none.)
    tol = o.calibration_tolerance
    min_loops = o.calibration_min_loops
    gate = o.outlier_chi2
    use = list(range(len(active)))
    vals0 = init
    for _ in range(4):
        graph0 = gtsam.NonlinearFactorGraph(weak_graph)
        for _, f in lg.factors(use):
            graph0.add(f)
        vals0 = solves.run(lg, graph0, vals0, solves.stage)
        sub = [lg.act_links[j] for j in use]
        m0 = lg.mahalanobis(vals0, sub)
        solved = use  # (the links of this solve: `use` may shrink below)
        medians, share = calibration_medians(m0, sub, group_of[use], min_loops)
        scales = np.ones(2)
        scales[: len(medians)] = _banded(medians, tol)
        # (the median without the tolerance band, for the trimming)
        k_raw = np.maximum(scales, 1.0)[group_of[use]]
        keep = [j for j, m, k in zip(use, m0, k_raw) if m <= gate * k]
        if len(keep) == len(use) or len(keep) < 8:
            break
        use = keep
    added = 0.0
    # The map links more spread than their covariance says (their median over chi-square's,
    # no tolerance band): the map's own errors, added to each as a variance (not a factor)
    if len(medians) > 1 and medians[1] > 1.0:  # (NaN: not measured)
        mine = [j for j in solved if group_of[j] == 1]
        r, _ = link_residuals(gtsam.utilities.extractPose2(vals0), [lg.act_links[j] for j in mine])
        added = added_variance(r, lg.noise_rows(mine)[1], share)
        scales[1] = 1.0
    for j, i in enumerate(active.tolist()):
        k = float(scales[group_of[j]])
        if k != 1.0:
            links[i].cov = links[i].cov * k
        if added and group_of[j] == 1:
            cov = links[i].cov.copy()
            cov[0, 0] += added
            cov[1, 1] += added
            links[i].cov = cov
    return float(scales[0]), float(scales[1]), added


def _graduated_solve(lg: _LinkGraph, solves: _Solves, values, scales: list[float], skip_ratio: float):
    """The solves from Gaussian to the final kernel scale: (values, final graph, link index ->
    factor index in it)."""
    # Graduated robustness: a Gaussian solve from odometry (convex: reaches the right basin
    # whatever the drift), then the kernel narrowed stage by stage down to its final scale,
    # so that no frame gets frozen in a wrong basin by a narrow kernel far from the optimum.
    # A stage is skipped when every link's whitened residual is already well inside it.
    graph = factor_of = None
    for si, scale in enumerate(scales):
        final = si == len(scales) - 1
        if 0 < scale and not final and lg.act_links:
            m = lg.mahalanobis(values, lg.act_links)
            if np.sqrt(m.max()) * skip_ratio < scale:
                continue
        graph = factor_of = None  # (the last stage's graph goes before the next is built)
        graph, factor_of = lg.build(scale)
        values = solves.run(lg, graph, values, solves.final if final else solves.stage, keep=final)
    return values, graph, factor_of


def _reject_outliers(lg: _LinkGraph, solves: _Solves, values, graph, factor_of: np.ndarray, o: OptimizeConfig,
                     log_of: np.ndarray, hub: int | None, pixel_size: float):
    """Outlier rejection passes, re-optimizing with the final kernel (factors removed from
    ``graph`` in place): (values, links rejected). A link is over the threshold when its
    squared Mahalanobis distance exceeds ``outlier_chi2``, or its residual (pixels at the
    overlap's centre) exceeds ``outlier_max_residual_px`` (a link whose own covariance is
    loose can disagree by many pixels within chi-square); the worst is the one furthest
    over either threshold, relatively."""
    links = lg.links
    chi2 = o.outlier_chi2
    max_px = o.outlier_max_residual_px
    max_passes = o.max_outlier_passes
    policy = o.outlier_policy
    span = o.outlier_cluster_frames
    rejected = 0
    active_set = set(lg.active.tolist())
    # (from pass max_passes on every link over a threshold goes, and passes go on until none
    # is left over after the re-solve, at most max_passes more)
    for rpass in range(1, 2 * max_passes + 1):
        idx = np.array(sorted(active_set), dtype=int)
        if len(idx) == 0:
            break
        act = [links[i] for i in idx]
        if max_px > 0:
            poses, _, p4 = _extract_poses(lg, values)
            res, m = _residuals(act, poses, p4, hub, pixel_size)
            severity = np.maximum(m / chi2, res / max_px)
        else:
            res, m = np.zeros(len(idx)), lg.mahalanobis(values, act)
            severity = m / chi2
        over = severity > 1.0
        if not np.any(over):
            break
        cand = idx[over]
        at = lambda i: np.searchsorted(idx, i)  # noqa: E731  (link index -> position in idx, sorted)
        if policy == "all" or rpass >= max_passes:
            drop = cand
        else:
            drop = np.array([g[np.argmax(severity[at(g)])] for g in _clusters(links, cand, span, log_of, hub)])
        for i in drop:
            i, k = int(i), int(at(i))
            lk = links[i]
            lk.status = "rejected"
            lk.reason = (f"outlier: Mahalanobis {m[k]:.1f} > {chi2:g} after optimization (pass {rpass})"
                         if m[k] > chi2 else
                         f"outlier: residual {res[k]:.1f} px > {max_px:g} px after optimization (pass {rpass})")
            lg.remove(graph, int(factor_of[i]))
            active_set.discard(i)
            rejected += 1
        del act, res, m, severity  # (not held through the re-solve: ~185,000 links each)
        values = solves.run(lg, graph, values, solves.resolve, keep=True)
    lg.split = None
    return values, rejected


def _extract_poses(lg: _LinkGraph, values) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """(N, 3) poses, (N,) frame scales (similarity, else None) and (N, 4) similarity poses
    (else None) of the solution."""
    if lg.sim:
        p4 = _extract_sim2(lg.gtsam, values, lg.n, lg.gtsam.symbol_shorthand.X)
        return p4[:, :3].copy(), p4[:, 3].copy(), p4
    return lg.gtsam.utilities.extractPose2(values), None, None


def _residuals(links: list[Link], poses: np.ndarray, p4: np.ndarray | None, hub: int | None,
               pixel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """(L,) residual of each link in frame a's pixels at the overlap's centre, and (L,)
    squared Mahalanobis distances, at the solution ``poses`` (or the similarity poses ``p4``)."""
    if p4 is not None:
        return _sim_residual_px(p4, links, hub, pixel_size)
    a, b, rel, cov = link_arrays(links)
    _, m = _pose2_residuals(poses, a, b, rel, cov)
    # The residual as a displacement where it matters: at the overlap's centre, taken as
    # the midpoint of the two frame centres (in frame a): where the link's measurement
    # and the optimized poses put the same point of frame b. (At b's own centre a tiny
    # rotation residual on a thin overlap strip would read as pixels of error.)
    est = se2_between(poses[a], poses[b])
    mid = np.zeros_like(rel)
    from_hub = (a == hub)[:, None]  # (all False without a hub)
    mid[:, :2] = np.where(from_hub, rel[:, :2], rel[:, :2] / 2.0)  # a map link: at b's centre
    q = se2_between(rel, mid)  # the midpoint in frame b, per the measurement
    disp = se2_compose(est, q)[:, :2] - mid[:, :2]
    return np.hypot(disp[:, 0], disp[:, 1]) / pixel_size, m


def _set_residuals(links: list[Link], poses: np.ndarray, p4: np.ndarray | None, hub: int | None,
                   pixel_size: float) -> float:
    """Set ``extra["residual_px"]`` and ``extra["mahalanobis"]`` on every link (rejected ones
    too: they show how far off they were); returns the accepted links' residual RMS (px)."""
    if not links:
        return 0.0
    res_px, m = _residuals(links, poses, p4, hub, pixel_size)
    for lk, rp, mm in zip(links, res_px, m):
        lk.extra["residual_px"] = float(rp)
        lk.extra["mahalanobis"] = float(mm)
    acc = np.array([lk.status == "accepted" for lk in links])
    return float(np.sqrt(np.mean(res_px[acc] ** 2))) if acc.any() else 0.0


def _marginals(lg: _LinkGraph, graph, values, max_frames: int) -> tuple[np.ndarray | None, float]:
    """(N, 3, 3) marginal covariances (m^2, m rad, rad^2), or None with more than
    ``max_frames`` frames or an indeterminate system; and the seconds they took."""
    gtsam, n = lg.gtsam, lg.n
    X = gtsam.symbol_shorthand.X
    marg = None
    tm = 0.0
    if n <= max_frames:
        t1 = time.perf_counter()
        try:
            marginals = gtsam.Marginals(graph, values)
            marg = np.empty((n, 3, 3))
            for i in range(n):
                marg[i] = marginals.marginalCovariance(X(i))[:3, :3]
        except RuntimeError as e:  # e.g. an indeterminate system: the poses stand, the marginals do not
            log.warning("marginal covariances unavailable: %s", str(e).splitlines()[0] if str(e) else e)
            marg = None
        tm = time.perf_counter() - t1
    return marg, tm


def optimize_poses(
    priors: list[np.ndarray],
    links: list[Link],
    cfg_opt: dict,
    pixel_size: float = 0.0025,
    hub: int | None = None,
    models: list[np.ndarray] | None = None,
) -> OptimizeResult:
    """Optimize all frame poses; reject outlier links (see the module docstring).

    Args:
        priors: per log, (N_k, 3) odometry poses at the frame times (metres, radians).
        links: registration links (global frame indices); only ``status == "accepted"``
            links enter the graph. Updated in place (status, reason, extra) and returned.
        cfg_opt: the ``[optimize]`` configuration table.
        pixel_size: metres per map pixel, for the residuals in pixels.
        hub: a frame standing for the published map (see
            :func:`pipeline.stages.optimize.optimize_over_map`): links from it are measured at
            frame b's centre, and it joins no outlier cluster.
        models: per log, its odometry error model ((4,), :mod:`pipeline.odometry_model`);
            None (or a None entry) = the ``[optimize]`` defaults.
    """
    import gtsam

    t0 = time.perf_counter()
    n = _check(priors, links)
    log_of = np.concatenate([np.full(len(p), k) for k, p in enumerate(priors)])
    o = _opt(cfg_opt)
    sim = pose_model(cfg_opt) == "similarity2"
    base_graph, init = _base_graph(gtsam, priors, cfg_opt, similarity=sim, models=models)
    solves = _solve_params(gtsam, cfg_opt, o)
    scales = _stage_scales(cfg_opt)
    gated = _odometry_gate(priors, links, cfg_opt, pixel_size, models)
    lg = _link_graph(gtsam, n, links, sim, hub, base_graph, o.robust_kernel.lower(), o.block_frames)
    cov_scale = map_cov_scale = 1.0
    map_var = 0.0
    if o.calibrate_link_covariance and not sim and len(lg.active) >= 8:
        cov_scale, map_cov_scale, map_var = _calibrate_covariances(lg, solves, init, priors, cfg_opt, o, models, hub)
    values, graph, factor_of = _graduated_solve(lg, solves, init, scales, o.anneal_skip_ratio)
    values, rejected = _reject_outliers(lg, solves, values, graph, factor_of, o, log_of, hub, pixel_size)
    poses, frame_scales, p4 = _extract_poses(lg, values)
    rms = _set_residuals(links, poses, p4, hub, pixel_size)
    seconds = time.perf_counter() - t0
    marg, tm = _marginals(lg, graph, values, o.marginals_max_frames)
    return OptimizeResult(poses, marg, links, rms, seconds, solves.iterations, gated + rejected, solves.passes, tm,
                          frame_scales, cov_scale, map_cov_scale, float(np.sqrt(map_var)))


def _sim_residual_px(p4: np.ndarray, links: list[Link], hub: int | None,
                     pixel_size: float) -> tuple[np.ndarray, np.ndarray]:
    """(L,) residual of each link in frame a's pixels at the overlap's centre (the midpoint of
    the two frame centres, or b's centre for a map link), and (L,) Mahalanobis distances
    squared, for (N, 4) similarity poses (as in :func:`optimize_poses` for Pose2)."""
    _, m = sim_link_residuals(p4, links)
    meas, _ = _sim_link_arrays(links)
    est = sim_between(p4[[lk.a for lk in links]], p4[[lk.b for lk in links]])
    from_hub = np.array([lk.a == hub for lk in links])[:, None]
    mid = np.where(from_hub, meas[:, :2], meas[:, :2] / 2.0)
    # The midpoint in b's nominal metres per the measurement, then back into a per the estimate.
    c, s = np.cos(meas[:, 2]), np.sin(meas[:, 2])
    d = (mid - meas[:, :2]) / np.exp(meas[:, 3:4])
    qb = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
    ce, se, ke = np.cos(est[:, 2]), np.sin(est[:, 2]), np.exp(est[:, 3])
    pa = est[:, :2] + ke[:, None] * np.column_stack([ce * qb[:, 0] - se * qb[:, 1], se * qb[:, 0] + ce * qb[:, 1]])
    disp = pa - mid
    return np.hypot(disp[:, 0], disp[:, 1]) / pixel_size, m



# Chains with a step whose translation 1-sigma exceeds this (metres: no odometry, GPS-like
# steps metres wide beside steps registered to 1e-4 rad, as with geotagged images) are solved
# with QR: Cholesky calls them indeterminate. QR costs ~5x more (20 x 20 m lawnmower: 45 s
# instead of 8 s of window fits), so chains held by odometry keep Cholesky.
QR_STEP_SIGMA_M = 0.1
# ... and when the step variances span more than this factor (whatever the units).
QR_VARIANCE_RANGE = 1.0e6


def isam_factorization(step_cov: np.ndarray) -> str:
    """'QR' when the chain's step translation variances span more than
    :data:`QR_VARIANCE_RANGE` (registered steps of millimetres beside prior steps of metres,
    or of a few pixels beside stage or GPS steps of tens: iSAM2's Cholesky then calls the
    system indeterminate), or when a step's exceeds :data:`QR_STEP_SIGMA_M` squared; else
    'CHOLESKY' (5x faster)."""
    if not len(step_cov):
        return "CHOLESKY"
    v = np.asarray(step_cov, float)[:, [0, 1], [0, 1]]
    v = v[np.isfinite(v) & (v > 0)]
    if not len(v):
        return "CHOLESKY"
    return "QR" if v.max() > QR_STEP_SIGMA_M**2 or v.max() > QR_VARIANCE_RANGE * v.min() else "CHOLESKY"


class IncrementalPoses:
    """The poses solved so far while revisits are registered window by window: a sliding
    local solve.

    Every window adds its frames (chain steps between them and from the previous frame, or a
    prior at a log start) and its accepted revisit links. Then the frames of this window and
    of the ``keep_windows`` before it (of the same log), and the earlier frames the window's
    links reach, are solved together (GTSAM's Levenberg-Marquardt from where they are) with
    every factor that touches them; every other frame is held where it was last solved. A
    factor reaching a held frame is the equivalent prior on its free end (a between factor
    from a fixed pose ``p`` measuring ``rel`` is exactly a prior at ``p + rel`` with the same
    noise). So a lane registered to its predecessor still moves the frames of the
    predecessor it links to, at a cost per window that does not grow with the path: the
    whole path in one iSAM2 kept every frame free and re-read all of them after each window,
    quadratic in the site's size (a 40 x 40 m lawnmower: 67 % of register, 3.2 GB).
    Plain Gaussian factors: a window starts within the search radius of the answer, and
    links that disagree after the solve (Mahalanobis above ``chi2``: the worst, and all
    above a quarter of the worst, up to ``max_passes`` times) are removed from this
    prediction graph only; the ``optimize`` stage decides on every link.
    """

    def __init__(self, chi2: float, max_passes: int = 3, keep_windows: int = 2, factorization: str = "CHOLESKY"):
        import gtsam

        self.gtsam = gtsam
        self.chi2 = float(chi2)
        self.max_passes = int(max_passes)
        self.keep_windows = int(keep_windows)
        self.solver = "MULTIFRONTAL_QR" if factorization == "QR" else "MULTIFRONTAL_CHOLESKY"
        self.n = 0
        self.X = gtsam.symbol_shorthand.X
        self.windows: list[int] = []  # first frames of the last windows of the current log
        self.starts: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # log start frame -> its prior (pose, sigmas)
        self.by_frame: dict[int, list[Link]] = {}  # the links kept (accepted, not dropped), by both ends

    def add_window(self, poses: np.ndarray, s: int, e: int, steps: np.ndarray, step_cov: np.ndarray,
                   links: list[Link], anchor: int | None, start_sigmas: np.ndarray,
                   prior: np.ndarray | None = None, absolute: np.ndarray | None = None) -> tuple[np.ndarray, list[int]]:
        """Add frames ``[s, e)`` (``s`` = the number of frames added so far) and solve.

        Args:
            poses: (N, 3) poses (metres, radians): frames before ``s`` as solved so far,
                ``[s, e)`` their prediction (the starting point).
            steps, step_cov: (N - 1, 3) chain steps (pose of frame k + 1 in frame k's frame)
                and (N - 1, 3, 3) their covariances in the step's components, as ``Link.cov``.
            links: the window's accepted revisit links (both ends below ``e``).
            anchor: ``s - 1`` when it belongs to the same log (tied to ``s`` by
                ``steps[s - 1]``); None at a log start, where frame ``s`` gets a prior at
                ``poses[s]`` with ``start_sigmas`` (metres, metres, radians).
            prior, absolute: (N, 3) prior poses and (N, 2) sigmas (metres, radians) of the
                frames whose prior is absolute (:mod:`pipeline.odometry_model`; NaN for the
                others): each such frame is also held at its prior pose.

        Returns:
            ``(poses (N, 3) with the solved frames replaced, indices into links removed)``.
        """
        if s != self.n:
            raise ValueError(f"windows must come in order: expected frame {self.n}, got {s}")
        if anchor is None:  # a new log: the earlier windows are another log's
            self.windows = []
            self.starts[s] = (np.array(poses[s], float), np.asarray(start_sigmas, float))
        self.windows = (self.windows + [s])[-(self.keep_windows + 1):]
        self.n = e
        recent = range(self.windows[0], e)
        out = poses.copy()
        active = list(range(len(links)))
        dropped: list[int] = []
        for n_pass in range(self.max_passes + 1):
            new = [links[i] for i in active]
            free = np.array(sorted(set(recent) | {f for lk in new for f in (lk.a, lk.b)}), int)
            out[free] = self._solve(out, free, steps, step_cov, new, prior, absolute)
            if not active or n_pass == self.max_passes:
                break
            _, m = link_residuals(out, new)
            worst = float(m.max())
            if worst <= self.chi2:
                break
            drop = [i for i, mi in zip(active, m.tolist()) if mi > max(self.chi2, worst / 4.0)]
            dropped += drop
            gone = set(drop)
            active = [i for i in active if i not in gone]
        for i in active:
            for f in {links[i].a, links[i].b}:
                self.by_frame.setdefault(f, []).append(links[i])
        return out, dropped

    def _solve(self, poses: np.ndarray, free: np.ndarray, steps: np.ndarray, step_cov: np.ndarray,
               new: list[Link], prior: np.ndarray | None, absolute: np.ndarray | None) -> np.ndarray:
        """The frames ``free`` (sorted) solved from ``poses`` (their starting point, and the
        held poses of every other frame) with every factor touching them; (len(free), 3)."""
        gtsam, X = self.gtsam, self.X
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        is_free = set(free.tolist())
        for k in free.tolist():
            values.insert(X(k), gtsam.Pose2(*poses[k]))

        def between(a: int, b: int, rel: np.ndarray, cov: np.ndarray) -> None:
            noise = gtsam.noiseModel.Gaussian.Covariance(cov)
            if a in is_free and b in is_free:
                graph.add(gtsam.BetweenFactorPose2(X(a), X(b), gtsam.Pose2(*rel), noise))
            elif b in is_free:  # a held at p: a prior on b at p + rel, the same error and noise
                graph.add(gtsam.PriorFactorPose2(X(b), gtsam.Pose2(*se2_compose(poses[a], rel)), noise))
            else:  # b held at q: a prior on a at q - rel, whose error is -Ad(rel) times the factor's
                ad = gtsam.Pose2(*rel).AdjointMap()
                graph.add(gtsam.PriorFactorPose2(X(a), gtsam.Pose2(*se2_compose(poses[b], se2_inverse(rel))),
                                                 gtsam.noiseModel.Gaussian.Covariance(ad @ cov @ ad.T)))

        # chain steps into and out of the free frames (none into a log's first frame)
        idx = np.unique(np.r_[free - 1, free])
        idx = idx[(idx >= 0) & (idx + 1 < self.n)]
        idx = np.array([k for k in idx.tolist() if k + 1 not in self.starts], int)
        if len(idx):
            for k, c in zip(idx.tolist(), local_covariance(steps[idx], step_cov[idx])):
                between(k, k + 1, steps[k], c)
        for k in free.tolist():
            if k in self.starts:
                pose, sig = self.starts[k]
                graph.add(gtsam.PriorFactorPose2(X(k), gtsam.Pose2(*pose), gtsam.noiseModel.Diagonal.Sigmas(sig)))
            if absolute is not None and prior is not None and np.isfinite(absolute[k]).all():
                sg = np.array([absolute[k, 0], absolute[k, 0], absolute[k, 1]])
                graph.add(gtsam.PriorFactorPose2(X(k), gtsam.Pose2(*prior[k]), gtsam.noiseModel.Diagonal.Sigmas(sg)))
        # the links kept that touch a free frame (each once), and the window's
        touching = {id(lk): lk for k in free.tolist() for lk in self.by_frame.get(k, ())}
        every = list(touching.values()) + list(new)
        if every:
            rel = np.array([lk.rel for lk in every], float)
            for lk, r, c in zip(every, rel, local_covariance(rel, np.array([lk.cov for lk in every], float))):
                between(lk.a, lk.b, r, c)
        params = gtsam.LevenbergMarquardtParams()
        params.setLinearSolverType(self.solver)
        params.setMaxIterations(20)
        result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
        return gtsam.utilities.extractPose2(result).reshape(-1, 3)  # in key order: free's
