"""Stage ``register``: candidate pairs from the prior, pairwise registration, links.csv.

Pairs are grouped by their first frame into tasks (each task computes that frame's
gradients once) and run as dask tasks on the configured scheduler (spawned processes by default;
OpenCV and numpy release the GIL). Every task reads the frames it needs from the frames
store itself, so tasks share nothing but read-only data.
"""

from __future__ import annotations

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

from mapstore.grid import se2_between, se2_compose
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
from pipeline.cli_common import progress
from pipeline.errors import JobFailed
from pipeline.framestore import STORE_NAME, FrameStore, store_version
from pipeline.links import Link, write_links
from pipeline.parallel import dask_scheduler
from pipeline.optimize import pose_model
from pipeline.registration import PreparedFrame, RegistrationParams, register_pair

log = logging.getLogger(__name__)

LINKS_FILE = "links.csv"


def frame_table(store: FrameStore) -> FrameTable:
    """The build's frames, numbered globally in log order, with their odometry priors."""
    return FrameTable.from_priors(
        [lf.prior for lf in store.logs], [lf.valid.shape for lf in store.logs], store.pixel_size
    )


@lru_cache(maxsize=4)
def _open_store(path: str) -> FrameStore:
    """One opened frames store per process (tasks only read it)."""
    return FrameStore(path)


class FrameReader:
    """Global frame index -> (image, valid), reading whole shards and keeping the most
    recently used ``capacity`` of them. Safe to share between threads (reads run unlocked)."""

    def __init__(self, store_path: Path, capacity: int = 8):
        self.store = _open_store(str(store_path))
        self.offsets = np.cumsum([0] + [lf.count for lf in self.store.logs])
        self.valid = [lf.valid for lf in self.store.logs]
        self.blocks: OrderedDict[tuple[int, int], np.ndarray] = OrderedDict()
        self.capacity = capacity
        self.lock = threading.Lock()

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
            data = lf.images(start, min(start + lf.shard_frames, lf.count))
            with self.lock:
                self.blocks[key] = data
                while len(self.blocks) > self.capacity:
                    self.blocks.popitem(last=False)
        return data[i % lf.shard_frames], self.valid[k]


@lru_cache(maxsize=2)
def _shared_reader(path: str, version: int) -> FrameReader:
    """One frame reader per store (``version``: its metadata's modification time, so that a
    store rewritten at the same path is read afresh) and process, shared by its tasks and
    threads: the progressive revisits send many small tasks over the same lanes, which would
    otherwise each read (and decompress) the same shards again. 24 shards of 16 frames of
    320 x 240 (float32) are ~120 MB: two lanes of a 20 m lawnmower."""
    return FrameReader(Path(path), capacity=24)


def _register_task(store_path: Path, prior: np.ndarray, pairs: list[tuple], params: RegistrationParams,
                   accept: dict, pixel_size: float) -> list[Link]:
    reader = _shared_reader(str(store_path), store_version(store_path))
    prepared: dict[int, PreparedFrame] = {}

    def frame(g: int) -> PreparedFrame:
        # Pairs come sorted by a: a few recent frames cover every reuse.
        if g not in prepared:
            if len(prepared) >= 16:
                prepared.pop(next(iter(prepared)))
            img, valid = reader.get(g)
            prepared[g] = PreparedFrame(img, valid, params.fine_smoothing_px)
        return prepared[g]

    links = []
    for a, b, overlap, radius, hsig in pairs:
        prior_rel = se2_between(prior[a], prior[b])
        r = register_pair(frame(a), None, frame(b), None, prior_rel, pixel_size, radius, hsig, params)
        link = Link(a, b, r.rel, r.cov, r.ncc, r.uniqueness, r.overlap, r.inliers or r.pixels, r.method, gain=r.gain,
                    log_scale=r.log_scale, cov4=r.cov4)
        link.extra.update(iterations=r.iterations, radius_px=round(float(radius), 2),
                          predicted_overlap=round(float(overlap), 3))
        if not r.ok:
            link.status, link.reason = "rejected", r.reason
        elif r.ncc < accept["min_ncc"]:
            link.status, link.reason = "rejected", f"low NCC: {r.ncc:.3f} (min {accept['min_ncc']})"
        elif r.method != "features" and r.uniqueness < accept["min_uniqueness"]:
            # (A feature-path link is already verified by its RANSAC inliers; on smooth
            # texture the short correlation search after it has no second peak to compare.)
            link.status, link.reason = "rejected", f"ambiguous: uniqueness C1-C2 {r.uniqueness:.3f} (min {accept['min_uniqueness']})"
        links.append(link)
    return links


def register_candidates(store_path: Path, prior: np.ndarray, pixel_size: float, cands: Candidates, cfg: dict, *,
                        quiet: bool = False, label: str = "register", run=None) -> list[Link]:
    """Register every candidate pair near ``prior`` (N, 3); returns links (accepted and rejected) in pair order.

    ``run``: an open :func:`pipeline.parallel.dask_scheduler` (one is opened when None).
    """
    reg = cfg["register"]
    params = RegistrationParams.from_config(reg)
    if pose_model(cfg["optimize"]) == "similarity2":
        params = replace(params, estimate_scale=True)
    accept = {"min_ncc": reg["min_ncc"], "min_uniqueness": reg["min_uniqueness"]}
    rows = list(zip(cands.a.tolist(), cands.b.tolist(), cands.overlap.tolist(),
                    cands.radius_px.tolist(), cands.heading_sigma.tolist()))
    workers = reg["workers"] or os.cpu_count() or 1
    # At most pairs_per_task per task, and at least two tasks per worker when there are few
    # pairs (a window of revisits), so that no worker idles.
    size = max(min(int(reg["pairs_per_task"]), -(-len(rows) // (2 * workers))), 1)
    chunks = [rows[i : i + size] for i in range(0, len(rows), size)]
    tasks = [dask.delayed(_register_task)(store_path, prior, c, params, accept, pixel_size) for c in chunks]
    links: list[Link] = []
    # Batches of tasks, so that the progress bar moves while dask works.
    batch = max(workers * 4, 1)

    def go(run) -> None:
        for i in progress(range(0, len(tasks), batch), length=(len(tasks) + batch - 1) // batch,
                          label=label, quiet=quiet):
            for part in run(tasks[i : i + batch]):
                links.extend(part)

    if run is not None:
        go(run)
    else:
        with dask_scheduler(reg["scheduler"], workers) as r:
            go(r)
    return links


def chain_steps(frames: FrameTable, links: list[Link], cfg_opt: dict,
                gate_sigmas: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The chain's steps between consecutive frames: the accepted link ``k -> k + 1`` where
    it agrees with the odometry step within ``gate_sigmas`` of the odometry's uncertainty,
    the odometry step elsewhere.

    Returns ``(steps (N - 1, 3), cov (N - 1, 3, 3), linked (N - 1,))``: ``steps[k]`` the
    pose of frame k + 1 in frame k's frame (metres, radians), its covariance (the link's, or
    the odometry's diagonal from the error gradient), and whether a link holds it. Steps
    across a log boundary are meaningless.
    """
    step_link = {}
    for lk in links:
        if lk.status == "accepted" and lk.b == lk.a + 1:
            step_link[lk.b] = lk
    odo_step = se2_between(frames.prior[:-1], frames.prior[1:])
    dist = np.hypot(odo_step[:, 0], odo_step[:, 1])
    sig_t, sig_h = odometry_sigmas(dist, cfg_opt)
    steps = odo_step.copy()
    cov = np.zeros((len(steps), 3, 3))
    cov[:, 0, 0] = cov[:, 1, 1] = sig_t**2
    cov[:, 2, 2] = sig_h**2
    linked = np.zeros(len(steps), bool)
    for k, lk in step_link.items():
        d = lk.rel - odo_step[k - 1]
        if np.hypot(d[0], d[1]) <= gate_sigmas * sig_t[k - 1] and abs(d[2]) <= gate_sigmas * sig_h[k - 1]:
            steps[k - 1] = lk.rel
            cov[k - 1] = lk.cov
            linked[k - 1] = True
    return steps, cov, linked


def _compose_chain(frames: FrameTable, steps: np.ndarray) -> np.ndarray:
    chain = frames.prior.copy()
    for k in range(1, len(chain)):
        if frames.log[k] == frames.log[k - 1]:
            chain[k] = se2_compose(chain[k - 1], steps[k - 1])
    return chain


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
    return _compose_chain(frames, steps), ChainUncertainty.from_steps(frames, var_t, var_h)


def chain_covariance(frames: FrameTable, chain: np.ndarray, step_cov: np.ndarray,
                     linked: np.ndarray) -> ChainCovariance:
    """:class:`ChainCovariance` of the chain from :func:`chain_steps`' covariances."""
    var_t = np.r_[0.0, np.where(linked, step_cov[:, 0, 0] + step_cov[:, 1, 1], step_cov[:, 0, 0])]
    return ChainCovariance.from_steps(frames, chain[:, :2], var_t, np.r_[0.0, step_cov[:, 2, 2]])


def progressive_revisits(store_path: Path, frames: FrameTable, chain: np.ndarray, steps: np.ndarray,
                         step_cov: np.ndarray, linked: np.ndarray, cfg: dict, run, *,
                         quiet: bool = False) -> tuple[list[Link], np.ndarray, dict]:
    """Revisit links window by window along the path (``[register] revisit_window_m``).

    For each window ``[s, e)``: its frames are predicted along the chain from the solved pose
    of frame ``s - 1``; revisit pairs whose later frame lies in the window are registered
    with search radii from the uncertainty since the last frame revisit links hold
    (:func:`pipeline.candidates.window_revisit_candidates`); then every pose so far is
    re-solved with the window's chain and accepted revisit links added
    (:class:`pipeline.optimize.IncrementalPoses`, iSAM2). The chain's error thus never
    accumulates beyond one window, however long the path.

    Returns ``(links, solved poses (N, 3), figures)``.
    """
    from pipeline.optimize import IncrementalPoses, isam_factorization

    reg, opt = cfg["register"], cfg["optimize"]
    cc = chain_covariance(frames, chain, step_cov, linked)
    est = chain.copy()
    solver = IncrementalPoses(float(opt["outlier_chi2"]), factorization=isam_factorization(step_cov))
    held = np.full(int(frames.log.max()) + 1, -1)
    links: list[Link] = []
    windows = revisit_windows(frames, float(reg["revisit_window_m"]))
    t_fit = 0.0
    dropped = 0
    radii = []
    start_sig = np.array([opt["log_start_sigma_m"], opt["log_start_sigma_m"], opt["log_start_sigma_rad"]], float)
    gauge = np.array([opt["anchor_sigma_m"], opt["anchor_sigma_m"], opt["anchor_sigma_rad"]], float)
    for s, e in progress(windows, length=len(windows), label="register revisits", quiet=quiet):
        k = int(frames.log[s])
        anchor = s - 1 if s > 0 and frames.log[s - 1] == k else None
        if anchor is not None:
            # The window's frames along the chain from the solved pose of frame s - 1.
            est[s:e] = se2_compose(est[anchor], se2_between(chain[anchor], chain[s:e]))
        cands = window_revisit_candidates(frames, est, s, e, held, cc, reg, opt)
        radii.append(cands.radius_px)
        new = register_candidates(store_path, est, frames.pixel_size, cands, cfg, quiet=True, run=run) if len(cands) else []
        links += new
        acc = [lk for lk in new if lk.status == "accepted"]
        t0 = time.perf_counter()
        try:
            est, drop = solver.add_window(est, s, e, steps, step_cov, acc, anchor,
                                          gauge if (anchor is None and k == 0) else start_sig)
        except RuntimeError as exc:  # gtsam's IndeterminateLinearSystemException
            if "Indeterminate" not in str(exc):
                raise
            raise JobFailed(f"register: the pose graph of frames {s}..{e - 1} is singular (GTSAM: indeterminate "
                            "system); two logs with identical frames (the same simulator seed) cause this") from None
        t_fit += time.perf_counter() - t0
        dropped += len(drop)
        gone = set(drop)
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


def run_register(workdir: Path, out_dir: Path, cfg: dict, *, quiet: bool = False,
                 base: dict | None = None) -> dict:
    """Stage entry: candidates and links for the frames store in ``workdir/ingest``.

    Two rounds: sequential pairs from the odometry prior; then revisits, progressively
    (window by window along the path, :func:`progressive_revisits`; ``[register]
    progressive_revisits``) or in one round predicted from the chain of sequential links
    (always over a published map, whose links already hold the chain). With ``base`` (``{"url", "snapshot"}`` of a published
    map version) a third round registers the frames to that map (:mod:`pipeline.anchor`)
    and writes ``map_links.csv``.
    """
    t0 = time.perf_counter()
    store_path = workdir / "ingest" / STORE_NAME
    store = FrameStore(store_path)
    frames = frame_table(store)
    reg, opt = cfg["register"], cfg["optimize"]
    seq = sequential_candidates(frames, reg, opt)
    workers = reg["workers"] or os.cpu_count() or 1
    extra_cols = ("iterations", "radius_px", "predicted_overlap")
    map_counts: dict = {}
    passes: dict = {"passes": 1}
    with dask_scheduler(reg["scheduler"], workers) as run:
        t1 = time.perf_counter()
        links = register_candidates(store_path, frames.prior, frames.pixel_size, seq, cfg, quiet=quiet,
                                    label="register sequential", run=run)
        chain, unc = chain_from_links(frames, links, opt, reg["chain_gate_sigmas"])
        progressive = bool(reg.get("progressive_revisits", True)) and base is None
        if base is not None:
            # Over a published map: anchor the chain to it first, so that revisits are
            # predicted from map-held poses (search radii of pixels, not of the drift).
            from pipeline.anchor import MAP_LINKS_FILE, anchored_chain, open_map_view, register_to_map

            t2 = time.perf_counter()
            map_links, outside = register_to_map(FrameReader(store_path), frames, chain,
                                                 open_map_view(base["url"], base["snapshot"]), cfg, quiet=quiet)
            write_links(out_dir / MAP_LINKS_FILE, map_links, extra_cols)
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
                                                        quiet=quiet)
            n_rev = len(rev_links)
            links += rev_links
        else:
            rev = revisit_candidates(frames, chain, unc, reg, opt)
            n_rev = len(rev)
            links += register_candidates(store_path, chain, frames.pixel_size, rev, cfg, quiet=quiet,
                                         label="register revisits", run=run)
    seconds_reg = time.perf_counter() - t1 - map_counts.get("map_seconds", 0.0)
    write_links(out_dir / LINKS_FILE, links, extra_cols)
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
        **passes,
        "pairs_per_s": len(links) / seconds_reg if seconds_reg > 0 else 0.0,
        "seconds": time.perf_counter() - t0,
    }
