"""The one owner of mosaicmap's coordinate conventions.

Every other module asks this one; none re-derives these formulas.

World frame
    x, y in metres on the floor plane; theta in radians, counter-clockwise from +x.

Pose (SE(2))
    ``(x, y, theta)``: the position of a frame's *image centre* on the floor and the
    vehicle heading, in the world (or a log's odometry) frame. Arrays of poses have shape
    ``(..., 3)``.

Frame (rectified ground image) convention
    A rectified frame of shape ``(H, W)`` at ``pixel_size`` metres per pixel has its centre
    at pixel ``((W - 1) / 2, (H - 1) / 2)`` (column, row; pixel centres at integers). The
    column axis is the vehicle's +x, the row axis the vehicle's -y (image top towards +y).
    So frame pixel ``(c, r)`` lies at vehicle-frame coordinates
    ``xv = (c - cx) * s``, ``yv = -(r - cy) * s`` and at world ``pose ⊕ (xv, yv)``.

Map grid
    A raster over the world with square pixels of ``pixel_size`` metres; columns run
    along +x, rows along -y (north up). ``(x0, y0)`` is the world position of the *centre*
    of pixel (row 0, column 0), so ``x = x0 + col * s`` and ``y = y0 - row * s``.
    (This matches OME-Zarr's convention of pixel centres at integer coordinates.)

Geographic reference (optional: maps of geotagged logs)
    A map whose world frame is a local east/north tangent plane around a point on the
    WGS 84 ellipsoid (``mosaicmap import-geotagged`` writes such logs: x east, y north,
    metres, origin = the first frame) records the origin in a :class:`GeoReference`
    (:mod:`mapstore.layout`: root attribute ``geo_reference``). World ``(x, y)`` and WGS 84
    ``(latitude, longitude)`` degrees convert through it: equirectangular, with WGS 84's
    meridional and prime-vertical radii of curvature at the origin's latitude (over a few
    kilometres the error stays far below GPS noise). Without one, x, y are local metres with
    no place on Earth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "MapGrid",
    "GeoReference",
    "GEO_PROJECTION",
    "WGS84_A",
    "WGS84_F",
    "WGS84_E2",
    "wrap_angle",
    "se2_compose",
    "se2_inverse",
    "se2_between",
    "se2_exp",
    "se2_log",
    "se2_interpolate",
    "frame_centre",
    "frame_pixels_to_vehicle",
    "vehicle_to_frame_pixels",
    "frame_pixels_to_world",
    "world_to_frame_pixels",
    "interpolate_trajectory",
    "frame_to_frame_affine",
    "frame_affine_to_rel",
    "affine_box",
]


def wrap_angle(a: np.ndarray | float) -> np.ndarray | float:
    """Wrap angles (radians) to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi


def _rot(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.cos(theta), np.sin(theta)


def se2_compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pose composition ``a ⊕ b`` (b expressed in a's frame). Shapes ``(..., 3)``."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    c, s = _rot(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, wrap_angle(a[..., 2] + b[..., 2])], axis=-1)


def se2_inverse(a: np.ndarray) -> np.ndarray:
    """Inverse pose ``⊖a``. Shape ``(..., 3)``."""
    a = np.asarray(a, dtype=float)
    c, s = _rot(a[..., 2])
    x = -(c * a[..., 0] + s * a[..., 1])
    y = -(-s * a[..., 0] + c * a[..., 1])
    return np.stack([x, y, wrap_angle(-a[..., 2])], axis=-1)


def se2_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Relative pose ``⊖a ⊕ b``: b expressed in a's frame (metres, radians)."""
    return se2_compose(se2_inverse(a), b)


def se2_exp(xi: np.ndarray) -> np.ndarray:
    """Exponential map of se(2): twist ``(vx, vy, w)`` -> pose. Shape ``(..., 3)``."""
    xi = np.asarray(xi, dtype=float)
    w = xi[..., 2]
    small = np.abs(w) < 1e-9
    ws = np.where(small, 1.0, w)
    a = np.where(small, 1.0 - w**2 / 6.0, np.sin(ws) / ws)
    b = np.where(small, w / 2.0, (1.0 - np.cos(ws)) / ws)
    x = a * xi[..., 0] - b * xi[..., 1]
    y = b * xi[..., 0] + a * xi[..., 1]
    return np.stack([x, y, wrap_angle(w)], axis=-1)


def se2_log(p: np.ndarray) -> np.ndarray:
    """Logarithm map SE(2) -> se(2) twist ``(vx, vy, w)``; inverse of :func:`se2_exp`."""
    p = np.asarray(p, dtype=float)
    w = wrap_angle(p[..., 2])
    small = np.abs(w) < 1e-9
    ws = np.where(small, 1.0, w)
    a = np.where(small, 1.0 - w**2 / 6.0, np.sin(ws) / ws)
    b = np.where(small, w / 2.0, (1.0 - np.cos(ws)) / ws)
    det = a * a + b * b
    vx = (a * p[..., 0] + b * p[..., 1]) / det
    vy = (-b * p[..., 0] + a * p[..., 1]) / det
    return np.stack([vx, vy, w], axis=-1)


def se2_interpolate(a: np.ndarray, b: np.ndarray, f: np.ndarray | float) -> np.ndarray:
    """Geodesic interpolation on SE(2): ``a ⊕ exp(f · log(⊖a ⊕ b))``, f in [0, 1]."""
    f = np.asarray(f, dtype=float)[..., None]
    return se2_compose(a, se2_exp(f * se2_log(se2_between(a, b))))


# --- rectified frames ------------------------------------------------------------------


def frame_centre(shape: tuple[int, int]) -> tuple[float, float]:
    """Pixel coordinates ``(cx, cy)`` (column, row) of the centre of a frame of ``(H, W)``."""
    h, w = shape[:2]
    return (w - 1) / 2.0, (h - 1) / 2.0


def frame_pixels_to_vehicle(
    cols: np.ndarray, rows: np.ndarray, shape: tuple[int, int], pixel_size: float
) -> tuple[np.ndarray, np.ndarray]:
    """Frame pixel (column, row) -> vehicle-frame floor coordinates (metres)."""
    cx, cy = frame_centre(shape)
    return (np.asarray(cols) - cx) * pixel_size, -(np.asarray(rows) - cy) * pixel_size


def vehicle_to_frame_pixels(
    xv: np.ndarray, yv: np.ndarray, shape: tuple[int, int], pixel_size: float
) -> tuple[np.ndarray, np.ndarray]:
    """Vehicle-frame floor coordinates (metres) -> frame pixel (column, row)."""
    cx, cy = frame_centre(shape)
    return np.asarray(xv) / pixel_size + cx, -np.asarray(yv) / pixel_size + cy


def frame_pixels_to_world(
    pose: np.ndarray,
    cols: np.ndarray,
    rows: np.ndarray,
    shape: tuple[int, int],
    pixel_size: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Frame pixel (column, row) of a frame at ``pose`` -> world (x, y) in metres."""
    xv, yv = frame_pixels_to_vehicle(cols, rows, shape, pixel_size)
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return pose[0] + c * xv - s * yv, pose[1] + s * xv + c * yv


def world_to_frame_pixels(
    pose: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    shape: tuple[int, int],
    pixel_size: float,
) -> tuple[np.ndarray, np.ndarray]:
    """World (x, y) in metres -> frame pixel (column, row) of a frame at ``pose``."""
    dx, dy = np.asarray(x) - pose[0], np.asarray(y) - pose[1]
    c, s = np.cos(pose[2]), np.sin(pose[2])
    return vehicle_to_frame_pixels(c * dx + s * dy, -s * dx + c * dy, shape, pixel_size)


def frame_to_frame_affine(
    rel: np.ndarray, shape_b: tuple[int, int], shape_a: tuple[int, int], pixel_size: float
) -> np.ndarray:
    """2x3 affine mapping pixels (col, row, 1) of frame b to pixels of frame a.

    ``rel`` is the pose of b in a's frame (:func:`se2_between`); both frames at
    ``pixel_size``. Usable with ``cv2.warpAffine`` to resample b into a's pixel frame.
    """
    cxa, cya = frame_centre(shape_a)
    cxb, cyb = frame_centre(shape_b)
    c, s = np.cos(rel[2]), np.sin(rel[2])
    a = np.array([[c, s], [-s, c]])
    t = np.array([cxa + rel[0] / pixel_size, cya - rel[1] / pixel_size]) - a @ np.array([cxb, cyb])
    return np.hstack([a, t[:, None]])


def frame_affine_to_rel(
    affine: np.ndarray, shape_b: tuple[int, int], shape_a: tuple[int, int], pixel_size: float
) -> np.ndarray:
    """Inverse of :func:`frame_to_frame_affine`: the pose of b in a's frame (metres, radians)."""
    cxa, cya = frame_centre(shape_a)
    col, row = affine @ np.array([*frame_centre(shape_b), 1.0])
    theta = np.arctan2(affine[0, 1], affine[0, 0])
    return np.array([(col - cxa) * pixel_size, -(row - cya) * pixel_size, theta])


def affine_box(affine: np.ndarray, x0: float, y0: float, x1: float, y1: float) -> tuple[float, float, float, float]:
    """The bounding box ``(u_min, v_min, u_max, v_max)`` of the rectangle ``[x0, x1] x [y0,
    y1]`` (e.g. frame pixels, columns x and rows y) under the 2x3 ``affine`` (e.g.
    :meth:`MapGrid.frame_to_grid_affine`: grid columns u, rows v). Scalar arithmetic: the
    tracker asks for a footprint's box several times per frame."""
    (a, b, c), (d, e, f) = affine.tolist()
    ax0, ax1, by0, by1 = a * x0, a * x1, b * y0, b * y1
    dx0, dx1, ey0, ey1 = d * x0, d * x1, e * y0, e * y1
    return (min(ax0, ax1) + min(by0, by1) + c, min(dx0, dx1) + min(ey0, ey1) + f,
            max(ax0, ax1) + max(by0, by1) + c, max(dx0, dx1) + max(ey0, ey1) + f)


# --- the map grid ------------------------------------------------------------------------


@dataclass(frozen=True)
class MapGrid:
    """A north-up raster over the world frame.

    Attributes:
        x0, y0: world position (metres) of the centre of pixel (row 0, col 0).
        pixel_size: metres per pixel (square pixels).
        width, height: raster size in pixels (columns, rows).
    """

    x0: float
    y0: float
    pixel_size: float
    width: int
    height: int

    @classmethod
    def covering(
        cls, xmin: float, ymin: float, xmax: float, ymax: float, pixel_size: float
    ) -> "MapGrid":
        """The smallest grid whose pixel centres span the box [xmin, xmax] x [ymin, ymax]."""
        width = int(np.ceil((xmax - xmin) / pixel_size)) + 1
        height = int(np.ceil((ymax - ymin) / pixel_size)) + 1
        return cls(float(xmin), float(ymax), float(pixel_size), width, height)

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, columns)``."""
        return self.height, self.width

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """Outer bounds ``(xmin, ymin, xmax, ymax)`` in metres, pixel edges included."""
        h = self.pixel_size / 2.0
        return (
            self.x0 - h,
            self.y0 - (self.height - 1) * self.pixel_size - h,
            self.x0 + (self.width - 1) * self.pixel_size + h,
            self.y0 + h,
        )

    def world_to_pixel(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World (x, y) metres -> fractional (column, row)."""
        return (np.asarray(x) - self.x0) / self.pixel_size, (self.y0 - np.asarray(y)) / self.pixel_size

    def pixel_to_world(self, col: np.ndarray, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fractional (column, row) -> world (x, y) metres."""
        return self.x0 + np.asarray(col) * self.pixel_size, self.y0 - np.asarray(row) * self.pixel_size

    def frame_to_grid_affine(
        self, pose: np.ndarray, frame_shape: tuple[int, int], frame_pixel_size: float
    ) -> np.ndarray:
        """2x3 affine mapping frame pixel (col, row, 1) -> grid pixel (col, row).

        Usable directly with ``cv2.warpAffine`` (with ``WARP_INVERSE_MAP`` on its inverse).
        """
        cx, cy = frame_centre(frame_shape)
        k = frame_pixel_size / self.pixel_size
        c, s = math.cos(float(pose[2])), math.sin(float(pose[2]))
        gx, gy = (float(pose[0]) - self.x0) / self.pixel_size, (self.y0 - float(pose[1])) / self.pixel_size
        # frame (dc, dr) -> vehicle (dc, -dr)*fs -> world rot -> grid (dx/gs, -dy/gs)
        # (scalar arithmetic: the tracker asks for this affine three times per fix, and a
        # dozen numpy calls on 2-vectors cost 10x the arithmetic)
        a00, a01, a10, a11 = k * c, k * s, -k * s, k * c
        return np.array([[a00, a01, gx - (a00 * cx + a01 * cy)], [a10, a11, gy - (a10 * cx + a11 * cy)]])

    def coarsened(self, factor: int) -> "MapGrid":
        """The grid whose pixel (row, col) covers this grid's ``factor`` x ``factor`` block
        of pixels starting at (factor*row, factor*col): pixel size ``factor`` times larger,
        pixel centres at the blocks' centres, partial blocks at the right and bottom edges
        included (size rounded up)."""
        f = int(factor)
        if f < 1:
            raise ValueError(f"coarsening factor must be >= 1, got {factor}")
        shift = (f - 1) * self.pixel_size / 2.0
        return MapGrid(self.x0 + shift, self.y0 - shift, self.pixel_size * f, -(-self.width // f), -(-self.height // f))

    def level(self, k: int) -> "MapGrid":
        """Pyramid level ``k`` (OME-Zarr multiscales dataset ``k``): :meth:`coarsened` by 2^k."""
        return self.coarsened(2 ** int(k))

    def extended(self, xmin: float, ymin: float, xmax: float, ymax: float) -> "MapGrid":
        """This grid grown (never shrunk) at the right and bottom edges to cover the box.

        The origin stays put, so every existing pixel keeps its coordinates (a map can
        grow without rewriting what it holds). Raises ValueError when the box reaches left
        of column 0 or above row 0.
        """
        c0, r0 = self.world_to_pixel(xmin, ymax)
        if c0 < -0.5 or r0 < -0.5:
            raise ValueError(
                f"box ({xmin:.3f}, {ymin:.3f}, {xmax:.3f}, {ymax:.3f}) m reaches left of or above the grid origin "
                f"({self.x0:.3f}, {self.y0:.3f}) m")
        c1, r1 = self.world_to_pixel(xmax, ymin)
        return MapGrid(self.x0, self.y0, self.pixel_size,
                       max(self.width, int(np.ceil(c1)) + 1), max(self.height, int(np.ceil(r1)) + 1))

    def ome_transformations(self) -> list[dict]:
        """OME-Zarr 0.5 ``coordinateTransformations`` for axes ``(y, x)`` in metres.

        OME's ``y`` axis is the world's -y (rows run south), ``x`` is the world's x: the
        physical position of array element (row, col) is ``(-y0 + row * s, x0 + col * s)``.
        """
        s = self.pixel_size
        return [{"type": "scale", "scale": [s, s]}, {"type": "translation", "translation": [-self.y0, self.x0]}]

    def to_attrs(self) -> dict:
        """JSON-serialisable description (stored in zarr attributes and manifests)."""
        return {
            "x0_m": self.x0,
            "y0_m": self.y0,
            "pixel_size_m": self.pixel_size,
            "width_px": self.width,
            "height_px": self.height,
            "axes": {"columns": "+x", "rows": "-y"},
            "origin": "centre of pixel (row 0, col 0)",
        }

    @classmethod
    def from_attrs(cls, attrs: dict) -> "MapGrid":
        return cls(
            float(attrs["x0_m"]),
            float(attrs["y0_m"]),
            float(attrs["pixel_size_m"]),
            int(attrs["width_px"]),
            int(attrs["height_px"]),
        )


def interpolate_trajectory(samples: np.ndarray, t: np.ndarray) -> np.ndarray:
    """SE(2) interpolation of a time series of poses at times ``t``.

    Args:
        samples: (M, 4) ``t, x, y, theta`` with strictly increasing t (seconds, metres, radians).
        t: (N,) query times inside ``[samples[0, 0], samples[-1, 0]]`` (clamped at the ends).

    Returns:
        (N, 3) poses ``x, y, theta``: the geodesic between the bracketing samples.
    """
    samples = np.asarray(samples, dtype=float)
    t = np.clip(np.asarray(t, dtype=float), samples[0, 0], samples[-1, 0])
    i = np.clip(np.searchsorted(samples[:, 0], t, side="right") - 1, 0, len(samples) - 2)
    t0, t1 = samples[i, 0], samples[i + 1, 0]
    f = (t - t0) / (t1 - t0)
    return se2_interpolate(samples[i, 1:], samples[i + 1, 1:], f)


# --- geographic reference ----------------------------------------------------------------

WGS84_A = 6378137.0  # WGS 84 semi-major axis (m)
WGS84_F = 1.0 / 298.257223563  # flattening
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)  # first eccentricity squared

GEO_PROJECTION = "local east/north tangent plane (equirectangular, WGS84 radii at the origin); x east, y north"


@dataclass(frozen=True)
class GeoReference:
    """Where the world frame lies on Earth: its origin (WGS 84 degrees) and projection
    (x east, y north in metres; see the module docstring)."""

    origin_latitude: float
    origin_longitude: float
    projection: str = GEO_PROJECTION

    def _radii(self) -> tuple[float, float]:
        """Metres per radian north and east at the origin."""
        phi0 = math.radians(self.origin_latitude)
        w = 1.0 - WGS84_E2 * math.sin(phi0) ** 2
        r_north = WGS84_A * (1.0 - WGS84_E2) / w**1.5
        return r_north, WGS84_A / math.sqrt(w) * math.cos(phi0)

    def from_wgs84(self, lat: np.ndarray, lon: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Latitude, longitude (degrees) -> world x (east), y (north) metres."""
        r_north, r_east = self._radii()
        dlon = (np.asarray(lon, float) - self.origin_longitude + 180.0) % 360.0 - 180.0
        return np.radians(dlon) * r_east, np.radians(np.asarray(lat, float) - self.origin_latitude) * r_north

    def to_wgs84(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World x, y (metres) -> (latitude, longitude) degrees; the inverse of :meth:`from_wgs84`
        (longitude wrapped to [-180, 180))."""
        r_north, r_east = self._radii()
        lat = self.origin_latitude + np.degrees(np.asarray(y, float) / r_north)
        lon = self.origin_longitude + np.degrees(np.asarray(x, float) / r_east)
        return lat, (lon + 180.0) % 360.0 - 180.0

    def to_attrs(self) -> dict:
        """JSON-serialisable description (the map's ``geo_reference`` root attribute)."""
        return {"crs": "EPSG:4326", "origin_latitude": float(self.origin_latitude),
                "origin_longitude": float(self.origin_longitude), "projection": self.projection}

    @classmethod
    def from_attrs(cls, attrs: dict) -> "GeoReference":
        """From :meth:`to_attrs`' dict; ValueError when a key is missing or not a valid angle."""
        try:
            lat, lon = float(attrs["origin_latitude"]), float(attrs["origin_longitude"])
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"geo_reference needs numeric origin_latitude and origin_longitude: {e}") from None
        if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
            raise ValueError(f"geo_reference origin ({lat}, {lon}) is not a latitude, longitude in degrees")
        return cls(lat, lon, str(attrs.get("projection", GEO_PROJECTION)))
