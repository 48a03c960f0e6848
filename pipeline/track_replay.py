"""A drive log replayed through a tracking session, timed as on the vehicle.

One measurement for ``mosaicmap track`` and ``bench/bench_tracker_speed.py``: the frames are
decoded and rectified **before** the timed loop (as a camera delivers them: in memory), in
blocks of at most ``block_bytes``; a block is decoded (in worker threads) only while the
tracker is idle, so decoding never competes with the tracker's thread. Each frame then goes
with the odometry's motion to :meth:`tracker.session.Session.step`, which times its
absolute fix (wall and thread CPU clock); the replay also times the whole step (prediction,
fix, relative mode, relocalization, bookkeeping).

:func:`speed_figures` turns the run into the figures both print (:func:`speed_line`):
fixes/s over the wall time of the fixes and over their CPU time (the tracker thread's,
which other processes sharing the core do not inflate), latency p50 / p99 / max per fix,
the same per step, and the conditions they hold for (the median prior 1-sigma given to the
fixes, the search radius it gives, the load average).
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Callable, Iterable, Sequence

import cv2
import numpy as np

__all__ = ["BLOCK_BYTES", "ReplayRun", "frame_blocks", "replay", "speed_figures", "speed_line"]

BLOCK_BYTES = 256 << 20
"""Frames decoded ahead of the timed loop at once (bytes of rectified uint8 frames)."""


@dataclass
class ReplayRun:
    """A replay: ``steps`` (:class:`tracker.session.Step` per frame), ``step_seconds`` and
    ``step_cpu_seconds`` (wall and thread CPU time of each whole step), ``prior_sigma``
    ((N, 3) 1-sigma m, m, rad given to each frame's fix; NaN when none was tried),
    ``decode_seconds`` (decoding and rectifying, outside the timed loop), ``blocks``."""

    steps: list = field(default_factory=list)
    step_seconds: list = field(default_factory=list)
    step_cpu_seconds: list = field(default_factory=list)
    prior_sigma: list = field(default_factory=list)
    decode_seconds: float = 0.0
    blocks: int = 0


def frame_blocks(load: Callable[[int], np.ndarray], idx: Sequence[int], frame_bytes: int, *, workers: int = 2,
                 block_bytes: int = BLOCK_BYTES) -> Iterable[tuple[list[np.ndarray], float]]:
    """Frames ``load(i)`` of rows ``idx``, in order, in blocks of at most ``block_bytes``
    (``frame_bytes`` per frame): ``(frames, seconds to decode them)``, each block decoded
    in ``workers`` threads before it is handed out (the consumer runs between blocks, never
    during one)."""
    per = max(1, int(block_bytes) // max(int(frame_bytes), 1))
    idx = list(idx)
    with ThreadPoolExecutor(max(1, workers)) as pool:
        for k in range(0, len(idx), per):
            t0 = time.perf_counter()
            frames = list(pool.map(load, idx[k : k + per]))
            yield frames, time.perf_counter() - t0


def replay(session, blocks: Iterable[tuple[list[np.ndarray], float]], valid: np.ndarray | None,
           motions: Sequence[np.ndarray | None], *, on_step: Callable[[], None] | None = None) -> ReplayRun:
    """Replay ``blocks`` of decoded frames (:func:`frame_blocks`) through ``session`` (a
    started :class:`tracker.session.Session`), frame k with ``motions[k]`` (the odometry's
    motion since frame k - 1, vehicle frame; None for the first) and the camera's ``valid``
    mask. ``on_step`` is called after each step, outside the timing (progress).

    The steps run on one core, as on a vehicle: OpenCV at one thread for the replay (its
    worker pool would spread a call over the other cores, and their CPU time would be
    missing from the tracker thread's)."""
    run = ReplayRun()
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        _replay(session, blocks, valid, motions, on_step, run)
    finally:
        cv2.setNumThreads(threads)
    return run


def _replay(session, blocks, valid, motions, on_step, run: ReplayRun) -> None:
    k = 0
    for frames, secs in blocks:
        run.decode_seconds += secs
        run.blocks += 1
        for frame in frames:
            c0, t0 = time.thread_time(), time.perf_counter()
            st = session.step(frame, valid, motions[k])
            run.step_seconds.append(time.perf_counter() - t0)
            run.step_cpu_seconds.append(time.thread_time() - c0)
            run.prior_sigma.append(st.prior_sigma if st.prior_sigma is not None else np.full(3, np.nan))
            run.steps.append(st)
            k += 1
            if on_step is not None:
                on_step()


def _pct(a: np.ndarray) -> dict:
    if not len(a):
        return {"p50": None, "p99": None, "max": None}
    return {"p50": 1e3 * float(np.percentile(a, 50)), "p99": 1e3 * float(np.percentile(a, 99)),
            "max": 1e3 * float(a.max())}


def speed_figures(run: ReplayRun, search_radius_px: Callable[[np.ndarray], int] | None = None) -> dict:
    """The speed figures of a replay (report key ``speed``): ``fixes`` (absolute fixes
    tried), ``wall`` and ``cpu`` (``fixes_per_s`` and ``latency_ms`` p50 / p99 / max of the
    fixes: wall clock, and the tracker thread's CPU time), ``step`` (the same for whole
    steps, every frame), ``prior_sigma_median`` (m, m, rad: the 1-sigma given to the fixes),
    ``search_radius_px`` (what that median prior gives, when ``search_radius_px`` maps a
    1-sigma to it), ``decode_seconds`` (outside the timing), ``load_avg_1min``."""
    fixed = [st.fix_seconds > 0 for st in run.steps]
    fw = np.array([st.fix_seconds for st, f in zip(run.steps, fixed) if f])
    fc = np.array([st.fix_cpu_seconds for st, f in zip(run.steps, fixed) if f])
    sw, sc = np.asarray(run.step_seconds, float), np.asarray(run.step_cpu_seconds, float)
    sig = np.array([s for s, f in zip(run.prior_sigma, fixed) if f]).reshape(-1, 3)
    med = np.median(sig, axis=0) if len(sig) else np.full(3, np.nan)
    out = {
        "fixes": int(len(fw)),
        "wall": {"fixes_per_s": float(len(fw) / fw.sum()) if fw.sum() > 0 else None, "latency_ms": _pct(fw)},
        "cpu": {"fixes_per_s": float(len(fc) / fc.sum()) if fc.sum() > 0 else None, "latency_ms": _pct(fc)},
        "step": {"frames": int(len(sw)), "per_s": float(len(sw) / sw.sum()) if sw.sum() > 0 else None,
                 "latency_ms": _pct(sw), "cpu_per_s": float(len(sc) / sc.sum()) if sc.sum() > 0 else None,
                 "cpu_latency_ms": _pct(sc)},
        "prior_sigma_median": [float(v) for v in med],
        "search_radius_px": None,
        "decode_seconds": run.decode_seconds,
        "decode_blocks": run.blocks,
        "load_avg_1min": os.getloadavg()[0],
        "cores": os.cpu_count(),
    }
    if search_radius_px is not None and np.isfinite(med).all():
        out["search_radius_px"] = int(search_radius_px(med))
    return out


def speed_line(sp: dict) -> str:
    """The printed speed line of :func:`speed_figures`."""
    w, c, s = sp["wall"], sp["cpu"], sp["step"]
    if not sp["fixes"]:
        return "speed: no fixes tried"
    lw, lc = w["latency_ms"], c["latency_ms"]
    sig = sp["prior_sigma_median"]
    rad = "" if sp["search_radius_px"] is None else f", search radius {sp['search_radius_px']} px"
    return (f"speed: {w['fixes_per_s']:.0f} fixes/s wall, p50 {lw['p50']:.2f} ms, p99 {lw['p99']:.2f} ms, "
            f"max {lw['max']:.2f} ms; CPU {c['fixes_per_s']:.0f} fixes/s, p50 {lc['p50']:.2f} ms, "
            f"p99 {lc['p99']:.2f} ms, max {lc['max']:.2f} ms (tracker thread, {sp['fixes']} fixes, frames decoded "
            f"before timing; prior 1-sigma median {1000 * sig[0]:.1f} mm / {1000 * sig[2]:.1f} mrad{rad}; "
            f"whole step p50 {s['latency_ms']['p50']:.2f} ms, p99 {s['latency_ms']['p99']:.2f} ms; "
            f"load {sp['load_avg_1min']:.2f} on {sp['cores']} cores)")
