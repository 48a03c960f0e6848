"""A tracking session: the vehicle's loop of prediction, fixes, relative steps and relocalization.

Per camera frame (rectified, :mod:`mapstore.grid` frame convention) and the odometry's
motion since the previous frame (vehicle frame: metres, radians), :meth:`Session.step`:

1. **predicts** the pose by dead reckoning; the 1-sigma grows linearly with the distance
   driven since the last good fix (Kelly (2000): error = error gradient x distance), on top of
   the last fix's own uncertainty;
2. when the prior is still usable (1-sigma position under ``lost_sigma_m``: the search
   windows can cover it), asks the floor tracker for a **fix** (:mod:`tracker.floor`). An
   ``ok`` fix resets the uncertainty to the fix's covariance;
   Near the edge of the mapped area the tracker chooses templates only where the map has
   data under the prior (:mod:`tracker.coverage`);
3. when the frame is mostly off the map (under ``off_map_fraction`` of it sees map data)
   and no fix succeeds, it measures the motion **relative** to the previous frame (:mod:`tracker.relative`) instead of trusting
   the odometry, and composes its covariance (the error growth is reported);
4. after ``lost_after`` failed fixes in a row on the map (``lost`` or ``ambiguous``: the
   prior is probably wrong, e.g. a kidnapped vehicle) or when the uncertainty outgrows
   ``lost_sigma_m`` (a long low-texture stretch), the session is **lost**: every
   ``reloc_every``-th frame then asks the relocalizer (:mod:`tracker.reloc`) for a pose,
   which the floor tracker has verified before it is accepted; every frame it also tries a
   fix at the dead-reckoned pose (uncertainty capped at ``lost_sigma_m``), so a lock lost
   in a noisy or bare stretch is found again where it is expected. With a dead-reckoned
   pose the relocalizer matches the index's features within ``reloc_local_m`` + 3 sigma of
   it (a few ms), and the whole index (~0.1 s on a 20 x 20 m map) only on the streak's
   2nd attempt and every ``reloc_global_every``-th after it: a vehicle lost for a frame or
   two in noise does not stall its loop, a kidnapped one is found one frame later.

Each step returns a :class:`Step` (status of the frame, how its pose was obtained, pose and
1-sigma in the world frame, tracker time). :func:`summarize` turns a run's steps, with
ground truth when available, into the figures ``mosaicmap track`` reports.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from mapstore.grid import wrap_angle
from mapstore.knobs import knob
from tracker.floor import AMBIGUOUS, LOST, OK, Fix, FloorTracker
from tracker.params import params_from_dict
from tracker.run_figures import run_figures
from tracker.relative import RelativeTracker, chain
from tracker.session_core import CoreParams, CoreState, SessionCore

__all__ = ["SessionParams", "Step", "Session", "summarize", "MODES"]

# How a step's pose was obtained.
FIX, RELOC, RELATIVE, ODOMETRY, NONE = "fix", "reloc", "relative", "odometry", "none"
MODES = (FIX, RELOC, RELATIVE, ODOMETRY, NONE)
OFF_MAP = "off_map"


@dataclass(frozen=True)
class SessionParams(CoreParams):
    """Session settings (``[tracker.session]`` in ``configs/tracker.toml`` documents each;
    the start, dead-reckoning and lost settings are :class:`tracker.session_core.CoreParams`')."""

    min_sigma_m: float = knob(ge=0.0, default=0.0005)
    min_sigma_rad: float = knob(ge=0.0, default=0.001)
    off_map_fraction: float = knob(ge=0.0, le=1.0, default=0.5)
    relative: bool = knob(default=True)
    look_ahead_px: int = knob(ge=0, default=128)
    cache_tiles: int = knob(ge=1, default=1024)
    reloc_local_m: float = knob(ge=0.0, default=1.0)
    reloc_global_every: int = knob(ge=1, default=5)

    @classmethod
    def from_dict(cls, d: dict) -> "SessionParams":
        return params_from_dict(cls, d, "tracker.session")


@dataclass
class Step:
    """One frame of a session.

    ``status``: the frame's fix status (``ok``, ``low_texture``, ``ambiguous``, ``lost``;
    ``off_map`` when too few templates fell on map data; ``lost`` while the session is
    lost and relocalization failed). ``mode``: how ``pose`` was obtained: ``fix`` (an ok
    absolute fix), ``reloc`` (an ok fix from relocalization), ``relative`` (frame to frame),
    ``odometry`` (dead reckoning), ``none`` (no pose: lost since the start). ``pose``
    (x, y, theta; world frame, NaN when none) and ``sigma`` (1-sigma m, m, rad) after the
    step. ``fix_seconds``: wall time of the absolute fix (0 when none was tried),
    ``fix_cpu_seconds`` its CPU time (this thread: what other processes on the core do not
    inflate);
    ``reloc_seconds``: time of a relocalization attempt; ``relative_seconds``;
    ``prior_sigma``: the 1-sigma (m, m, rad) given to the absolute fix (None when none was
    tried); ``prefetch_seconds``: map tiles read ahead of the next fixes after this one
    (:meth:`Session.step`), ``prefetched`` how many.
    """

    index: int
    status: str
    mode: str
    pose: np.ndarray
    sigma: np.ndarray
    fix_seconds: float = 0.0
    reloc_seconds: float = 0.0
    relative_seconds: float = 0.0
    fix: Fix | None = None
    lost: bool = False
    fix_cpu_seconds: float = 0.0
    prior_sigma: np.ndarray | None = None
    prefetch_seconds: float = 0.0
    prefetched: int = 0

    @property
    def ok(self) -> bool:
        return self.status == OK

    @property
    def seconds(self) -> float:
        return self.fix_seconds + self.reloc_seconds + self.relative_seconds + self.prefetch_seconds


@dataclass
class _State(CoreState):
    cov_rel: np.ndarray | None = None  # covariance while chaining relative steps
    previous: tuple[np.ndarray, np.ndarray | None] | None = None


class Session(SessionCore):
    """The tracking loop over one map (see the module docstring).

    Args:
        tracker: the floor tracker over the map (its tile cache is grown to ``cache_tiles``).
        relocalizer: a :class:`tracker.reloc.Relocalizer` (None: a lost session stays lost).
        params: :class:`SessionParams`.
    """

    def __init__(self, tracker: FloorTracker, relocalizer=None, params: SessionParams | None = None):
        self.tracker = tracker
        self.relocalizer = relocalizer
        self.p = params or SessionParams()
        self.relative = RelativeTracker(tracker.frame_pixel_size, tracker.p) if self.p.relative else None
        if self.p.cache_tiles > tracker.tiles.capacity:  # the map's tiles read (and checked) once while they fit
            tracker.tiles.resize(self.p.cache_tiles)
        self.s = _State()
        self.index = 0
        self._cpu = 0.0
        self._fix_sigma: np.ndarray | None = None
        self._cold = True  # no step since start(): read the tiles around the start pose first
        self._min_sigma = np.array([self.p.min_sigma_m, self.p.min_sigma_m, self.p.min_sigma_rad])

    def _new_state(self) -> _State:
        return _State()

    def start(self, pose: np.ndarray | None, sigma: np.ndarray | None = None) -> None:
        """Start from ``pose`` (world frame) with 1-sigma ``sigma`` (default the start sigma),
        or with no pose (``None``: relocalize first); the map tiles around it are read first."""
        super().start(pose, sigma)
        self._cold = True

    @property
    def sigma(self) -> np.ndarray:
        """The current 1-sigma (m, m, rad) of the pose."""
        s = self.s
        if s.cov_rel is not None:
            return np.sqrt(np.maximum(np.diag(s.cov_rel), 0.0))
        return s.sigma

    def _accept(self, fix: Fix) -> None:
        sd = np.sqrt(np.maximum(np.diag(fix.cov), 0.0))
        self._locked(fix.pose, np.maximum(sd, self._min_sigma))
        self.s.cov_rel = None

    def step(self, frame: np.ndarray, valid: np.ndarray | None, motion: np.ndarray | None) -> Step:
        """Process one rectified ``frame`` (uint8) with its ``valid`` mask; ``motion``: the
        odometry's motion since the previous frame (vehicle frame; None for the first)."""
        s, p = self.s, self.p
        i = self.index
        self.index += 1
        # the pose and its covariance before this frame's dead reckoning (a relative step replaces it)
        before = None if s.pose is None else (s.pose.copy(), s.cov_rel.copy() if s.cov_rel is not None
                                              else np.diag(self.sigma**2))
        self._predict(motion)
        if s.pose is not None and motion is not None and s.cov_rel is not None:
            s.cov_rel = s.cov_rel + np.diag(self._growth(motion) ** 2)
        self._lose_if_uncertain()
        self._fix_sigma = None
        pre, pre_s = 0, 0.0
        if self._cold and p.look_ahead_px > 0 and s.pose is not None:  # start-up: the tiles around the start pose
            t0 = time.perf_counter()
            pre = self.tracker.prefetch(s.pose, frame.shape, p.look_ahead_px)
            pre_s = time.perf_counter() - t0
        if s.lost:
            step = self._reloc(frame, valid, motion, before, i)
        else:
            step = self._track(frame, valid, motion, before, i)
        s.previous = (frame, valid)
        self._cold = False
        step.prior_sigma = self._fix_sigma
        if p.look_ahead_px > 0 and s.pose is not None:
            # the map tiles around this pose, a margin beyond the footprint, read now: the next
            # fixes find them decoded instead of reading (and checking) a bundle member mid-fix
            t0 = time.perf_counter()
            pre += self.tracker.prefetch(s.pose, frame.shape, p.look_ahead_px)
            pre_s += time.perf_counter() - t0
        step.prefetched, step.prefetch_seconds = pre, pre_s
        return step

    def _relative(self, frame: np.ndarray, valid: np.ndarray | None, motion: np.ndarray | None,
                  before: tuple[np.ndarray, np.ndarray] | None) -> tuple[bool, float]:
        """Frame-to-frame motion from the previous frame; on success the pose and its
        covariance are the pre-prediction ones composed with it. (ok, seconds)."""
        s = self.s
        if self.relative is None or s.previous is None or motion is None or before is None:
            return False, 0.0
        t1 = time.perf_counter()
        sig = self._min_sigma + self._growth(motion)
        rel = self.relative.step(s.previous[0], s.previous[1], frame, valid, np.asarray(motion, float), sig)
        if rel.ok:
            s.pose, s.cov_rel = chain(before[0], before[1], rel)
        return rel.ok, time.perf_counter() - t1

    def _reloc(self, frame: np.ndarray, valid: np.ndarray | None, motion: np.ndarray | None,
               before: tuple[np.ndarray, np.ndarray] | None, i: int) -> Step:
        s, p = self.s, self.p
        if s.pose is not None:
            # first the dead-reckoned pose, its uncertainty capped at what the search covers
            # (what was lost may be found again where it is expected: a noisy or bare stretch)
            sigma = np.minimum(self.sigma, [p.lost_sigma_m, p.lost_sigma_m, np.inf])
            self._fix_sigma = sigma
            t0, c0 = time.perf_counter(), time.thread_time()
            fix = self.tracker.fix(frame, s.pose, sigma, valid)
            fix_s, self._cpu = time.perf_counter() - t0, time.thread_time() - c0
            if fix.ok:
                self._accept(fix)
                return self._result(i, OK, FIX, fix=fix, fix_seconds=fix_s)
        fix, secs = None, 0.0
        attempt = s.since_reloc // max(p.reloc_every, 1)
        if self._reloc_due(self.relocalizer is not None):
            fix = self.relocalizer.locate(frame, valid, self._reloc_disc(attempt))
            secs = self.relocalizer.last_seconds
        if fix is not None and fix.ok:
            self._accept(fix)
            return self._result(i, OK, RELOC, fix=fix, reloc_seconds=secs)
        if s.pose is None:
            return self._result(i, LOST, NONE, fix=fix, reloc_seconds=secs, lost=True)
        # still lost: carry the pose on, frame to frame where the floor allows (off the map)
        ok, rel_s = self._relative(frame, valid, motion, before)
        return self._result(i, LOST, RELATIVE if ok else ODOMETRY, fix=fix, reloc_seconds=secs,
                            relative_seconds=rel_s, lost=True)

    def _reloc_disc(self, attempt: int) -> tuple[float, float, float] | None:
        """Where lost streak's relocalization ``attempt`` (0 first) searches: (x, y, radius)
        around the dead-reckoned pose (``reloc_local_m`` + 3 sigma, metres), or None for the
        whole index: no (finite) pose, or the streak's 2nd attempt and every
        ``reloc_global_every``-th after it (every attempt when it is 1)."""
        s, g = self.s, self.p.reloc_global_every
        if s.pose is None or attempt % g == min(1, g - 1):
            return None
        sd = self.sigma
        if not (np.isfinite(s.pose[:2]).all() and np.isfinite(sd[:2]).all()):
            return None
        return float(s.pose[0]), float(s.pose[1]), self.p.reloc_local_m + 3.0 * float(max(sd[0], sd[1]))

    def _track(self, frame: np.ndarray, valid: np.ndarray | None, motion: np.ndarray | None,
               before: tuple[np.ndarray, np.ndarray] | None, i: int) -> Step:
        s, p = self.s, self.p
        sigma = self._fix_sigma = self.sigma
        t0, c0 = time.perf_counter(), time.thread_time()
        fix = self.tracker.fix(frame, s.pose, sigma, valid)
        fix_s, self._cpu = time.perf_counter() - t0, time.thread_time() - c0
        if fix.ok:
            self._accept(fix)
            return self._result(i, OK, FIX, fix=fix, fix_seconds=fix_s)
        if fix.coverage < p.off_map_fraction:
            s.fails = 0
            ok, rel_s = self._relative(frame, valid, motion, before)
            return self._result(i, OFF_MAP, RELATIVE if ok else ODOMETRY, fix=fix, fix_seconds=fix_s,
                                relative_seconds=rel_s)
        if fix.status in (LOST, AMBIGUOUS):
            self._rejected()
        return self._result(i, fix.status, ODOMETRY, fix=fix, fix_seconds=fix_s, lost=s.lost)

    def _result(self, i: int, status: str, mode: str, *, fix: Fix | None = None, fix_seconds: float = 0.0,
                reloc_seconds: float = 0.0, relative_seconds: float = 0.0, lost: bool = False) -> Step:
        pose = np.full(3, np.nan) if self.s.pose is None else self.s.pose.copy()
        sigma = np.full(3, np.nan) if self.s.pose is None else self.sigma
        cpu = self._cpu if fix_seconds > 0 else 0.0
        return Step(i, status, mode, pose, sigma, fix_seconds, reloc_seconds, relative_seconds, fix, lost, cpu)


def summarize(steps: list[Step], truth: np.ndarray | None, pixel_size: float, wrong_px: float = 2.0) -> dict:
    """The figures of a run (report keys of ``mosaicmap track``): ``fixes`` (frames),
    ``ok_rate``, ``statuses`` and ``modes`` (counts), ``fixes_per_s`` and ``latency_ms``
    (absolute fixes only, wall clock: p50, p99, max), ``cpu_fixes_per_s`` and
    ``cpu_latency_ms`` (the same in CPU time of the tracker's thread), ``relocalizations`` (successful; ``relocalization``
    attempts and times), and with ``truth`` ((N, 3) world poses of the frames): errors of
    the ok fixes in map pixels of ``pixel_size`` metres (``error_rms_px``,
    ``error_max_ok_px``, ``heading_error_rms_deg``), ``wrong_ok`` (ok fixes off by more
    than ``wrong_px``), and ``relative`` (frames, metres, error growth)."""
    ok = np.array([st.ok for st in steps], bool)
    out = run_figures(steps, MODES, RELOC)
    if truth is None:
        return out
    poses = np.array([st.pose for st in steps])
    err = np.hypot(poses[:, 0] - truth[:, 0], poses[:, 1] - truth[:, 1]) / pixel_size
    herr = np.degrees(np.abs(wrap_angle(poses[:, 2] - truth[:, 2])))
    e_ok = err[ok]
    out.update({
        "error_rms_px": float(np.sqrt(np.mean(e_ok**2))) if len(e_ok) else None,
        "error_median_px": float(np.median(e_ok)) if len(e_ok) else None,
        "error_max_ok_px": float(e_ok.max()) if len(e_ok) else None,
        "heading_error_rms_deg": float(np.sqrt(np.mean(herr[ok] ** 2))) if ok.any() else None,
        "wrong_ok": int((e_ok > wrong_px).sum()),
        "wrong_px": wrong_px,
    })
    out["relative"] = _relative_stretches(steps, err * pixel_size, poses)
    return out



def _relative_stretches(steps: list[Step], err_m: np.ndarray, poses: np.ndarray) -> dict:
    """Stretches of consecutive relative steps: their length (m, along the estimate), the
    error at their end minus the error before them (m), and the 1-sigma reported there."""
    runs, cur = [], []
    for k, st in enumerate(steps):
        if st.mode == RELATIVE:
            cur.append(k)
        elif cur:
            runs.append(cur)
            cur = []
    if cur:
        runs.append(cur)
    stretches = []
    for r in runs:
        a, b = r[0], r[-1]
        start = a - 1 if a > 0 else a
        length = float(np.sum(np.hypot(*np.diff(poses[start : b + 1, :2], axis=0).T)))
        e0 = float(err_m[start]) if np.isfinite(err_m[start]) else 0.0
        stretches.append({"frames": len(r), "length_m": length, "error_start_m": e0, "error_end_m": float(err_m[b]),
                          "sigma_end_m": float(steps[b].sigma[:2].max())})
    total = sum(s["length_m"] for s in stretches)
    growth = sum(max(s["error_end_m"] - s["error_start_m"], 0.0) for s in stretches)
    return {"frames": int(sum(s["frames"] for s in stretches)), "length_m": total,
            "error_growth_per_m": growth / total if total > 0 else None, "stretches": stretches}
