"""Stage ``register``: candidate pairs from the prior, pairwise registration, links.csv.

Pairs are grouped by their first frame into tasks (each task computes that frame's
gradients once) and run as dask tasks on the configured scheduler (spawned processes by default;
OpenCV and numpy release the GIL). Every task reads the frames it needs from the frames
store itself, so tasks share nothing but read-only data.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections import Counter, OrderedDict
from functools import lru_cache
from dataclasses import replace
from pathlib import Path

import dask
import numpy as np

from mapstore.grid import interpolate_trajectory, se2_between, se2_compose, wrap_angle
from pipeline.candidates import (
    Candidates,
    ChainCovariance,
    ChainUncertainty,
    FrameTable,
    odometry_sigmas,
    revisit_candidates,
    revisit_windows,
    sequential_candidates,
    window_revisit_candidates,
)
from pipeline.progress import counter, progress
from pipeline.errors import JobFailed
from pipeline.framestore import FrameStore, dequantize, store_version
from pipeline.geometry_gate import JumpParams, frame_diagonal_m, prior_spikes
from pipeline.links import Link, components, table_links, write_links
from pipeline.parallel import dask_scheduler
from pipeline.peak_null import NullFigures, null_pairs, null_peak_z, null_threshold
from pipeline.odometry_model import inflated_table
from pipeline.prior_bias import BiasParams, PriorCorrection, calibrate_models, estimate_prior_correction, failed_runs
from pipeline.fsutil import write_text_atomic
from pipeline.optimize import pose_model
from pipeline.coarse import CoarseParams
from pipeline.registration import PreparedFrame, RegistrationParams, register_pair
from pipeline.spectrum import clear_caches
from pipeline.stages.stage import Stage, StageParams
from pipeline.stages.workspace import Workspace

log = logging.getLogger(__name__)


def prior_spike_masks(store: FrameStore, cfg_opt: dict | None = None) -> list[np.ndarray]:
    """Per log, (n,) bool: frames inside a spike of the prior (:func:`pipeline.geometry_gate.prior_spikes`
    with ``[optimize] jump_*``; none when ``cfg_opt`` is None)."""
    if cfg_opt is None:
        return [np.zeros(lf.count, bool) for lf in store.logs]
    params = JumpParams.from_config(cfg_opt)
    return [prior_spikes(np.asarray(lf.prior), np.asarray(lf.t), frame_diagonal_m(lf.valid.shape, store.pixel_size),
                         params) for lf in store.logs]


def frame_table(store: FrameStore, cfg_opt: dict | None = None) -> FrameTable:
    """The build's frames, numbered globally in log order, with their odometry priors.

    With ``cfg_opt``, frames inside a spike of the prior (:func:`prior_spike_masks`) take
    part in no pair and their prior is interpolated (in time) between the frames flanking
    the spike: the path travelled, the chain and the search radii do not see the spike (a
    1 km spike would otherwise give its neighbours' pairs search radii of kilometres).
    The optimize stage drops them (:mod:`pipeline.geometry_gate`)."""
    spikes = prior_spike_masks(store, cfg_opt)
    priors = [np.asarray(lf.prior) for lf in store.logs]
    registrable = [lf.registrable for lf in store.logs]
    for k, (lf, sp) in enumerate(zip(store.logs, spikes)):
        if sp.any():
            t = np.asarray(lf.t, float)
            p = priors[k].copy()
            p[sp] = interpolate_trajectory(np.column_stack([t[~sp], p[~sp]]), t[sp])
            priors[k] = p
            registrable[k] = np.asarray(lf.registrable, bool) & ~sp
    return FrameTable.from_priors(
        priors, [lf.valid.shape for lf in store.logs], store.pixel_size,
        [dict(lf.attrs.get("odometry_model") or {}) for lf in store.logs],
        registrable,
    )


def _frame_names(store: FrameStore, frames: np.ndarray) -> list[str]:
    """``"<log id> frame <row in its frames.csv>"`` of global frame indices."""
    offsets = np.cumsum([0] + [lf.count for lf in store.logs])
    out = []
    for g in np.asarray(frames, int).tolist():
        k = int(np.searchsorted(offsets, g, side="right") - 1)
        lf = store.logs[k]
        out.append(f"{lf.attrs['log_id']} frame {int(lf.source_index[g - offsets[k]])}")
    return out


@lru_cache(maxsize=4)
def _open_store(path: str) -> FrameStore:
    """One opened frames store per process (tasks only read it)."""
    return FrameStore(path)


class FrameReader:
    """Global frame index -> (image, valid), reading whole shards and keeping the most
    recently used ``capacity`` of them as stored (uint16: half a float copy's memory, and
    only the frames asked for are converted). Safe to share between threads (reads run
    unlocked)."""

    def __init__(self, store_path: Path, capacity: int = 8):
        self.store = _open_store(str(store_path))
        self.offsets = np.cumsum([0] + [lf.count for lf in self.store.logs])
        self.valid = [lf.valid for lf in self.store.logs]
        self.blocks: OrderedDict[tuple[int, int], np.ndarray] = OrderedDict()
        self.capacity = capacity
        self.lock = threading.Lock()
        # SIFT features per frame (the feature path), kept across tasks: each task
        # prepares its frames afresh, and detection was 60 % of a drone log's stage.
        self.features: OrderedDict[int, tuple] = OrderedDict()

    def sift(self, g: int) -> tuple | None:
        with self.lock:
            return self.features.get(g)

    def keep_sift(self, g: int, feats: tuple) -> None:
        with self.lock:
            self.features[g] = feats
            while len(self.features) > 4 * self.capacity:
                self.features.popitem(last=False)

    def log_of(self, g: int) -> int:
        return int(np.searchsorted(self.offsets, g, side="right") - 1)

    def get(self, g: int) -> tuple[np.ndarray, np.ndarray]:
        k = self.log_of(g)
        lf = self.store.logs[k]
        i = int(g - self.offsets[k])
        block = i // lf.shard_frames
        key = (k, block)
        with self.lock:
            data = self.blocks.get(key)
            if data is not None:
                self.blocks.move_to_end(key)
        if data is None:
            start = block * lf.shard_frames
            data = lf.images_uint16(start, min(start + lf.shard_frames, lf.count))
            with self.lock:
                self.blocks[key] = data
                while len(self.blocks) > self.capacity:
                    self.blocks.popitem(last=False)
        return dequantize(data[i % lf.shard_frames]), self.valid[k]


@lru_cache(maxsize=2)
def _shared_reader(path: str, version: int) -> FrameReader:
    """One frame reader per store (``version``: its metadata's modification time, so that a
    store rewritten at the same path is read afresh) and process, shared by its tasks and
    threads: the progressive revisits send many small tasks over the same lanes, which would
    otherwise each read (and, where compressed, decompress) the same shards again. 24 shards
    of 16 frames of 320 x 240 (uint16) are ~60 MB: two lanes of a 20 m lawnmower."""
    return FrameReader(Path(path), capacity=24)


def _register_task(store_path: Path, pairs: list[tuple], prior_rel: np.ndarray, params: RegistrationParams,
                   accept: dict, pixel_size: float) -> list[Link]:
    """Register ``pairs`` (rows ``a, b, overlap, radius_px, heading_sigma, heading_known``)
    from their prior relative poses ``prior_rel`` ((P, 3): b in a's frame, metres and
    radians): the pairs' own rows, not the whole prior (a task's payload is its pairs, not
    the site: 1 MB per task of a 40 x 40 m floor's revisits, ~5,000 tasks)."""
    reader = _shared_reader(str(store_path), store_version(store_path))
    prepared: dict[int, PreparedFrame] = {}
    sig: NullFigures = accept["significance"]

    def frame(g: int) -> PreparedFrame:
        # Pairs come sorted by a: a few recent frames cover every reuse.
        if g not in prepared:
            if len(prepared) >= 16:
                prepared.pop(next(iter(prepared)))
            img, valid = reader.get(g)
            prepared[g] = PreparedFrame(img, valid, params.fine_smoothing_px, features=reader.sift(g))
        return prepared[g]

    links = []
    for (a, b, overlap, radius, hsig, known), rel0 in zip(pairs, prior_rel):
        fa, fb = frame(a), frame(b)
        r = register_pair(fa, None, fb, None, rel0, pixel_size, radius, hsig, params, heading_known=known)
        for g, f in ((a, fa), (b, fb)):
            if f.has_sift:
                reader.keep_sift(g, f.sift())
        link = Link(a, b, r.rel, r.cov, r.ncc, r.uniqueness, r.overlap, r.inliers or r.pixels, r.method, gain=r.gain,
                    log_scale=r.log_scale, cov4=r.cov4)
        link.extra.update(iterations=r.iterations, radius_px=round(float(radius), 2),
                          predicted_overlap=round(float(overlap), 3), peak_z=round(float(r.peak_z), 2),
                          peak_ncc=round(float(r.peak_ncc), 3), rotation=r.rotation)
        if not r.ok:
            link.status, link.reason = "rejected", r.reason
        elif r.ncc < accept["min_ncc"]:
            link.status, link.reason = "rejected", f"low NCC: {r.ncc:.3f} (min {accept['min_ncc']})"
        elif r.method != "features" and not sig.accepts(r.peak_z, r.peak_ncc):
            link.status, link.reason = "rejected", (f"no match: correlation peak {r.peak_z:.1f} sigma "
                                                    f"(min {sig.threshold_z:.1f} for this build)"
                                                    + (f", NCC {r.peak_ncc:.2f} (min {sig.threshold_ncc:.2f})"
                                                       if np.isfinite(r.peak_ncc) else ""))
        links.append(link)
    return links


def register_candidates(store_path: Path, prior: np.ndarray, pixel_size: float, cands: Candidates, cfg: dict, *,
                        quiet: bool = False, label: str = "register", run=None,
                        significance: NullFigures | None = None) -> list[Link]:
    """Register every candidate pair near ``prior`` (N, 3); returns links (accepted and rejected) in pair order.

    ``run``: an open :func:`pipeline.parallel.dask_scheduler` (one is opened when None).
    ``significance``: the build's thresholds on the coarse peak (:func:`peak_significance`;
    default ``[register] min_peak_z`` alone).
    """
    reg = cfg["register"]
    params = RegistrationParams.from_config(reg)
    if pose_model(cfg["optimize"]) == "similarity2":
        params = replace(params, estimate_scale=True)
    sig = significance if significance is not None else null_threshold(np.zeros(0), float(reg["min_peak_z"]), 0.0,
                                                                        None, float(reg["min_peak_ncc"]))
    accept = {"min_ncc": reg["min_ncc"], "significance": sig}
    # (the pair's own early exit uses the build's thresholds too: a loose heading's pair then
    # goes on to the feature path instead of ending on a peak that noise reaches)
    params = replace(params, min_peak_z=max(params.min_peak_z, sig.threshold_z), min_peak_ncc=sig.threshold_ncc)
    rows = list(zip(cands.a.tolist(), cands.b.tolist(), cands.overlap.tolist(),
                    cands.radius_px.tolist(), cands.heading_sigma.tolist(), cands.heading_known.tolist()))
    workers = reg["workers"] or os.cpu_count() or 1
    # At most pairs_per_task per task, and at least two tasks per worker when there are few
    # pairs (a window of revisits), so that no worker idles.
    size = max(min(int(reg["pairs_per_task"]), -(-len(rows) // (2 * workers))), 1)
    rel = se2_between(prior[cands.a], prior[cands.b])
    tasks = [dask.delayed(_register_task)(store_path, rows[i : i + size], rel[i : i + size], params, accept, pixel_size)
             for i in range(0, len(rows), size)]
    links: list[Link] = []

    def go(run) -> None:
        # all tasks in one go, the bar moved as each ends (batches were barriers)
        with counter(len(tasks), label=label, unit="tasks", quiet=quiet) as bar:
            for part in run(tasks, done=bar.advance):
                links.extend(table_links(part))  # (held through the revisits: see table_links)

    if run is not None:
        go(run)
    else:  # (auto, decided per build by register_plan, is threads for a lone call)
        with dask_scheduler("threads" if reg["scheduler"] == "auto" else reg["scheduler"], workers) as r:
            go(r)
    return links


def chain_steps(frames: FrameTable, links: list[Link], cfg_opt: dict,
                gate_sigmas: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The chain's steps between consecutive frames: the accepted link ``k -> k + 1`` where
    it agrees with the odometry step within ``gate_sigmas`` of the odometry's uncertainty,
    the odometry step elsewhere.

    Returns ``(steps (N - 1, 3), cov (N - 1, 3, 3), linked (N - 1,))``: ``steps[k]`` the
    pose of frame k + 1 in frame k's frame (metres, radians), its covariance, and whether a
    link holds it. A held step is the link fused with the odometry step (inverse-covariance
    weighted: the link decides where it is the sharper, e.g. translation on a floor, the
    odometry where it is, e.g. the heading of a stage that cannot rotate); a step without a
    link is the odometry's, with its diagonal covariance from the error model. Steps across
    a log boundary are meaningless.
    """
    step_link = {}
    for lk in links:
        if lk.status == "accepted" and lk.b == lk.a + 1:
            step_link[lk.b] = lk
    odo_step = se2_between(frames.prior[:-1], frames.prior[1:])
    dist = np.hypot(odo_step[:, 0], odo_step[:, 1])
    sig_t, sig_h = odometry_sigmas(dist, cfg_opt, frames.models(cfg_opt)[1:])
    steps = odo_step.copy()
    cov = np.zeros((len(steps), 3, 3))
    cov[:, 0, 0] = cov[:, 1, 1] = sig_t**2
    cov[:, 2, 2] = sig_h**2
    linked = np.zeros(len(steps), bool)
    for k, lk in step_link.items():
        d = lk.rel - odo_step[k - 1]
        if np.hypot(d[0], d[1]) <= gate_sigmas * sig_t[k - 1] and abs(d[2]) <= gate_sigmas * sig_h[k - 1]:
            steps[k - 1], cov[k - 1] = _fuse(lk.rel, lk.cov, odo_step[k - 1], cov[k - 1])
            linked[k - 1] = True
    return steps, cov, linked


def _fuse(m1: np.ndarray, c1: np.ndarray, m2: np.ndarray, c2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Inverse-covariance weighted mean of two estimates of one relative pose (3,) with
    covariances (3, 3); the heading difference is wrapped (the two are close)."""
    try:
        i1, i2 = np.linalg.inv(c1), np.linalg.inv(c2)
        cov = np.linalg.inv(i1 + i2)
    except np.linalg.LinAlgError:
        return np.asarray(m1, float), np.asarray(c1, float)
    d2 = np.asarray(m2, float) - m1
    d2[2] = wrap_angle(d2[2])
    return np.asarray(m1, float) + cov @ (i2 @ d2), cov


def _compose_chain(frames: FrameTable, steps: np.ndarray, restart: np.ndarray | None = None) -> np.ndarray:
    """Dead reckoning along ``steps``; at frames where ``restart`` (N,) is True the chain
    starts again from the prior pose (see :func:`chain_restarts`)."""
    chain = frames.prior.copy()
    for k in range(1, len(chain)):
        if frames.log[k] == frames.log[k - 1] and not (restart is not None and restart[k]):
            chain[k] = se2_compose(chain[k - 1], steps[k - 1])
    return chain


def chain_restarts(frames: FrameTable, linked: np.ndarray, cfg_opt: dict) -> np.ndarray | None:
    """(N,) True at the frames of logs with an absolute prior (a stage, GPS:
    :mod:`pipeline.odometry_model`) whose step from the previous frame no link holds: there
    the prior pose predicts the frame better than chaining the prior's step, whose error
    would add to everything before it. None when no log's prior is absolute."""
    absolute = frames.models(cfg_opt)[:, 4] > 0.5
    if not absolute.any():
        return None
    return absolute & np.r_[True, ~np.asarray(linked, bool)]


def chain_from_links(frames: FrameTable, links: list[Link], cfg_opt: dict, gate_sigmas: float) -> tuple[np.ndarray, ChainUncertainty]:
    """Dead reckoning along accepted links between consecutive frames, odometry elsewhere.

    A link is used only when it agrees with the odometry step within ``gate_sigmas`` of the
    odometry's uncertainty, so that one wrong link cannot throw the chain (and every revisit
    predicted from it) off; the optimizer still sees every link.

    Returns the chain poses (N, 3) and their step-wise uncertainty.
    """
    steps, cov, linked = chain_steps(frames, links, cfg_opt, gate_sigmas)
    # A link's translation variance is its trace; the odometry's (error gradient x step)^2.
    var_t = np.r_[0.0, np.where(linked, cov[:, 0, 0] + cov[:, 1, 1], cov[:, 0, 0])]
    var_h = np.r_[0.0, cov[:, 2, 2]]
    return _compose_chain(frames, steps, chain_restarts(frames, linked, cfg_opt)), ChainUncertainty.from_steps(frames, var_t, var_h)


def chain_covariance(frames: FrameTable, chain: np.ndarray, step_cov: np.ndarray,
                     linked: np.ndarray) -> ChainCovariance:
    """:class:`ChainCovariance` of the chain from :func:`chain_steps`' covariances."""
    var_t = np.r_[0.0, np.where(linked, step_cov[:, 0, 0] + step_cov[:, 1, 1], step_cov[:, 0, 0])]
    return ChainCovariance.from_steps(frames, chain[:, :2], var_t, np.r_[0.0, step_cov[:, 2, 2]])


# How much wider a revisit that found no match is searched again (see progressive_revisits).
REVISIT_RETRY_GROWTH = 4.0


def progressive_revisits(store_path: Path, frames: FrameTable, chain: np.ndarray, steps: np.ndarray,
                         step_cov: np.ndarray, linked: np.ndarray, cfg: dict, run, *,
                         quiet: bool = False, significance: NullFigures | None = None
                         ) -> tuple[list[Link], np.ndarray, dict]:
    """Revisit links window by window along the path (``[register] revisit_window_m``).

    For each window ``[s, e)``: its frames are predicted along the chain from the solved pose
    of frame ``s - 1``; revisit pairs whose later frame lies in the window are registered
    with search radii from the uncertainty since the last frame revisit links hold
    (:func:`pipeline.candidates.window_revisit_candidates`); then the window and the two
    before it are re-solved with the window's chain and accepted revisit links added, the
    frames before them held (:class:`pipeline.optimize.IncrementalPoses`). The chain's error
    thus never accumulates beyond one window, however long the path, and a window costs the
    same wherever it lies on the path.

    Returns ``(links, solved poses (N, 3), figures)``.
    """
    from pipeline.optimize import IncrementalPoses, isam_factorization

    reg, opt = cfg["register"], cfg["optimize"]
    cc = chain_covariance(frames, chain, step_cov, linked)
    est = chain.copy()
    solver = IncrementalPoses(float(opt["outlier_chi2"]), factorization=isam_factorization(step_cov))
    held = np.full(int(frames.log.max()) + 1, -1)
    links: list[Link] = []
    windows = revisit_windows(frames, float(reg["revisit_window_m"]), opt)
    t_fit = 0.0
    dropped = 0
    radii = []
    start_sig = np.array([opt["log_start_sigma_m"], opt["log_start_sigma_m"], opt["log_start_sigma_rad"]], float)
    gauge = np.array([opt["anchor_sigma_m"], opt["anchor_sigma_m"], opt["anchor_sigma_rad"]], float)
    restart = chain_restarts(frames, linked, opt)
    # (frames joined by held chain steps and accepted revisit links: see window_revisit_candidates)
    held_steps = np.flatnonzero(linked)
    joined = np.stack([held_steps, held_steps + 1], axis=1)
    models = frames.models(opt)
    absolute = np.where((models[:, 4] > 0.5)[:, None], models[:, [1, 3]] / np.sqrt(2.0), np.nan)
    if not np.isfinite(absolute).any():
        absolute = None
    for s, e in progress(windows, length=len(windows), label="register revisits", quiet=quiet):
        k = int(frames.log[s])
        anchor = s - 1 if s > 0 and frames.log[s - 1] == k else None
        if anchor is not None:
            # The window's frames along the chain from the solved pose of frame s - 1 (up
            # to where the chain restarts from the prior: an absolute prior's unlinked step).
            stop = e
            if restart is not None and restart[s:e].any():
                stop = s + int(np.argmax(restart[s:e]))
            est[s:stop] = se2_compose(est[anchor], se2_between(chain[anchor], chain[s:stop]))
        cands = window_revisit_candidates(frames, est, s, e, held, cc, reg, opt,
                                          components(len(est), *joined.T) if absolute is not None else None)
        radii.append(cands.radius_px)
        new = (register_candidates(store_path, est, frames.pixel_size, cands, cfg, quiet=True, run=run,
                                   significance=significance) if len(cands) else [])
        # A prediction is only as good as the links' covariances, which on real images can
        # be far too sharp (a lens's distortion: links good to ~1 px claim 0.01 px, and a
        # chain of them predicted tile-grid revisits 2-3 px off with radii of 4 px): a
        # revisit that finds no match is searched once more, REVISIT_RETRY_GROWTH times
        # wider.
        # (never wider than the prior alone allows: from the log's start, or for an
        # absolute prior two of its poses)
        if len(cands):
            sig_prior, _ = cc.since(frames, np.full(len(cands), -1), cands.b, opt)
            cap = float(reg["search_sigmas"]) * sig_prior / frames.pixel_size + float(reg["search_floor_px"])
            grown = np.minimum(REVISIT_RETRY_GROWTH * cands.radius_px + 2.0 * float(reg["search_floor_px"]), cap)
        retry = np.array([lk.status != "accepted" and lk.reason.startswith(("no match", "ambiguous"))
                          for lk in new], bool)
        if retry.any():
            retry &= grown > 1.5 * cands.radius_px
        if retry.any():
            wide = cands.subset(retry)
            wide.radius_px = grown[retry]
            again = iter(register_candidates(store_path, est, frames.pixel_size, wide, cfg, quiet=True, run=run,
                                             significance=significance))
            new = [next(again) if r else lk for lk, r in zip(new, retry.tolist())]
        links += new
        acc = [lk for lk in new if lk.status == "accepted"]
        t0 = time.perf_counter()
        try:
            est, drop = solver.add_window(est, s, e, steps, step_cov, acc, anchor,
                                          gauge if (anchor is None and k == 0 and absolute is None) else start_sig,
                                          frames.prior, absolute)
        except RuntimeError as exc:  # gtsam's IndeterminateLinearSystemException
            if "Indeterminate" not in str(exc):
                raise
            raise JobFailed(f"register: the pose graph of frames {s}..{e - 1} is singular (GTSAM: indeterminate "
                            "system); two logs with identical frames (the same simulator seed) cause this") from None
        t_fit += time.perf_counter() - t0
        dropped += len(drop)
        gone = set(drop)
        joined = np.vstack([joined] + [np.array([[lk.a, lk.b]]) for i, lk in enumerate(acc) if i not in gone])
        ends = [f for i, lk in enumerate(acc) if i not in gone for f in (lk.a, lk.b) if s <= f < e]
        if ends:
            held[k] = max(ends)
    r = np.concatenate(radii) if radii else np.zeros(0)
    figures = {
        "passes": len(windows),
        "window_fit_seconds": t_fit,
        "window_fit_dropped": dropped,
        "revisit_radius_px_median": float(np.median(r)) if len(r) else 0.0,
        "revisit_radius_px_p95": float(np.percentile(r, 95)) if len(r) else 0.0,
    }
    return links, est, figures


def correct_prior(store_path: Path, frames: FrameTable, seq: Candidates, links: list[Link], cfg: dict, run,
                  significance: NullFigures) -> tuple[PriorCorrection | None, dict]:
    """A prior biased for a whole run (:mod:`pipeline.prior_bias`), from the sequential links.

    Sequential pairs that failed in a run of consecutive frames are first searched again
    with a wide radius (twice the step the prior predicts, plus the usual radius: a lane
    whose prior heading is flipped by pi is predicted a step backwards), so that such a run
    has links to show its bias. Returns the correction (None with ``[register]
    prior_correction = false``) and the report's figures.
    """
    reg, opt = cfg["register"], cfg["optimize"]
    if not reg["prior_correction"]:
        return None, {"enabled": False}
    bp = BiasParams.from_config(reg)
    ok = np.array([lk.status == "accepted" for lk in links], bool)
    far: list[Link] = []
    if len(seq):
        retry = failed_runs(seq.a, seq.b, ok, frames.log, bp.min_run_frames) & frames.pairable(seq.a, seq.b)
        if retry.any():
            wide = seq.subset(retry)
            step = np.hypot(*se2_between(frames.prior[wide.a], frames.prior[wide.b])[:, :2].T) / frames.pixel_size
            wide.radius_px = wide.radius_px + 2.0 * step + float(reg["search_floor_px"])
            far = register_candidates(store_path, frames.prior, frames.pixel_size, wide, cfg, quiet=True, run=run,
                                      significance=significance)
    absolute = frames.models(opt)[:, 4] > 0.5
    corr = estimate_prior_correction(frames.prior, frames.log, absolute, links + far, frames.pixel_size, bp)
    figures = {"enabled": True, "pairs_searched_wide": len(far),
               "pairs_found_wide": sum(lk.status == "accepted" for lk in far), **corr.to_dict()}
    return corr, figures


def write_prior(path: Path, prior: np.ndarray) -> None:
    """The prior poses the build used (after :func:`correct_prior`): ``frame,x,y,theta``
    (global frame index, metres, radians), full precision."""
    lines = ["frame,x,y,theta"] + [f"{g},{x!r},{y!r},{t!r}" for g, (x, y, t) in enumerate(prior.tolist())]
    write_text_atomic(path, "\n".join(lines) + "\n")


def read_prior(path: Path, n: int) -> np.ndarray | None:
    """:func:`write_prior`'s poses (n, 3), or None when the file is absent."""
    if not path.exists():
        return None
    d = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    if d.shape != (n, 4):
        raise JobFailed(f"{path}: {d.shape[0]} prior poses for {n} frames (a stale work directory?)")
    return d[:, 1:]


def _null_task(store_path: Path, pairs: list[tuple[int, int]], rel: np.ndarray, radius: np.ndarray,
               pixel_size: float, coarse: CoarseParams) -> tuple[np.ndarray, np.ndarray]:
    reader = _shared_reader(str(store_path), store_version(store_path))
    return null_peak_z(reader.get, pairs, rel, radius, pixel_size, coarse)


def peak_significance(store_path: Path, frames: FrameTable, cands: Candidates, reg: dict, run=None) -> NullFigures:
    """The build's threshold on a link's correlation peak significance, from null pairs of
    this build's own frames (:mod:`pipeline.peak_null`): ``[register] peak_null_pairs`` of
    them, or none (the configured ``min_peak_z`` alone) when that is 0; and the same for the
    band-passed NCC of answers told apart from peaks of their height (floor ``min_peak_ncc``).
    ``run``: an open :func:`pipeline.parallel.dask_scheduler` (the pairs are shared among its
    workers), None = here."""
    count = min(int(reg["peak_null_pairs"]), max(int(reg["peak_null_min_pairs"]), len(cands) // 3))
    floor = float(reg["min_peak_z"])
    if count <= 0 or len(cands) == 0:
        return null_threshold(np.zeros(0), floor, 0.0, None, float(reg["min_peak_ncc"]))
    shapes = np.array([frames.shapes[k] for k in frames.log], float)
    pairs = null_pairs(frames.prior, shapes, frames.pixel_size, cands.a, count, float(reg["peak_null_far_diagonals"]),
                       eligible=frames.registrable)
    rel = np.array([se2_between(frames.prior[cands.a[i]], frames.prior[cands.b[i]]) for i, _ in pairs]).reshape(-1, 3)
    radius = np.array([cands.radius_px[i] for i, _ in pairs])
    ac = [(int(cands.a[i]), c) for i, c in pairs]
    coarse = RegistrationParams.from_config(reg).coarse
    if run is None:
        z, ncc = null_peak_z(FrameReader(store_path).get, ac, rel, radius, frames.pixel_size, coarse)
    else:
        workers = reg["workers"] or os.cpu_count() or 1
        size = max(-(-len(ac) // (2 * workers)), 1)
        parts = run([dask.delayed(_null_task)(store_path, ac[i : i + size], rel[i : i + size], radius[i : i + size],
                                              frames.pixel_size, coarse) for i in range(0, len(ac), size)])
        z = np.concatenate([p[0] for p in parts]) if parts else np.zeros(0)
        ncc = np.concatenate([p[1] for p in parts]) if parts else np.zeros(0)
    return null_threshold(z, floor, float(reg["peak_null_sigmas"]), ncc, float(reg["min_peak_ncc"]))


def register_plan(reg: dict, frames: FrameTable) -> tuple[str, int]:
    """Where register runs: ``(scheduler, workers)`` from ``[register] scheduler`` and
    ``workers`` (0 = one per core).

    ``auto``: frames of ``threads_min_frame_px`` pixels or more (median over the frames)
    on threads, one per core (their time is in OpenCV and numpy, which release the
    interpreter: 1.7x one thread's rate on 1024 px tiles); smaller frames, whose pairs are
    mostly Python between short OpenCV calls (two threads were slower than one), on worker
    processes, one per core, when the build has ``processes_min_frames`` frames or more
    (2 processes: 1.72x one thread on a 10 x 10 m floor of 320 x 240 frames; starting them
    costs ~2-3 s), else one thread. ``threads`` with workers 0: one per core for large
    frames, one thread for small ones. Other schedulers: one worker per core.
    """
    cores = os.cpu_count() or 1
    sched = reg["scheduler"]
    if sched not in ("threads", "auto") or not len(frames.log):
        return ("threads" if sched == "auto" else sched), int(reg["workers"]) or cores
    px = float(np.median([frames.shapes[k][0] * frames.shapes[k][1] for k in frames.log]))
    if px >= reg["threads_min_frame_px"]:
        return "threads", int(reg["workers"]) or cores
    if sched == "auto" and reg["workers"] != 1 and cores > 1 and len(frames.log) >= reg["processes_min_frames"]:
        return "processes", int(reg["workers"]) or cores
    return "threads", int(reg["workers"]) or 1


def run_register(ws: Workspace, params: StageParams) -> dict:
    """Stage entry: :func:`register_frames` over the build's published base; the report's
    ``links`` and ``registration`` sections."""
    counts = register_frames(ws, params.cfg, quiet=params.quiet, base=params.build.base)
    return {"links": {k: counts[k] for k in ("candidates", "accepted", "rejected")}, "registration": counts}


def register_frames(ws: Workspace, cfg: dict, *, quiet: bool = False, base: dict | None = None) -> dict:
    """Candidates and links for the frames store (``ws.frames_store``); returns the counts.

    Two rounds: sequential pairs from the odometry prior; then revisits, progressively
    (window by window along the path, :func:`progressive_revisits`; ``[register]
    progressive_revisits``) or in one round predicted from the chain of sequential links
    (always over a published map, whose links already hold the chain). With ``base`` (``{"url", "snapshot"}`` of a published
    map version) a third round registers the frames to that map (:mod:`pipeline.anchor`)
    and writes ``map_links.csv``.
    """
    t0 = time.perf_counter()
    store_path = ws.frames_store
    store = FrameStore(store_path)
    reg, opt = cfg["register"], cfg["optimize"]
    frames = frame_table(store, opt)
    spikes = np.concatenate(prior_spike_masks(store, opt)) if len(frames.prior) else np.zeros(0, bool)
    if spikes.any():
        log.warning("register: %d frame(s) whose odometry jumps off the path faster than the log's speed cap "
                    "are left out of registration (e.g. %s)", int(spikes.sum()),
                    ", ".join(_frame_names(store, np.flatnonzero(spikes)[:5])))
    seq = sequential_candidates(frames, reg, opt)
    # the scheduler and worker count decided once; every task sizing below reads them from cfg
    sched, n_workers = register_plan(reg, frames)
    reg = dict(reg, scheduler=sched, workers=n_workers)
    cfg = dict(cfg, register=reg)
    workers = reg["workers"]
    extra_cols = ("iterations", "radius_px", "predicted_overlap", "peak_z", "peak_ncc", "rotation")
    map_counts: dict = {}
    passes: dict = {"passes": 1}
    with dask_scheduler(reg["scheduler"], workers) as run:
        t1 = time.perf_counter()
        null = peak_significance(store_path, frames, seq, reg, run)
        links = register_candidates(store_path, frames.prior, frames.pixel_size, seq, cfg, quiet=quiet,
                                    label="register sequential", run=run, significance=null)
        correction, prior_figures = correct_prior(store_path, frames, seq, links, cfg, run, null)
        if correction is not None and correction.any:
            # The prior was biased: its corrected poses from here on, and the sequential
            # pairs that touch a corrected frame registered again from them.
            frames = replace(frames, prior=correction.prior)
            redo = correction.changed[seq.a] | correction.changed[seq.b]
            again = register_candidates(store_path, frames.prior, frames.pixel_size, seq.subset(redo), cfg,
                                        quiet=True, run=run, significance=null)
            it = iter(again)
            links = [next(it) if r else lk for lk, r in zip(links, redo.tolist())]
            prior_figures["pairs_registered_again"] = int(redo.sum())
        if correction is not None:
            # A prior noisier than its error model (e.g. a wandering compass heading): its
            # sigmas grow to what the links show, so that the odometry gate and the
            # optimizer weigh it for what it is; failed sequential pairs are tried again
            # with the wider search that follows.
            grown = calibrate_models(frames.prior, frames.log, frames.models(opt), links,
                                     float(reg["prior_noise_tolerance"]), BiasParams.from_config(reg).min_scale_links)
            if grown:
                tables = list(frames.odometry_tables or [{} for _ in frames.shapes])
                for g in grown:
                    tables[g["log"]] = inflated_table(opt, tables[g["log"]], g["translation"], g["heading"])
                frames = replace(frames, odometry_tables=tables)
                seq2 = sequential_candidates(frames, reg, opt)
                failed = {(lk.a, lk.b) for lk in links if lk.status != "accepted"}
                retry = np.array([(a, b) in failed for a, b in zip(seq2.a.tolist(), seq2.b.tolist())], bool)
                if retry.any():
                    again = register_candidates(store_path, frames.prior, frames.pixel_size, seq2.subset(retry), cfg,
                                                quiet=True, run=run, significance=null)
                    by_pair = {(lk.a, lk.b): lk for lk in again}
                    links = [by_pair.get((lk.a, lk.b), lk) for lk in links]
                prior_figures["noisier_than_model"] = grown
        write_prior(ws.register_prior, frames.prior)
        write_text_atomic(ws.register_models, json.dumps(frames.odometry_tables or [], indent=1) + "\n")
        chain, unc = chain_from_links(frames, links, opt, reg["chain_gate_sigmas"])
        progressive = reg["progressive_revisits"] and base is None
        if base is not None:
            # Over a published map: anchor the chain to it first, so that revisits are
            # predicted from map-held poses (search radii of pixels, not of the drift).
            from pipeline.anchor import anchored_chain, open_map_view, register_to_map

            t2 = time.perf_counter()
            map_links, outside = register_to_map(FrameReader(store_path), frames, chain,
                                                 open_map_view(base["url"], base["snapshot"]), cfg, quiet=quiet,
                                                 names=[str(lf.attrs["log_id"]) for lf in store.logs],
                                                 map_name=str(base["url"]))
            write_links(ws.register_map_links, map_links, extra_cols)
            chain, unc = anchored_chain(frames, chain, map_links, unc, opt)
            map_counts = {
                "map_candidates": len(map_links),
                "map_accepted": sum(lk.status == "accepted" for lk in map_links),
                "map_outside": outside,
                "map_seconds": time.perf_counter() - t2,
            }
        if progressive:
            steps, step_cov, linked = chain_steps(frames, links, opt, reg["chain_gate_sigmas"])
            rev_links, _, passes = progressive_revisits(store_path, frames, chain, steps, step_cov, linked, cfg, run,
                                                        quiet=quiet, significance=null)
            n_rev = len(rev_links)
            links += rev_links
        else:
            rev = revisit_candidates(frames, chain, unc, reg, opt)
            n_rev = len(rev)
            links += register_candidates(store_path, chain, frames.pixel_size, rev, cfg, quiet=quiet,
                                         label="register revisits", run=run, significance=null)
    seconds_reg = time.perf_counter() - t1 - map_counts.get("map_seconds", 0.0)
    _shared_reader.cache_clear()  # this process's decoded shards and features: not needed after the stage
    clear_caches()  # (and its spectra's layouts: see pipeline.spectrum.clear_caches)
    write_links(ws.register_links, links, extra_cols)
    accepted = sum(lk.status == "accepted" for lk in links)
    reasons = Counter(lk.reason.split(":")[0] for lk in links if lk.status != "accepted")
    return {
        **map_counts,
        "frames": int(len(frames.prior)),
        "candidates": len(links),
        "sequential_candidates": len(seq),
        "revisit_candidates": n_rev,
        "accepted": accepted,
        "rejected": len(links) - accepted,
        "rejection_reasons": dict(reasons.most_common()),
        "feature_path": sum(lk.method == "features" for lk in links),
        "peak_null": null.to_dict(),
        "prior": prior_figures,
        "prior_spikes": _frame_names(store, np.flatnonzero(spikes)[:200]),
        **passes,
        "pairs_per_s": len(links) / seconds_reg if seconds_reg > 0 else 0.0,
        "seconds": time.perf_counter() - t0,
    }


STAGE = Stage("register", run_register, params_tables=("register", "optimize"), reads_base=True)
