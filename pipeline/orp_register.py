"""Registering omni runs of one route to each other by their horizon lines (the ``orp`` stage's numerics).

Frames and units
    Poses ``(x, y, theta)``: metres and radians; a run's poses are in its odometry frame (the
    site frame, as the floor build's priors) until optimized. Path length ``s`` (metres) along
    a run's own odometry path (:func:`tracker.orp.path_length`). Horizon lines ``(N, A)``: grey
    levels, sample ``j`` at camera azimuth ``j / samples_per_degree`` degrees (counter-clockwise
    from the vehicle's +x), as :class:`tracker.orp.HorizonSampler` writes them.

Coarse registration (:func:`coarse_register`)
    Both runs are resampled at ``coarse_spacing_m`` along their odometry paths; every line is
    turned into a *signature* (log intensity, azimuth frequencies below ``highpass_cycles``
    removed, unit norm). For each along-track lag (rows, within ``+-max_offset_m``) the
    circular cross-correlations over azimuth of all overlapping row pairs are averaged (one
    FFT product per row); the lag and azimuth shift with the highest mean NCC win. The shift
    is the heading of the run minus the reference's (a scene point seen at azimuth ``a`` by
    the run is seen at ``a + dtheta`` by the reference), refined to a fraction of a sample.

Fine registration (:func:`localize_run`)
    The run's frames are localized one by one on the reference's ORP
    (:class:`tracker.orp.ORPLocalizer`), in tracking mode: the first prior is the coarse one
    (the reference's route pose at ``s + offset``, heading ``+ dtheta``), every next one the
    last accepted fix composed with the run's odometry increment (the coarse prior again after
    ``reset_m`` without an accepted fix). A fix is kept when the localizer says ok, its NCC and
    valid fraction pass the gates and (tracking) it lands within ``gate_m`` of its prior.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mapstore.grid import se2_between, se2_compose, se2_interpolate, wrap_angle
from tracker.orp import ORP, ORPLocalizer

__all__ = [
    "Coarse",
    "Fix",
    "signatures",
    "coarse_register",
    "route_pose_at",
    "path_pose_at",
    "localize_run",
    "roll_lines",
    "project_on_path",
    "resample_rows",
    "interpolate_corrections",
    "keep_every",
    "RowMatch",
    "match_rows",
]


@dataclass
class Coarse:
    """Coarse registration of a run to a reference.

    Attributes:
        offset_m: along-track offset: the run's path length ``s`` is at the reference's
            ``s + offset_m`` (metres).
        dtheta: heading of the run minus the reference's at corresponding points (radians).
        ncc: mean NCC of the overlapping rows at the best lag and shift.
        rows: overlapping rows at the best lag.
    """

    offset_m: float
    dtheta: float
    ncc: float
    rows: int


@dataclass
class Fix:
    """One fine registration of a run frame on the reference ORP.

    Attributes:
        index: the frame (index into the run's arrays given to :func:`localize_run`).
        pose: ``(3,)`` the frame's pose in the reference's frame (metres, radians).
        prior: ``(3,)`` the prior it started from.
        s: path length on the reference (metres).
        ncc, valid_fraction: the localizer's quality figures.
        accepted: passed the gates; ``reason`` says why not.
    """

    index: int
    pose: np.ndarray
    prior: np.ndarray
    s: float
    ncc: float
    valid_fraction: float
    accepted: bool
    reason: str = ""


def signatures(lines: np.ndarray, highpass_cycles: int = 3) -> np.ndarray:
    """Complex spectra ``(N, A//2+1)`` of log-intensity lines with the lowest
    ``highpass_cycles`` azimuth frequencies (DC included) removed and unit energy: the
    circular cross-correlation of two such lines is their NCC at each azimuth shift."""
    a = np.log1p(np.asarray(lines, np.float64))
    f = np.fft.rfft(a, axis=-1)
    f[..., : max(1, int(highpass_cycles))] = 0.0
    n = a.shape[-1]
    # energy of the real signal from its half spectrum (Parseval)
    w = np.full(f.shape[-1], 2.0)
    w[0] = 1.0
    if n % 2 == 0:
        w[-1] = 1.0
    e = np.sqrt((w * np.abs(f) ** 2).sum(-1, keepdims=True) / n)
    return f / np.maximum(e, 1e-12)


def coarse_register(ref_sig: np.ndarray, run_sig: np.ndarray, n_azimuths: int, spacing_m: float,
                    max_offset_m: float, min_overlap: float = 0.5) -> Coarse:
    """Along-track offset and heading of a run against a reference (module docstring).

    ``ref_sig``, ``run_sig``: :func:`signatures` of the two runs' lines resampled every
    ``spacing_m`` metres along their paths (row ``i`` at ``s = i * spacing_m``). Lags keep at
    least ``min_overlap`` of the shorter run overlapping.
    """
    n_ref, n_run = len(ref_sig), len(run_sig)
    max_lag = int(round(max_offset_m / spacing_m))
    need = max(2, int(math.ceil(min_overlap * min(n_ref, n_run))))
    best = Coarse(0.0, 0.0, -1.0, 0)
    best_curve = None
    for lag in range(-max_lag, max_lag + 1):  # run row i <-> reference row i + lag
        i0, i1 = max(0, -lag), min(n_run, n_ref - lag)
        if i1 - i0 < need:
            continue
        spec = (ref_sig[i0 + lag : i1 + lag] * np.conj(run_sig[i0:i1])).mean(0)
        curve = np.fft.irfft(spec, n=n_azimuths)  # NCC per azimuth shift (irfft divides by n)
        k = int(np.argmax(curve))
        if curve[k] > best.ncc:
            best, best_curve = Coarse(lag * spacing_m, float(k), float(curve[k]), i1 - i0), curve
    if best_curve is None:
        raise ValueError("runs too short to overlap for the coarse registration")
    k = int(best.dtheta)
    c_m, c_0, c_p = best_curve[(k - 1) % n_azimuths], best_curve[k], best_curve[(k + 1) % n_azimuths]
    den = c_m - 2.0 * c_0 + c_p
    frac = 0.5 * (c_m - c_p) / den if den < 0 else 0.0
    shift = (k + float(np.clip(frac, -0.5, 0.5))) * (2.0 * math.pi / n_azimuths)
    best.dtheta = float(wrap_angle(shift))
    return best


def route_pose_at(orp: ORP, s: np.ndarray | float) -> np.ndarray:
    """Route pose(s) ``(..., 3)`` of an ORP at path length(s) ``s`` (metres; clamped to the
    route), SE(2)-interpolated between rows."""
    s = np.asarray(s, float)
    m = len(orp.poses)
    r = np.clip((s - orp.s0) / orp.spacing_m, 0.0, m - 1.0)
    i = np.minimum(r.astype(int), max(m - 2, 0))
    p = orp.poses.astype(np.float64)
    if m < 2:
        return np.broadcast_to(p[0], s.shape + (3,)).copy()
    return se2_interpolate(p[i], p[i + 1], r - i)


def path_pose_at(poses: np.ndarray, s_poses: np.ndarray, s: np.ndarray | float) -> np.ndarray:
    """Pose(s) ``(..., 3)`` on a path of poses ``(N, 3)`` (metres, radians) at path length(s)
    ``s`` (metres; clamped to the path), ``s_poses (N,)`` increasing: SE(2)-interpolated
    between the two poses around each."""
    sp = np.asarray(s_poses, float)
    p = np.asarray(poses, float)
    q = np.clip(np.asarray(s, float), sp[0], sp[-1])
    i = np.clip(np.searchsorted(sp, q, side="right") - 1, 0, len(sp) - 2)
    f = np.clip((q - sp[i]) / np.maximum(sp[i + 1] - sp[i], 1e-12), 0.0, 1.0)
    return se2_interpolate(p[i], p[i + 1], f)


def localize_run(loc: ORPLocalizer, lines: np.ndarray, odo: np.ndarray, s_run: np.ndarray, coarse: Coarse,
                 *, min_ncc: float, min_valid: float, gate_m: float, gate_rad: float, reset_m: float) -> list[Fix]:
    """Fine registration of a run's frames (``lines (N, A)``, odometry poses ``odo (N, 3)``,
    path lengths ``s_run (N,)``, metres) on the reference ORP of ``loc`` (module docstring)."""
    orp = loc.orp
    fixes: list[Fix] = []
    last: int | None = None  # index of the last accepted fix
    last_pose = np.zeros(3)
    shift = coarse.offset_m  # reference s minus run s, updated by each accepted fix
    for i in range(len(lines)):
        tracking = last is not None and s_run[i] - s_run[last] <= reset_m
        if tracking:
            prior = se2_compose(last_pose, se2_between(odo[last], odo[i]))
        else:
            s_ref = s_run[i] + shift
            if s_ref < orp.s0 - 0.5 * orp.spacing_m or s_ref > orp.s0 + orp.length_m + 0.5 * orp.spacing_m:
                continue  # beyond the reference's ends
            prior = route_pose_at(orp, s_ref)
            prior[2] = wrap_angle(prior[2] + coarse.dtheta)
        fix = loc.localize(lines[i], prior)
        d = float(np.hypot(*(fix.pose[:2] - prior[:2])))
        dh = abs(float(wrap_angle(fix.pose[2] - prior[2])))
        reason = ""
        if not fix.ok:
            reason = "localizer: not ok"
        elif fix.ncc < min_ncc:
            reason = f"ncc {fix.ncc:.3f} < {min_ncc:g}"
        elif fix.valid_fraction < min_valid:
            reason = f"valid fraction {fix.valid_fraction:.2f} < {min_valid:g}"
        elif fix.s <= orp.s0 + 1e-9 or fix.s >= orp.s0 + orp.length_m - 1e-9:
            reason = "at the reference's end"
        elif tracking and (d > gate_m or dh > gate_rad):
            reason = f"{d:.3f} m / {math.degrees(dh):.2f} deg from its prior (gate {gate_m:g} m)"
        ok = not reason
        fixes.append(Fix(i, np.asarray(fix.pose, float).copy(), np.asarray(prior, float), float(fix.s),
                         float(fix.ncc), float(fix.valid_fraction), ok, reason))
        if ok:
            last, last_pose = i, fixes[-1].pose
            shift = float(fix.s) - float(s_run[i])
    return fixes


def roll_lines(lines: np.ndarray, dtheta: np.ndarray) -> np.ndarray:
    """Lines ``(N, A)`` re-expressed for a heading ``dtheta`` (radians, ``(N,)``) smaller:
    what a camera at the same place turned by ``-dtheta`` sees (sample ``a`` of the result =
    sample ``a - dtheta`` of the input), by an exact Fourier shift (circular)."""
    lines = np.asarray(lines, np.float64)
    n = lines.shape[-1]
    k = np.arange(n // 2 + 1)
    shift = np.asarray(dtheta, float)[..., None] * (n / (2.0 * math.pi))
    f = np.fft.rfft(lines, axis=-1) * np.exp(-2j * math.pi * k * shift / n)
    return np.fft.irfft(f, n=n, axis=-1)


def project_on_path(path: np.ndarray, s_path: np.ndarray, xy: np.ndarray, chunk: int = 4096):
    """Nearest points of positions ``xy (N, 2)`` on a polyline ``path (M, 3)`` whose vertices
    are at path lengths ``s_path (M,)``: returns ``(s (N,), lateral (N,), theta (N,))``:
    path length of the foot point, signed distance (metres, left of the path positive) and
    the path's heading there (radians, interpolated between vertices)."""
    p = np.asarray(path, float)
    a, b = p[:-1, :2], p[1:, :2]
    ab = b - a
    len2 = np.maximum((ab**2).sum(1), 1e-18)
    th = np.unwrap(p[:, 2])
    out_s, out_d, out_t = [], [], []
    for c0 in range(0, len(xy), chunk):
        q = np.asarray(xy[c0 : c0 + chunk], float)[:, None, :]
        f = np.clip(((q - a) * ab).sum(-1) / len2, 0.0, 1.0)
        foot = a + f[..., None] * ab
        d2 = ((q - foot) ** 2).sum(-1)
        j = np.argmin(d2, axis=1)
        r = np.arange(len(j))
        fj = f[r, j]
        v = q[:, 0, :] - foot[r, j]
        seg = ab[j] / np.sqrt(len2[j])[:, None]
        out_s.append(s_path[j] + fj * (s_path[j + 1] - s_path[j]))
        out_d.append(seg[:, 0] * v[:, 1] - seg[:, 1] * v[:, 0])
        out_t.append(th[j] + fj * (th[j + 1] - th[j]))
    return np.concatenate(out_s), np.concatenate(out_d), np.concatenate(out_t)


def resample_rows(s_frames: np.ndarray, lines: np.ndarray, s_grid: np.ndarray, max_gap_m: float):
    """Lines of frames at path lengths ``s_frames`` (increasing, metres) linearly interpolated
    at ``s_grid``: returns ``(values (M, A) float64, valid (M,) bool)``; a row is valid when it
    lies between two frames at most ``max_gap_m`` apart."""
    s = np.asarray(s_frames, float)
    out = np.zeros((len(s_grid), lines.shape[1]))
    valid = np.zeros(len(s_grid), bool)
    if len(s) < 2:
        return out, valid
    i = np.clip(np.searchsorted(s, s_grid, side="right") - 1, 0, len(s) - 2)
    gap = s[i + 1] - s[i]
    f = (s_grid - s[i]) / np.maximum(gap, 1e-12)
    valid = (f >= -1e-9) & (f <= 1 + 1e-9) & (gap <= max_gap_m) & (gap > 0)
    f = np.clip(f, 0.0, 1.0)[:, None]
    out = lines[i] * (1.0 - f) + lines[i + 1] * f
    return out, valid


def interpolate_corrections(odo: np.ndarray, kept: np.ndarray, optimized: np.ndarray) -> np.ndarray:
    """Optimized poses ``(N, 3)`` of every frame from those of the ``kept`` frames
    (``optimized (K, 3)``, ``kept`` indices increasing): between two kept frames, the odometry
    increments composed on both ends, blended by SE(2) interpolation along the way; before the
    first and after the last kept frame, the odometry increments from it."""
    odo = np.asarray(odo, float)
    n = len(odo)
    kept = np.asarray(kept, int)
    seg = np.clip(np.searchsorted(kept, np.arange(n), side="right") - 1, 0, len(kept) - 1)
    k0 = kept[seg]
    from_a = se2_compose(optimized[seg], se2_between(odo[k0], odo))
    nxt = np.minimum(seg + 1, len(kept) - 1)
    k1 = kept[nxt]
    from_b = se2_compose(optimized[nxt], se2_between(odo[k1], odo))
    span = np.maximum(k1 - k0, 1)
    f = np.where(k1 > k0, np.clip((np.arange(n) - k0) / span, 0.0, 1.0), 0.0)
    return se2_interpolate(from_a, from_b, f)


def keep_every(s: np.ndarray, step_m: float) -> np.ndarray:
    """Indices of the frames kept at one per ``step_m`` metres of path ``s`` (the first and
    the last frame always)."""
    s = np.asarray(s, float)
    kept = [0]
    for i in range(1, len(s)):
        if s[i] - s[kept[-1]] >= step_m - 1e-9:
            kept.append(i)
    if kept[-1] != len(s) - 1:
        kept.append(len(s) - 1)
    return np.asarray(kept, int)


@dataclass
class RowMatch:
    """Where one horizon line best matches the rows of an ORP (by correlation alone).

    Attributes:
        s: path length of the match (metres; sub-row by a parabola when the peak is interior).
        dtheta: heading of the line's camera minus the route's there (radians).
        ncc: the NCC at the match. interior: the peak is not at the first or last row.
    """

    s: float
    dtheta: float
    ncc: float
    interior: bool


def match_rows(orp: ORP, line: np.ndarray, highpass_cycles: int = 3) -> RowMatch:
    """The ORP row (path length) and azimuth shift at which ``line`` (``(A,)`` grey levels)
    correlates best: circular cross-correlation against every row (one FFT product each),
    refined to a fraction of a row and of an azimuth sample by parabolas."""
    rows = signatures(orp.lines, highpass_cycles)
    q = signatures(np.asarray(line, np.float64)[None], highpass_cycles)[0]
    n = orp.lines.shape[1]
    curves = np.fft.irfft(rows * np.conj(q), n=n, axis=-1)  # (M, A): NCC per row and shift
    best = curves.max(1)
    i = int(np.argmax(best))
    interior = 0 < i < len(best) - 1
    fi = 0.0
    if interior:
        den = best[i - 1] - 2.0 * best[i] + best[i + 1]
        fi = float(np.clip(0.5 * (best[i - 1] - best[i + 1]) / den, -0.5, 0.5)) if den < 0 else 0.0
    c = curves[i]
    k = int(np.argmax(c))
    c_m, c_0, c_p = c[(k - 1) % n], c[k], c[(k + 1) % n]
    den = c_m - 2.0 * c_0 + c_p
    fk = float(np.clip(0.5 * (c_m - c_p) / den, -0.5, 0.5)) if den < 0 else 0.0
    # rows[i] (reference) at azimuth a + d matches the line at a: d = heading(line) - heading(row)
    return RowMatch(orp.s0 + (i + fi) * orp.spacing_m, float(wrap_angle((k + fk) * 2.0 * math.pi / n)),
                    float(best[i]), interior)
