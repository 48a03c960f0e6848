"""A tracking session on a route panorama (ORP): prediction, fixes, lost lock, relocalization.

Vehicle side: numpy and OpenCV only (with :mod:`tracker.orp`, :mod:`tracker.orp_reloc`,
:mod:`mapstore.grid`). The structure and the report keys follow the floor session
(:mod:`tracker.session`).

Per omni frame, :meth:`ORPSession.step` takes its horizon line (``(A,)`` grey levels from
:class:`tracker.orp.HorizonSampler` with the route's ``samples_per_degree`` and
``horizon_band_deg``; see :meth:`ORPSession.sampler_for`) and the odometry's motion since
the previous frame (vehicle frame: metres, radians), and:

1. **predicts** the pose by dead reckoning; the 1-sigma (m, m, rad) grows linearly with the
   distance driven (``error_gradient`` m/m, ``heading_gradient`` rad/m, Kelly (2000)) on top of
   the last fix's (``fix_sigma_m``, ``fix_sigma_rad``: the localizer gives no covariance);
2. when the predicted position is within ``max_off_route_m`` of the route, **localizes** the
   line with :class:`tracker.orp.ORPLocalizer` from the prediction and **gates** the result:
   the fit must be ok with NCC >= ``min_ncc`` and a valid fraction >= ``min_valid_fraction``
   (else ``weak``), mask at most ``max_masked_fraction`` of the azimuths (else ``masked``),
   and land within ``gate_sigmas`` 1-sigmas (+ ``gate_floor_m`` / ``gate_floor_rad``) of the
   prediction in position and heading (else ``jump``: a wrong prior converging elsewhere);
3. after ``lost_after`` rejected fixes in a row, or when the position 1-sigma exceeds
   ``lost_sigma_m`` (beyond the localizer's basin), the session is **lost**: every
   ``reloc_every``-th frame asks the global relocalizer (:mod:`tracker.orp_reloc`; the
   dead-reckoned pose is verified beside its candidates, under the same ambiguity rule); an
   ok result that passes the fix gates (except the jump gate) is accepted.

Statuses of a step: ``ok`` (a fix or relocalization accepted), ``weak`` (the line does not
match the synthesized one: low NCC or too few usable azimuths), ``masked`` (too much of the
horizon disagreed), ``jump`` (the fit left the prediction's uncertainty), ``off_route`` (the
prediction is too far from the route to localize: dead reckoning, not a failure), ``lost``
(lost and the relocalizer found nothing), ``ambiguous`` (lost and the relocalizer refused two
distinct places fitting about equally). Modes (how the pose was obtained): ``fix``, ``reloc``,
``odometry`` (dead reckoning), ``none`` (no pose: lost since the start).

:func:`summarize` turns a run's steps (with ground truth when available) into the figures
``mosaicmap track`` reports on omni logs.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from mapstore.grid import wrap_angle
from mapstore.knobs import knob
from tracker.omnicam import OmniCamera
from tracker.orp import ORP, HorizonSampler, ORPFix, ORPLocalizer, ORPParams
from tracker.orp_reloc import AMBIGUOUS as RELOC_AMBIGUOUS
from tracker.orp_reloc import ORPRelocalizer
from tracker.params import params_from_dict
from tracker.run_figures import run_figures
from tracker.session_core import CoreParams, SessionCore

__all__ = ["ORPSessionParams", "ORPStep", "ORPSession", "summarize", "STATUSES", "MODES"]

OK, WEAK, MASKED, JUMP, OFF_ROUTE, LOST, AMBIGUOUS = "ok", "weak", "masked", "jump", "off_route", "lost", "ambiguous"
STATUSES = (OK, WEAK, MASKED, JUMP, OFF_ROUTE, LOST, AMBIGUOUS)
FIX, RELOC, ODOMETRY, NONE = "fix", "reloc", "odometry", "none"
MODES = (FIX, RELOC, ODOMETRY, NONE)


@dataclass(frozen=True)
class ORPSessionParams(CoreParams):
    """Session settings on a route (``[tracker.orp_session]`` in configs/tracker.toml documents
    each; the start, dead-reckoning and lost settings are
    :class:`tracker.session_core.CoreParams`', with a looser start and lost bound)."""

    start_sigma_m: float = knob(gt=0.0, default=0.05)
    start_sigma_rad: float = knob(gt=0.0, default=0.035)
    lost_sigma_m: float = knob(gt=0.0, default=0.2)
    fix_sigma_m: float = knob(gt=0.0, default=0.005)
    fix_sigma_rad: float = knob(gt=0.0, default=0.005)
    min_ncc: float = knob(ge=-1.0, le=1.0, default=0.6)
    min_valid_fraction: float = knob(ge=0.0, le=1.0, default=0.4)
    max_masked_fraction: float = knob(ge=0.0, le=1.0, default=0.5)
    gate_sigmas: float = knob(gt=0.0, default=3.0)
    gate_floor_m: float = knob(ge=0.0, default=0.03)
    gate_floor_rad: float = knob(ge=0.0, default=0.035)
    max_off_route_m: float = knob(gt=0.0, default=0.6)

    @classmethod
    def from_dict(cls, d: dict) -> "ORPSessionParams":
        """From a ``[tracker.orp_session]`` table; an unknown key, a wrong type or a value out of
        range raises ValueError (:class:`mapstore.knobs.ConfigError`)."""
        return params_from_dict(cls, d, "tracker.orp_session")


@dataclass
class ORPStep:
    """One frame of an ORP session.

    ``status`` and ``mode``: see the module docstring. ``pose`` (x, y, theta; world frame,
    metres, radians; NaN when none) and ``sigma`` (1-sigma m, m, rad) after the step. ``fix``:
    the localizer's result (the relocalizer's best when relocalizing; None when none was
    tried). ``fix_seconds`` / ``fix_cpu_seconds``: wall / thread CPU time of the localization
    from the prediction (0 when none); ``reloc_seconds``: time of a relocalization attempt.
    """

    index: int
    status: str
    mode: str
    pose: np.ndarray
    sigma: np.ndarray
    fix: ORPFix | None = None
    fix_seconds: float = 0.0
    fix_cpu_seconds: float = 0.0
    reloc_seconds: float = 0.0
    lost: bool = False

    @property
    def ok(self) -> bool:
        return self.status == OK

    @property
    def seconds(self) -> float:
        return self.fix_seconds + self.reloc_seconds


class ORPSession(SessionCore):
    """The tracking loop over one route (see the module docstring).

    Args:
        localizer: the :class:`tracker.orp.ORPLocalizer` over the route's ORP.
        relocalizer: an :class:`tracker.orp_reloc.ORPRelocalizer` (None: a lost session stays lost).
        params: :class:`ORPSessionParams`.
    """

    def __init__(self, localizer: ORPLocalizer, relocalizer: ORPRelocalizer | None = None,
                 params: ORPSessionParams | None = None):
        self.loc = localizer
        self.reloc = relocalizer
        self.p = params or ORPSessionParams()
        self.s = self._new_state()
        self.index = 0
        self._fix_sigma = np.array([self.p.fix_sigma_m, self.p.fix_sigma_m, self.p.fix_sigma_rad])

    @staticmethod
    def sampler_for(orp: ORP, camera: OmniCamera, params: ORPParams = ORPParams()) -> HorizonSampler:
        """The horizon sampler for live frames on ``orp``: the route's samples per degree and
        horizon band, ``params.oversample``."""
        return HorizonSampler(camera, orp.samples_per_degree, orp.horizon_band_deg, params.oversample)

    def distance_to_route(self, xy: np.ndarray) -> float:
        """Distance (metres) from ``xy`` to the nearest route row's position."""
        d = self.loc.xy - np.asarray(xy, float)[:2]
        return float(np.sqrt(np.min(np.einsum("ij,ij->i", d, d))))

    def _quality(self, fix: ORPFix) -> str:
        """The gate a fix fails on its own (weak, masked), or ok."""
        p = self.p
        if not fix.ok or fix.ncc < p.min_ncc or fix.valid_fraction < p.min_valid_fraction:
            return WEAK
        if fix.masked_fraction > p.max_masked_fraction:
            return MASKED
        return OK

    def _within_gate(self, fix: ORPFix, pred: np.ndarray, sigma: np.ndarray) -> bool:
        p = self.p
        dxy = math.hypot(fix.pose[0] - pred[0], fix.pose[1] - pred[1])
        dth = abs(float(wrap_angle(fix.pose[2] - pred[2])))
        return (dxy <= p.gate_sigmas * float(sigma[:2].max()) + p.gate_floor_m
                and dth <= p.gate_sigmas * float(sigma[2]) + p.gate_floor_rad)

    def _accept(self, fix: ORPFix) -> None:
        self._locked(fix.pose, self._fix_sigma.copy())

    def step(self, line: np.ndarray, motion: np.ndarray | None) -> ORPStep:
        """Process one horizon ``line`` (``(A,)`` grey levels); ``motion``: the odometry's
        motion since the previous frame (vehicle frame; None for the first)."""
        s = self.s
        i = self.index
        self.index += 1
        self._predict(motion)
        self._lose_if_uncertain()
        if s.lost:
            return self._relocalize(line, i)
        return self._track(line, i)

    def _track(self, line: np.ndarray, i: int) -> ORPStep:
        s, p = self.s, self.p
        if self.distance_to_route(s.pose) > p.max_off_route_m:
            return self._result(i, OFF_ROUTE, ODOMETRY)
        t0, c0 = time.perf_counter(), time.thread_time()
        fix = self.loc.localize(line, s.pose)
        secs, cpu = time.perf_counter() - t0, time.thread_time() - c0
        status = self._quality(fix)
        if status == OK and not self._within_gate(fix, s.pose, s.sigma):
            status = JUMP
        if status == OK:
            self._accept(fix)
            return self._result(i, OK, FIX, fix=fix, fix_seconds=secs, cpu=cpu)
        self._rejected()
        return self._result(i, status, ODOMETRY, fix=fix, fix_seconds=secs, cpu=cpu)

    def _relocalize(self, line: np.ndarray, i: int) -> ORPStep:
        s = self.s
        mode = NONE if s.pose is None else ODOMETRY
        if not self._reloc_due(self.reloc is not None):
            return self._result(i, LOST, mode)
        res = self.reloc.locate(line, extra_priors=None if s.pose is None else [s.pose])
        if res.ok and self._quality(res.fix) == OK:
            self._accept(res.fix)
            return self._result(i, OK, RELOC, fix=res.fix, reloc_seconds=res.seconds)
        status = AMBIGUOUS if res.status == RELOC_AMBIGUOUS else LOST
        return self._result(i, status, mode, fix=res.fix, reloc_seconds=res.seconds)

    def _result(self, i: int, status: str, mode: str, *, fix: ORPFix | None = None, fix_seconds: float = 0.0,
                cpu: float = 0.0, reloc_seconds: float = 0.0) -> ORPStep:
        s = self.s
        pose = np.full(3, np.nan) if s.pose is None else s.pose.copy()
        sigma = np.full(3, np.nan) if s.pose is None else s.sigma.copy()
        return ORPStep(i, status, mode, pose, sigma, fix, fix_seconds, cpu, reloc_seconds, s.lost)




def summarize(steps: list[ORPStep], truth: np.ndarray | None, wrong_m: float = 0.10) -> dict:
    """The figures of a run on a route (report keys of ``mosaicmap track`` on omni logs; the
    floor session's keys where they apply): ``fixes`` (frames), ``ok``, ``ok_rate``,
    ``statuses``, ``modes``, ``fixes_per_s`` and ``latency_ms`` (localizations from the
    prediction, wall clock: p50, p99, max), ``cpu_fixes_per_s``, ``cpu_latency_ms``,
    ``relocalizations`` (accepted) and ``relocalization`` (attempts, seconds median / max,
    ``first_ok_frame``: the first frame relocalized), ``tracker_seconds``; with ``truth``
    ((N, 3) world poses of the frames), over the ok steps: ``error_mean_m``,
    ``error_rms_m``, ``error_median_m``, ``error_max_m`` (position, metres),
    ``heading_rms_deg`` (also as the floor's ``heading_error_rms_deg``), ``heading_max_deg``,
    ``wrong_ok`` (ok steps off by more than ``wrong_m`` metres) and ``wrong_m``."""
    ok = np.array([st.ok for st in steps], bool)
    out = run_figures(steps, MODES, RELOC)
    if truth is None:
        return out
    poses = np.array([st.pose for st in steps]).reshape(-1, 3)
    err = np.hypot(poses[:, 0] - truth[:, 0], poses[:, 1] - truth[:, 1])
    herr = np.degrees(np.abs(wrap_angle(poses[:, 2] - truth[:, 2])))
    e, h = err[ok], herr[ok]
    has = bool(ok.any())
    out.update({
        "error_mean_m": float(e.mean()) if has else None,
        "error_rms_m": float(np.sqrt(np.mean(e**2))) if has else None,
        "error_median_m": float(np.median(e)) if has else None,
        "error_max_m": float(e.max()) if has else None,
        "heading_rms_deg": float(np.sqrt(np.mean(h**2))) if has else None,
        "heading_error_rms_deg": float(np.sqrt(np.mean(h**2))) if has else None,
        "heading_max_deg": float(h.max()) if has else None,
        "wrong_ok": int((e > wrong_m).sum()),
        "wrong_m": wrong_m,
    })
    return out
