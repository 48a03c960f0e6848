"""Sane geometry before publish: wild odometry and the map's extent.

A frame that no registration link holds is placed where its prior (odometry) puts it. One
wild odometry row would then put a frame, and the map's grid with it, a kilometre away.
Three checks, all from the log's own speed model:

- **Speed cap** of a log (:func:`speed_cap`): ``[optimize] jump_speed_factor`` times the
  ``jump_speed_percentile``-th percentile of the speeds its prior implies between
  consecutive frames (metres per second of the log's own time stamps; a few wild rows do not
  move a high percentile). A frame may lie ``cap x |dt| + jump_slack_frames x frame
  diagonal`` (metres) from another frame of its log ``dt`` seconds away (:func:`allowed_m`).
- **Prior spikes** (:func:`prior_spikes`, at registration): runs of at most
  ``jump_max_frames`` frames inside a log entered and left by steps beyond that allowance
  which cancel (the prior jumps out and comes back: no vehicle does that; a raster scan's
  row return jumps one way only), and such a run at either end of a log cut off from the
  (longer) rest by one such step. They take part in no pair and their prior is interpolated
  from the frames around them (:func:`pipeline.stages.register.frame_table`): the path travelled
  and the search radii stay sane (a 1 km step would give its pairs radii of kilometres).
- **Wild unlinked frames** (:func:`wild_unlinked`, after optimizing): a frame without any
  accepted link (sequential, revisit or map) that lies beyond the allowance from each of its
  log's nearest linked frames before and after it is dropped: listed with its reason in the
  report (``geometry.dropped``) and ``optimize/dropped.csv``, not rendered, not published.

The publish gate then compares the extent of the frames it would render with the extent of
the linked frames (:func:`extent_growth_m`, ``[publish] max_extent_growth_fraction`` and
``max_extent_growth_frames``). ``jump_speed_factor = 0`` switches the first three off.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.fsutil import write_text_atomic

DROPPED_FILE = "dropped.csv"


@dataclass(frozen=True)
class JumpParams:
    """The speed model's knobs (``[optimize] jump_*``; see the module docstring).

    Attributes:
        speed_factor: cap = factor x the percentile speed; 0 = checks off.
        speed_percentile: percentile (0-100) of the prior's step speeds.
        slack_frames: distance allowed on top of the speed, in frame diagonals.
        max_frames: longest run of frames a prior spike may span.
    """

    speed_factor: float = 10.0
    speed_percentile: float = 90.0
    slack_frames: float = 1.0
    max_frames: int = 10

    @classmethod
    def from_config(cls, opt: dict) -> "JumpParams":
        """From the ``[optimize]`` table (read through its schema, :mod:`pipeline.schema`)."""
        from pipeline.schema import settings
        from pipeline.schema_floor import OptimizeConfig

        o = settings(OptimizeConfig, opt)
        return cls(o.jump_speed_factor, o.jump_speed_percentile, o.jump_slack_frames, o.jump_max_frames)

    @property
    def enabled(self) -> bool:
        return self.speed_factor > 0


def speed_cap(prior: np.ndarray, t: np.ndarray, params: JumpParams) -> float:
    """A log's speed cap (metres per second): ``speed_factor`` x the ``speed_percentile``-th
    percentile of the speeds between its consecutive frames' priors ((N, >=2) metres, (N,)
    seconds, strictly increasing); 0 for a log of one frame."""
    if len(prior) < 2:
        return 0.0
    dt = np.diff(np.asarray(t, float))
    step = np.hypot(*np.diff(np.asarray(prior, float)[:, :2], axis=0).T)
    speed = step / np.maximum(dt, 1e-12)
    return float(params.speed_factor * np.percentile(speed, params.speed_percentile))


def allowed_m(cap: float, dt: np.ndarray | float, diagonal_m: float, params: JumpParams) -> np.ndarray:
    """Farthest a frame may lie from another of its log ``dt`` seconds away (metres)."""
    return cap * np.abs(np.asarray(dt, float)) + params.slack_frames * diagonal_m


def prior_spikes(prior: np.ndarray, t: np.ndarray, diagonal_m: float, params: JumpParams) -> np.ndarray:
    """(N,) bool: frames of one log inside a spike of its prior (module docstring).

    ``prior`` (N, >=2) metres, ``t`` (N,) seconds, ``diagonal_m`` a frame's footprint diagonal."""
    n = len(prior)
    out = np.zeros(n, bool)
    if not params.enabled or n < 3:
        return out
    xy = np.asarray(prior, float)[:, :2]
    t = np.asarray(t, float)
    cap = speed_cap(prior, t, params)
    step = np.diff(xy, axis=0)  # step k: frame k -> k + 1
    jump = np.hypot(*step.T) > allowed_m(cap, np.diff(t), diagonal_m, params)
    starts = np.flatnonzero(jump)
    used: set[int] = set()
    for k in starts:  # a run begins at frame k + 1 and ends before the next cancelling jump
        if k in used:
            continue
        for e in starts[(starts > k) & (starts <= k + params.max_frames)]:
            back = step[k] + step[e]
            span = allowed_m(cap, t[e + 1] - t[k], diagonal_m, params)
            if np.hypot(*back) <= min(span, 0.5 * min(np.hypot(*step[k]), np.hypot(*step[e]))):
                out[k + 1 : e + 1] = True
                used.update((int(k), int(e)))
                break
    rest = [int(k) for k in starts if int(k) not in used]
    if rest:  # a short run at either end of the log, cut off from the rest by a jump
        first, last = rest[0] + 1, n - 1 - rest[-1]  # frames before the first / after the last jump
        if first <= params.max_frames and first < n - first:
            out[:first] = True
        if last <= params.max_frames and last < n - last:
            out[n - last :] = True
    return out


def spike_reasons(raw: np.ndarray, used: np.ndarray, spikes: np.ndarray, log_of: np.ndarray,
                  caps: list[float]) -> dict[int, str]:
    """Global index -> reason of the frames inside a prior spike (``spikes`` (N,) bool):
    ``raw`` (N, >=2) the logged prior, ``used`` the prior the build used (spikes
    interpolated), metres; ``caps`` each log's speed cap (m/s)."""
    out = {}
    for g in np.flatnonzero(spikes).tolist():
        d = float(np.hypot(*(np.asarray(raw[g, :2], float) - np.asarray(used[g, :2], float))))
        out[g] = (f"its odometry puts it {d:.4g} m off the path of the frames around it, a jump faster than the "
                  f"log's speed cap of {float(caps[int(log_of[g])]):.3g} m/s; not registered, no registration "
                  "link holds it")
    return out


@dataclass(frozen=True)
class Dropped:
    """A frame left out of the map: global index ``frame`` (frames-store order), its log id,
    its row in that log's frames.csv, and why."""

    frame: int
    log_id: str
    source: int
    reason: str

    def name(self) -> str:
        return f"{self.log_id} frame {self.source}"


def wild_unlinked(poses: np.ndarray, t: np.ndarray, log_of: np.ndarray, linked: np.ndarray, caps: list[float],
                  diagonals_m: list[float], params: JumpParams, skip: np.ndarray | None = None) -> dict[int, str]:
    """Frames without an accepted link too far from their log's linked frames, global index
    -> reason (module docstring).

    ``poses`` (N, >=2) optimized, metres; ``t`` (N,) seconds; ``log_of`` (N,) log index;
    ``linked`` (N,) bool: the frame holds an accepted link; ``caps`` / ``diagonals_m`` per log
    (:func:`speed_cap`, metres); ``skip`` (N,) bool: frames not judged here (the prior
    spikes, dropped for that: :func:`spike_reasons`)."""
    out: dict[int, str] = {}
    if not params.enabled:
        return out
    xy = np.asarray(poses, float)[:, :2]
    for k in np.unique(log_of):
        idx = np.flatnonzero(log_of == k)
        ref = idx[linked[idx]]
        if len(ref) == 0:
            continue  # the whole log rests on its prior: nothing to judge it by (the extent gate)
        cap, diag = float(caps[k]), float(diagonals_m[k])
        for g in idx[~linked[idx]].tolist():
            pos = np.searchsorted(ref, g)
            sides = [int(ref[j]) for j in (pos - 1, pos) if 0 <= j < len(ref)]
            dist = [float(np.hypot(*(xy[g] - xy[r]))) for r in sides]
            lim = [float(allowed_m(cap, t[g] - t[r], diag, params)) for r in sides]
            if skip is not None and skip[g]:
                continue
            if all(d > m for d, m in zip(dist, lim)):
                j = int(np.argmin(dist))
                out[g] = (f"no registration link holds it and its odometry puts it {dist[j]:.3g} m from the "
                          f"nearest linked frame {abs(t[g] - t[sides[j]]):.3g} s away (at most {lim[j]:.3g} m at "
                          f"the log's speed cap of {cap:.3g} m/s)")
    return out


def footprint_extent(poses: np.ndarray, log_of: np.ndarray, diagonals_m: list[float],
                     mask: np.ndarray) -> list[float] | None:
    """``[xmin, ymin, xmax, ymax]`` (metres) of the footprints (discs of half the frame
    diagonal about the frame centres) of the frames where ``mask``; None when none."""
    sel = np.flatnonzero(mask)
    if not len(sel):
        return None
    half = 0.5 * np.asarray(diagonals_m, float)[log_of[sel]]
    xy = np.asarray(poses, float)[sel, :2]
    return [float((xy[:, 0] - half).min()), float((xy[:, 1] - half).min()),
            float((xy[:, 0] + half).max()), float((xy[:, 1] + half).max())]


def extent_growth_m(extent: list[float], linked: list[float]) -> float:
    """How far (metres) ``extent`` reaches beyond ``linked`` on its worst side (0 inside)."""
    return float(max(linked[0] - extent[0], linked[1] - extent[1], extent[2] - linked[2], extent[3] - linked[3], 0.0))


def extent_tolerance_m(linked: list[float], diagonal_m: float, cfg_pub: dict) -> float:
    """How far (metres) the rendered extent may reach beyond the linked frames' on any side:
    ``max_extent_growth_fraction`` x the linked extent's longer side plus
    ``max_extent_growth_frames`` frame diagonals."""
    size = max(linked[2] - linked[0], linked[3] - linked[1])
    return float(cfg_pub["max_extent_growth_fraction"] * size + cfg_pub["max_extent_growth_frames"] * diagonal_m)


def write_dropped(path: Path, dropped: list[Dropped]) -> None:
    """``frame,log_id,source,reason`` (global index, log id, row in frames.csv, why)."""
    import io

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["frame", "log_id", "source", "reason"])
    for d in dropped:
        w.writerow([d.frame, d.log_id, d.source, d.reason])
    write_text_atomic(path, buf.getvalue())


def read_dropped(path: Path) -> list[Dropped]:
    """:func:`write_dropped`'s frames; [] when the file is absent (a work directory of an
    older build, or a stage that does not drop)."""
    if not path.exists():
        return []
    with open(path, newline="", encoding="utf-8") as f:
        return [Dropped(int(r["frame"]), r["log_id"], int(r["source"]), r["reason"]) for r in csv.DictReader(f)]


def dropped_mask(path: Path, n: int) -> np.ndarray:
    """(n,) bool: frames :func:`read_dropped` lists."""
    out = np.zeros(n, bool)
    for d in read_dropped(path):
        if 0 <= d.frame < n:
            out[d.frame] = True
    return out


def frame_diagonal_m(shape: tuple[int, int], pixel_size: float) -> float:
    """A frame's footprint diagonal (metres) from its rectified shape (rows, cols)."""
    return float(np.hypot(*shape) * pixel_size)
