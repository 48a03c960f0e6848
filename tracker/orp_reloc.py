"""Global relocalization on a route panorama (ORP): a pose from one horizon line and no prior.

Vehicle side: numpy and OpenCV only (with :mod:`tracker.orp`, :mod:`mapstore.grid`).

Gaspar et al. (2000) (section II): turning the vehicle circularly shifts its panorama, so a comparison
that does not depend on the shift recognizes a place whatever the heading; the seed uses the
panoramas' power spectra in a PCA eigenspace. Here the comparison keeps the phase: the
**maximum over all shifts of the circular cross-correlation** of two prepared lines (as
heading-invariant as the power spectrum, which is the correlation's Fourier magnitude, but
it also needs the panels to be in the same order). Measured on the 20 m loop
(``bench/bench_orp_track.py``; a candidate within 30 cm of the truth among the first six):
power spectra (DFT magnitudes 1..48, any high-pass / normalization / PCA tried) 19-39 % of the
night frames, 72-83 % at 30 deg across the route; the maximal cross-correlation 100 % at night,
and with a second, coarser preparation for the parallax of off-route poses, 95 % across.

1. **Index**: every ``index_spacing_m`` of path length, the route row prepared at each of the
   ``scales`` (high-pass / normalization / smoothing sigmas in degrees of azimuth: log
   intensity minus its Gaussian, divided by its local RMS, smoothed, as the localizer
   prepares lines), zero-mean and unit length, kept as conjugate spectra (``rfft``).
2. **Candidates**: for the live line, per scale, the correlation of every indexed row at
   every shift (one batched inverse FFT); the rows whose best shift correlates most, no two
   within ``separation_m`` of path length: ``candidates`` per scale, merged. The best shift
   ``k`` (sub-sample, parabolic) of a row gives the heading: ``theta_row - k /
   samples_per_degree`` (degrees).
3. **Verification**: :meth:`tracker.orp.ORPLocalizer.localize` from each (row position,
   heading); the ``refine`` best distinct fits are localized again from their own pose
   (a start 30 cm beside the route does not converge within one call's trust region).
4. **Decision**: fits are ranked by :meth:`ORPRelocalizer.score` (NCC x sqrt(valid
   fraction)); the best is accepted when it is ok with NCC >= ``min_ncc``, and refused as
   ``ambiguous`` when another fit more than ``distinct_m`` away (metres, world frame) scores
   within ``ambiguity_margin`` of it (a repeated place: rather lost than a
   confident wrong fix); otherwise ``lost``.

:meth:`ORPRelocalizer.locate` returns an :class:`ORPRelocResult` (status ``ok``,
``ambiguous`` or ``lost``, the fix, the candidates tried, the time taken).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from mapstore.knobs import knob
from tracker.orp import ORP, ORPFix, ORPLocalizer, prepare_lines
from tracker.params import params_from_dict

__all__ = ["ORPRelocParams", "ORPRelocResult", "ORPRelocalizer"]

OK, AMBIGUOUS, LOST = "ok", "ambiguous", "lost"


@dataclass(frozen=True)
class ORPRelocParams:
    """Relocalization settings (``[tracker.orp_reloc]`` of configs/tracker.toml documents each)."""

    index_spacing_m: float = knob(gt=0.0, default=0.1)
    scales: tuple[tuple[float, float, float], ...] = knob(ge=0.0, default=((2.0, 2.0, 1.0), (5.0, 5.0, 2.0)))
    candidates: int = knob(ge=1, default=4)
    separation_m: float = knob(ge=0.0, default=0.5)
    refine: int = knob(ge=0, default=3)
    min_ncc: float = knob(ge=-1.0, le=1.0, default=0.8)
    distinct_m: float = knob(ge=0.0, default=0.3)
    ambiguity_margin: float = knob(ge=0.0, default=0.05)

    @classmethod
    def from_dict(cls, d: dict) -> "ORPRelocParams":
        """From a ``[tracker.orp_reloc]`` table; an unknown key, a wrong type or a value out of
        range raises ValueError (:class:`mapstore.knobs.ConfigError`)."""
        return params_from_dict(cls, d, "tracker.orp_reloc")

    def __post_init__(self) -> None:
        if self.index_spacing_m <= 0 or self.candidates < 1 or self.refine < 0:
            raise ValueError("index_spacing_m > 0, candidates >= 1 and refine >= 0 are required")
        if not self.scales or any(len(sc) != 3 for sc in self.scales):
            raise ValueError("scales: a non-empty list of [highpass_deg, normalize_deg, smoothing_deg]")


@dataclass
class ORPRelocResult:
    """One relocalization attempt.

    Attributes:
        status: ``ok`` (``fix`` is the pose), ``ambiguous`` (two distinct places fit about
            equally well: refused), ``lost`` (no candidate verified).
        fix: the best verified :class:`tracker.orp.ORPFix` (None when nothing converged).
        runner_up: the best ok fit more than ``distinct_m`` from ``fix`` (None when none).
        candidates: ``(n, 3)`` the starting poses tried (world frame: metres, radians).
        seconds: wall time of the attempt.
        fits: every fit, in the order of ``candidates`` (refinements appended).
    """

    status: str
    fix: ORPFix | None
    runner_up: ORPFix | None
    candidates: np.ndarray
    seconds: float
    fits: list = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.status == OK


class ORPRelocalizer:
    """Global relocalization over one ORP (see the module docstring).

    Args:
        localizer: the :class:`tracker.orp.ORPLocalizer` over the route (verifies candidates).
        params: :class:`ORPRelocParams`.
    """

    def __init__(self, localizer: ORPLocalizer, params: ORPRelocParams = ORPRelocParams()):
        self.loc, self.p = localizer, params
        orp: ORP = localizer.orp
        self.spd = orp.samples_per_degree
        t0 = time.perf_counter()
        stride = max(1, int(round(params.index_spacing_m / orp.spacing_m)))
        self.rows = np.arange(0, len(orp.lines), stride, dtype=np.intp)
        self.spectra = [np.conj(np.fft.rfft(self._unit(orp.lines[self.rows], sc), axis=1)).astype(np.complex64)
                        for sc in params.scales]
        self.index_seconds = time.perf_counter() - t0
        self.last_seconds = 0.0

    @property
    def nbytes(self) -> int:
        """Memory of the index (bytes)."""
        return int(sum(f.nbytes for f in self.spectra))

    def _unit(self, lines: np.ndarray, scale) -> np.ndarray:
        """Lines prepared at ``scale`` (high-pass, normalize, smoothing degrees), zero-mean, unit length."""
        hp, nd, sm = (float(v) * self.spd for v in scale)
        x = np.atleast_2d(prepare_lines(lines, hp, sm, nd)).astype(np.float32)
        x = x - x.mean(axis=1, keepdims=True)
        return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)

    def candidates(self, line: np.ndarray) -> np.ndarray:
        """Starting poses ``(n, 3)`` (x, y metres, theta radians; world frame) for the live
        ``line`` (``(A,)`` grey levels): per scale the ``candidates`` best-correlating indexed
        rows (at their best shift), no two within ``separation_m``, the scales merged."""
        n = self.loc.n_az
        sep = self.p.separation_m / self.loc.orp.spacing_m
        out: list[list[float]] = []
        chosen: list[int] = []
        for sc, spec in zip(self.p.scales, self.spectra):
            q = np.fft.rfft(self._unit(line, sc)[0]).astype(np.complex64)
            cc = np.fft.irfft(spec * q[None, :], n=n, axis=1)  # cc[r, k] = sum_j live[j + k] row_r[j]
            k = np.argmax(cc, axis=1)
            best = cc[np.arange(len(cc)), k]
            taken: list[int] = []
            for r in np.argsort(-best):
                row = int(self.rows[r])
                if any(abs(row - j) <= sep for j in taken):
                    continue
                taken.append(row)
                if not any(abs(row - j) < 1 for j in chosen):
                    chosen.append(row)
                    out.append(self._start(row, cc[r], int(k[r])))
                if len(taken) >= self.p.candidates:
                    break
        return np.array(out, float).reshape(-1, 3)

    def _start(self, row: int, cc: np.ndarray, k: int) -> list[float]:
        """The pose at route ``row`` turned by the correlation peak at shift ``k`` (sub-sample):
        the live line is the row's shifted by ``-k`` samples, i.e. heading ``theta_row - k``."""
        n = len(cc)
        c0, cm, cp = cc[k], cc[(k - 1) % n], cc[(k + 1) % n]
        den = cm - 2.0 * c0 + cp
        sub = 0.5 * (cm - cp) / den if den < 0 else 0.0
        x, y, th = (float(v) for v in self.loc.orp.poses[row])
        return [x, y, float(th - (k + sub) / self.loc.col_per_rad)]

    def locate(self, line: np.ndarray, extra_priors: list[np.ndarray] | None = None) -> ORPRelocResult:
        """Relocalize the horizon ``line`` (``(A,)`` grey levels) on the route; ``extra_priors``
        (poses, world frame) are verified beside the index's candidates (e.g. the session's
        dead-reckoned pose) and judged by the same rules."""
        t0 = time.perf_counter()
        starts = self.candidates(line)
        extra = [np.asarray(pr, float) for pr in (extra_priors or []) if pr is not None and np.isfinite(pr).all()]
        if extra:
            starts = np.vstack([starts, np.array(extra).reshape(-1, 3)])
        fits = [self.loc.localize(line, st) for st in starts]
        # the best distinct fits converge further from their own pose
        for f in self._distinct(sorted(fits, key=lambda f: -self.score(f)))[: self.p.refine]:
            g = self.loc.localize(line, f.pose)
            if math.hypot(*(g.pose[:2] - f.pose[:2])) > 0.005:
                g = self.loc.localize(line, g.pose)
            fits.append(g)
        good = self._distinct(sorted((f for f in fits if f.ok), key=lambda f: -self.score(f)))
        best = good[0] if good else None
        runner = good[1] if len(good) > 1 else None
        if best is None or best.ncc < self.p.min_ncc:
            status = LOST
        elif runner is not None and self.score(runner) >= self.score(best) - self.p.ambiguity_margin:
            status = AMBIGUOUS
        else:
            status = OK
        self.last_seconds = time.perf_counter() - t0
        return ORPRelocResult(status, best, runner, starts, self.last_seconds, fits)

    @staticmethod
    def score(fit: ORPFix) -> float:
        """A fit's score: its NCC times the square root of its valid fraction (an NCC over the
        few azimuths left after heavy masking is easily high: measured at night, a fit 20 cm
        off with NCC 0.892 over 43 % of the azimuths beside the right one, 0.890 over 60 %)."""
        return float(fit.ncc * math.sqrt(max(fit.valid_fraction, 0.0)))

    def _distinct(self, fits: list[ORPFix]) -> list[ORPFix]:
        """``fits`` (best first) without those within ``distinct_m`` of a better one."""
        out: list[ORPFix] = []
        for f in fits:
            if all(math.hypot(*(f.pose[:2] - g.pose[:2])) > self.p.distinct_m for g in out):
                out.append(f)
        return out
