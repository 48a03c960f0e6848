"""The skeleton both tracking sessions share: predict, gate, accept, lose the lock, relocalize.

A session (:class:`tracker.session.Session` over a floor map, :class:`tracker.orp_session.ORPSession`
over a route panorama) keeps a pose (world frame: x, y metres, theta radians) and its
1-sigma (m, m, rad), and per frame:

1. **predicts** by dead reckoning: the pose composed with the odometry's motion (vehicle
   frame) and the 1-sigma grown linearly with the distance driven (Kelly (2000): error =
   error gradient x distance; :func:`dead_reckoning_growth`);
2. declares itself **lost** when the position 1-sigma outgrows ``lost_sigma_m`` (the
   localizer's search no longer covers it), or after ``lost_after`` rejected fixes in a row;
3. while lost, asks its relocalizer every ``reloc_every``-th frame;
4. **accepts** a fix: the pose and 1-sigma from the fix, the failure count reset.

What a fix is, how it is gated and what a step records is the subclass's (the floor
tracker's templates and relative mode; the route localizer's horizon line and jump gate).
Vehicle side: numpy only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from mapstore.grid import se2_compose
from mapstore.knobs import knob

__all__ = ["CoreParams", "CoreState", "SessionCore", "dead_reckoning_growth"]


def dead_reckoning_growth(odometry_delta: np.ndarray, error_gradient: float, heading_gradient: float) -> np.ndarray:
    """1-sigma (m, m, rad) that dead reckoning over ``odometry_delta`` (vehicle frame) adds:
    the error gradients (m/m, rad/m) times the distance driven (Kelly (2000))."""
    d = math.hypot(float(odometry_delta[0]), float(odometry_delta[1]))
    return np.array([error_gradient, error_gradient, heading_gradient]) * d


@dataclass(frozen=True)
class CoreParams:
    """The settings every session has (its own table in ``configs/tracker.toml`` documents
    each; a subclass restates the defaults that differ)."""

    start_sigma_m: float = knob(gt=0.0, default=0.02)
    start_sigma_rad: float = knob(gt=0.0, default=0.02)
    error_gradient: float = knob(ge=0.0, default=0.02)
    heading_gradient: float = knob(ge=0.0, default=0.02)
    lost_sigma_m: float = knob(gt=0.0, default=0.04)
    lost_after: int = knob(ge=1, default=5)
    reloc_every: int = knob(ge=1, default=1)


@dataclass
class CoreState:
    """A session's state: ``pose`` (None: none yet), ``sigma`` (1-sigma since the last fix,
    dead reckoning included), ``fails`` (rejected fixes in a row), ``lost``, ``since_reloc``
    (frames since the session was lost: the relocalizer's cadence)."""

    pose: np.ndarray | None = None
    sigma: np.ndarray = field(default_factory=lambda: np.zeros(3))
    fails: int = 0
    lost: bool = True
    since_reloc: int = 0


class SessionCore:
    """The shared loop state and its transitions (see the module docstring). Subclasses set
    ``self.p`` (a :class:`CoreParams`), may extend the state (:meth:`_new_state`) and the
    1-sigma (:attr:`sigma`), and call these from their ``step``."""

    p: CoreParams
    s: CoreState

    def _new_state(self) -> CoreState:
        return CoreState()

    def start(self, pose: np.ndarray | None, sigma: np.ndarray | None = None) -> None:
        """Start from ``pose`` (world frame) with 1-sigma ``sigma`` (default the start sigma),
        or with no pose (``None``: relocalize first)."""
        self.s = self._new_state()
        if pose is not None:
            self.s.pose = np.asarray(pose, float).copy()
            self.s.sigma = (np.asarray(sigma, float) if sigma is not None else
                            np.array([self.p.start_sigma_m, self.p.start_sigma_m, self.p.start_sigma_rad]))
            self.s.lost = False

    @property
    def sigma(self) -> np.ndarray:
        """The current 1-sigma (m, m, rad) of the pose."""
        return self.s.sigma

    def _growth(self, motion: np.ndarray) -> np.ndarray:
        return dead_reckoning_growth(motion, self.p.error_gradient, self.p.heading_gradient)

    def _predict(self, motion: np.ndarray | None) -> None:
        """Dead reckoning over ``motion`` (vehicle frame; nothing without a pose or motion)."""
        s = self.s
        if s.pose is not None and motion is not None:
            s.pose = se2_compose(s.pose, np.asarray(motion, float))
            s.sigma = np.asarray(s.sigma, float) + self._growth(motion)

    def _lose_if_uncertain(self) -> None:
        """Lost when the position 1-sigma outgrows ``lost_sigma_m``."""
        if not self.s.lost and self.sigma[:2].max() > self.p.lost_sigma_m:
            self.s.lost, self.s.since_reloc = True, 0

    def _rejected(self) -> None:
        """A fix rejected on the map: lost after ``lost_after`` in a row."""
        s = self.s
        s.fails += 1
        if s.fails >= self.p.lost_after:
            s.lost, s.since_reloc = True, 0

    def _reloc_due(self, has_relocalizer: bool) -> bool:
        """Whether this lost frame asks the relocalizer (every ``reloc_every``-th); counts it."""
        due = has_relocalizer and self.s.since_reloc % max(self.p.reloc_every, 1) == 0
        self.s.since_reloc += 1
        return due

    def _locked(self, pose: np.ndarray, sigma: np.ndarray) -> None:
        """A fix accepted: its pose and 1-sigma, the failure count reset, not lost."""
        s = self.s
        s.pose = np.asarray(pose, float).copy()
        s.sigma = sigma
        s.fails, s.lost = 0, False
