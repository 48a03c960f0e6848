"""Ground-truth routes over a rectangular floor area (pure functions).

A route is a dense path in the world frame (metres, radians; :mod:`mapstore.grid`): poses
``(x, y, theta)`` of the image centre with the heading along the direction of travel (the
camera's +x axis points forward). :class:`Route` interpolates it by arc length, so frames
(every ``frame_spacing_m``), motion-blur sub-poses and odometry samples all come from the
same continuous path. The area is the box ``[0, area_x] x [0, area_y]``; every route stays
``inset_m`` inside it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mapstore.grid import wrap_angle

__all__ = ["Route", "ROUTES", "make_route", "lawnmower", "loop", "figure8", "random_walk", "from_polyline"]


@dataclass(frozen=True)
class Route:
    """A dense path parameterised by arc length.

    Attributes:
        s: (N,) cumulative arc length, metres, starting at 0, strictly increasing.
        x, y: (N,) world position of the image centre, metres.
        theta: (N,) unwrapped heading, radians (continuous, so it can be interpolated).
    """

    s: np.ndarray
    x: np.ndarray
    y: np.ndarray
    theta: np.ndarray

    @property
    def length(self) -> float:
        """Total length in metres."""
        return float(self.s[-1])

    def at(self, s: np.ndarray) -> np.ndarray:
        """Poses ``(..., 3)`` at arc lengths ``s`` (metres); theta wrapped.

        Beyond the ends the route continues straight along its end heading, so that the
        motion blur of the first and last frames stays centred on their poses.
        """
        s = np.asarray(s, dtype=float)
        c = np.clip(s, 0.0, self.length)
        beyond = s - c
        th = np.interp(c, self.s, self.theta)
        return np.stack(
            [np.interp(c, self.s, self.x) + beyond * np.cos(th), np.interp(c, self.s, self.y) + beyond * np.sin(th),
             wrap_angle(th)],
            axis=-1,
        )

    def samples(self, spacing: float) -> np.ndarray:
        """Arc lengths ``0, spacing, 2 spacing, ... <= length`` (metres)."""
        n = int(np.floor(self.length / spacing + 1e-9)) + 1
        return np.arange(n) * spacing


def from_polyline(points: np.ndarray, step: float) -> Route:
    """Route through the dense polyline ``points`` (M, 2), resampled every ``step`` metres.

    Headings follow the direction of travel (central differences of the resampled path).
    """
    p = np.asarray(points, dtype=float)
    d = np.hypot(*np.diff(p, axis=0).T)
    keep = np.concatenate([[True], d > 1e-12])
    p = p[keep]
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(p, axis=0).T))])
    n = max(2, int(np.ceil(s[-1] / step)) + 1)
    si = np.linspace(0.0, s[-1], n)
    x, y = np.interp(si, s, p[:, 0]), np.interp(si, s, p[:, 1])
    th = np.unwrap(np.arctan2(np.gradient(y), np.gradient(x)))
    return Route(si, x, y, th)


def _arc(cx: float, cy: float, r: float, a0: float, a1: float, step: float) -> np.ndarray:
    n = max(2, int(np.ceil(abs(a1 - a0) * r / step)) + 1)
    a = np.linspace(a0, a1, n)
    return np.stack([cx + r * np.cos(a), cy + r * np.sin(a)], axis=1)


def _segment(p0, p1, step: float) -> np.ndarray:
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    n = max(2, int(np.ceil(np.hypot(*(p1 - p0)) / step)) + 1)
    f = np.linspace(0.0, 1.0, n)[:, None]
    return p0 + f * (p1 - p0)


def _box(area: tuple[float, float], inset: float) -> tuple[float, float, float, float]:
    ax, ay = area
    x0, x1 = min(inset, ax / 2), max(ax - inset, ax / 2)
    y0, y1 = min(inset, ay / 2), max(ay - inset, ay / 2)
    return x0, y0, x1, y1


def lawnmower(area: tuple[float, float], *, inset: float, lane_spacing: float, step: float) -> Route:
    """Boustrophedon: lanes along x from low y to high y, joined by semicircular U-turns.

    The lane spacing is ``lane_spacing`` (metres) or less, so that the lanes fill
    ``[inset, area_y - inset]`` evenly; the U-turn radius is half of it.
    """
    x0, y0, x1, y1 = _box(area, inset)
    span = y1 - y0
    n_lanes = max(1, int(np.ceil(span / lane_spacing - 1e-9)) + 1) if span > 0 else 1
    gap = span / (n_lanes - 1) if n_lanes > 1 else 0.0
    r = gap / 2.0
    # U-turns bulge r beyond the lane ends: they may use the inset, never leave the area
    over = max(0.0, r - inset)
    xa, xb = x0 + over, x1 - over
    if xb <= xa:
        xa = xb = (x0 + x1) / 2.0
    parts = []
    for i in range(n_lanes):
        y = y0 + i * gap
        fwd = i % 2 == 0
        parts.append(_segment((xa, y), (xb, y), step) if fwd else _segment((xb, y), (xa, y), step))
        if i + 1 < n_lanes and r > 0:
            if fwd:
                parts.append(_arc(xb, y + r, r, -np.pi / 2, np.pi / 2, step))
            else:
                parts.append(_arc(xa, y + r, r, -np.pi / 2, -3 * np.pi / 2, step))
    return from_polyline(np.vstack(parts), step)


def loop(area: tuple[float, float], *, inset: float, corner_radius: float, laps: int, step: float) -> Route:
    """Counter-clockwise rounded rectangle ``inset`` inside the area, ``laps`` times."""
    x0, y0, x1, y1 = _box(area, inset)
    r = max(1e-3, min(corner_radius, (x1 - x0) / 2, (y1 - y0) / 2))
    one = np.vstack(
        [
            _segment((x0 + r, y0), (x1 - r, y0), step),
            _arc(x1 - r, y0 + r, r, -np.pi / 2, 0, step),
            _segment((x1, y0 + r), (x1, y1 - r), step),
            _arc(x1 - r, y1 - r, r, 0, np.pi / 2, step),
            _segment((x1 - r, y1), (x0 + r, y1), step),
            _arc(x0 + r, y1 - r, r, np.pi / 2, np.pi, step),
            _segment((x0, y1 - r), (x0, y0 + r), step),
            _arc(x0 + r, y0 + r, r, np.pi, 3 * np.pi / 2, step),
        ]
    )
    return from_polyline(np.vstack([one] * max(1, laps)), step)


def figure8(area: tuple[float, float], *, inset: float, laps: int, step: float) -> Route:
    """Lemniscate of Gerono filling the inset box: ``x = cx + a sin t``, ``y = cy + b sin 2t``."""
    x0, y0, x1, y1 = _box(area, inset)
    cx, cy, a, b = (x0 + x1) / 2, (y0 + y1) / 2, (x1 - x0) / 2, (y1 - y0) / 2
    perimeter = 4 * (a + 2 * b) + 1e-9
    n = max(16, int(np.ceil(perimeter / step * 2)))
    t = np.linspace(0.0, 2 * np.pi * max(1, laps), n * max(1, laps) + 1)
    return from_polyline(np.stack([cx + a * np.sin(t), cy + b * np.sin(2 * t)], axis=1), step)


def random_walk(
    area: tuple[float, float],
    rng: np.random.Generator,
    *,
    inset: float,
    length: float,
    turn_radius: float,
    reach: float,
    walk_step: float,
    step: float,
) -> Route:
    """Smooth random walk: pursue random waypoints with a bounded turning rate.

    Waypoints are drawn inside the box ``inset + 2 turn_radius`` from the border, so that the
    path (whose curvature is at most ``1 / turn_radius``) stays inside the ``inset`` box;
    positions are finally clamped to it as a guarantee. The walk is integrated every
    ``walk_step`` metres, then resampled every ``step``.
    """
    x0, y0, x1, y1 = _box(area, inset)
    m = 2.0 * turn_radius
    wx0, wx1 = (x0 + m, x1 - m) if x1 - x0 > 2 * m else ((x0 + x1) / 2,) * 2
    wy0, wy1 = (y0 + m, y1 - m) if y1 - y0 > 2 * m else ((y0 + y1) / 2,) * 2
    n = max(2, int(np.ceil(length / walk_step)) + 1)
    px, py = float(rng.uniform(wx0, wx1)), float(rng.uniform(wy0, wy1))
    heading = float(rng.uniform(-np.pi, np.pi))
    wx, wy = float(rng.uniform(wx0, wx1)), float(rng.uniform(wy0, wy1))
    max_turn = walk_step / turn_radius
    pts = np.empty((n, 2))
    for i in range(n):
        pts[i] = px, py
        if math.hypot(wx - px, wy - py) < reach:
            wx, wy = float(rng.uniform(wx0, wx1)), float(rng.uniform(wy0, wy1))
        err = (math.atan2(wy - py, wx - px) - heading + math.pi) % (2 * math.pi) - math.pi
        heading += min(max(err, -max_turn), max_turn)
        px = min(max(px + walk_step * math.cos(heading), x0), x1)
        py = min(max(py + walk_step * math.sin(heading), y0), y1)
    return from_polyline(pts, step)


ROUTES = ("lawnmower", "loop", "figure8", "random")


def make_route(
    kind: str,
    area: tuple[float, float],
    rng: np.random.Generator,
    cfg: dict,
    footprint_height_m: float,
) -> Route:
    """The route ``kind`` over ``area`` with the ``[simulate.floor.route]`` settings ``cfg``.

    ``footprint_height_m``: the camera footprint across the direction of travel (metres),
    which sets the lawnmower lane spacing.
    """
    step = cfg["dense_step_m"]
    inset = cfg["inset_m"]
    if kind == "lawnmower":
        spacing = footprint_height_m * (1.0 - cfg["lane_overlap"])
        return lawnmower(area, inset=inset, lane_spacing=spacing, step=step)
    if kind == "loop":
        return loop(area, inset=inset, corner_radius=cfg["loop_corner_radius_m"], laps=cfg["laps"], step=step)
    if kind == "figure8":
        return figure8(area, inset=inset, laps=cfg["laps"], step=step)
    if kind == "random":
        return random_walk(
            area,
            rng,
            inset=inset,
            length=cfg["random_length_m"],
            turn_radius=cfg["random_turn_radius_m"],
            reach=cfg["random_waypoint_reach_m"],
            walk_step=cfg["random_walk_step_m"],
            step=step,
        )
    raise ValueError(f"unknown route {kind!r}")
