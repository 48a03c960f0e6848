"""Omnidirectional (catadioptric) camera models and unwarping with precomputed remap tables.

Vehicle side: numpy and OpenCV only (plus :mod:`mapstore.grid` for the frame convention);
``pipeline`` imports this module, never the reverse.

Frames and units
    *Camera frame* (metres): origin at the camera's single effective viewpoint (for the
    hyperboloidal mirror: the mirror's focus O_M), ``z`` up along the mirror axis, ``x``
    forward (the vehicle's +x), ``y`` left (the vehicle's +y). The mirror axis is vertical
    and passes through the pose position (:mod:`mapstore.grid`: a pose is the position of
    the camera axis on the floor and the heading), so a floor point at vehicle-frame
    ``(xv, yv)`` is the camera-frame point ``(xv, yv, -height_m)``.
    *Azimuth* (radians): ``atan2(y, x)`` in the camera frame, 0 = vehicle +x, counter-
    clockwise. *Elevation* (radians): angle above the horizontal plane through the
    viewpoint (negative towards the floor).
    *Image* (pixels): ``(column, row)``, pixel centres at integers. Both models put the
    nadir (straight down) at the image centre ``(cx, cy)``, the vehicle's +x towards the
    image top and its +y towards the image left: the image is the scene as seen from
    above, so azimuth grows counter-clockwise on screen. (A camera looking up into a mirror
    records the left-right mirror image of this; catadioptric drivers flip the read-out.)
    A real image only holds the annulus ``hole_radius_px < r < rim_radius_px`` around
    ``(cx, cy)`` (the camera's own reflection inside, the mirror rim outside); 0 = no limit.

Models
    :class:`HyperboloidCamera`: the hyperboloidal mirror of Yagi et al. (2005) (eq. 1-4). The mirror
    is the upper sheet of ``(X^2 + Y^2) / a^2 - Z^2 / b^2 = -1`` with foci ``(0, 0, +-c)``,
    ``c = sqrt(a^2 + b^2)``; the camera's optical centre O_C sits at the second focus
    ``(0, 0, -c)`` looking up the axis with focal length ``f`` pixels. A ray from a scene
    point towards O_M is reflected by the mirror through O_C: a single viewpoint. Projection
    and back-projection are computed from that geometry (mirror intersection, then the
    pinhole), not from an approximation.
    :class:`MeiCamera`: Mei's unified model as ``cv2.omnidir`` implements it (``xi``, ``K``
    with skew, ``D = (k1, k2, p1, p2)``) in OpenCV's camera frame, which is the camera
    frame above rotated by :data:`MEI_ROTATION` (optical axis = nadir). A hyperboloidal
    mirror is exactly a Mei camera with ``xi = 2 b c / (b^2 + c^2)`` and
    ``fx = fy = f a^2 / (b^2 + c^2)`` (:meth:`HyperboloidCamera.as_mei`).

Unwarping (:func:`panorama_unwarp`, :func:`birdseye_unwarp`) precomputes a remap table once
per camera and output geometry; :meth:`Unwarp.apply` is one ``cv2.remap`` per frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import ClassVar, Union

import cv2
import numpy as np

from mapstore.grid import frame_pixels_to_vehicle

__all__ = [
    "MIRRORS",
    "MEI_ROTATION",
    "CameraFieldError",
    "HyperboloidCamera",
    "MeiCamera",
    "OmniCamera",
    "camera_from_table",
    "Unwarp",
    "Panorama",
    "panorama_unwarp",
    "birdseye_unwarp",
    "azimuth_elevation_to_directions",
]

MIRRORS = ("hyperboloid", "mei")

# Rows: OpenCV omnidir camera axes (x right, y down, z optical axis) expressed in the camera
# frame above (x forward, y left, z up): x_cv = -y, y_cv = -x, z_cv = -z. A proper rotation
# (determinant +1): image right = vehicle right, image down = backwards, optical axis = nadir.
MEI_ROTATION = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


class CameraFieldError(ValueError):
    """A bad or missing field of a ``[camera]`` table: ``field`` names it, ``what`` says why."""

    def __init__(self, field_name: str, what: str):
        self.field = field_name
        self.what = what
        super().__init__(f"[camera.{field_name}]: {what}")


def _as_points(points: np.ndarray, n: int) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.shape[-1] != n:
        raise ValueError(f"expected an array of shape (..., {n}), got {p.shape}")
    return p


def _unit(v: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore", divide="ignore"):
        return v / np.linalg.norm(v, axis=-1, keepdims=True)


@dataclass(frozen=True)
class _OmniBase:
    """Shared behaviour of the omni models (the geometry fields live in the subclasses)."""

    mirror: ClassVar[str] = ""

    # -- to be provided by subclasses -----------------------------------------------------
    def project(self, points_cam: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def ray(self, pixels: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    # -- common ---------------------------------------------------------------------------
    def radius_px(self, pixels: np.ndarray) -> np.ndarray:
        """Distance (pixels) of image points ``(..., 2)`` (column, row) from ``(cx, cy)``."""
        p = _as_points(pixels, 2)
        return np.hypot(p[..., 0] - self.cx, p[..., 1] - self.cy)

    def in_image_circle(self, pixels: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """True where image points lie in the annulus ``hole + margin < r < rim - margin``."""
        r = self.radius_px(pixels)
        ok = np.isfinite(r)
        if self.rim_radius_px > 0:
            ok &= r < self.rim_radius_px - margin_px
        if self.hole_radius_px > 0:
            ok &= r > self.hole_radius_px + margin_px
        return ok

    def image_mask(self, shape: tuple[int, int], margin_px: float = 0.0) -> np.ndarray:
        """Boolean ``(H, W)`` mask of the pixels inside the image annulus."""
        h, w = shape
        rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
        return self.in_image_circle(np.stack([cols, rows], axis=-1), margin_px)

    def vignetting_gain(self, shape: tuple[int, int], vignetting: tuple[float, float] | None) -> np.ndarray:
        """Relative gain ``1 + v1 r^2 + v2 r^4`` per pixel, float32 ``(H, W)``.

        ``r`` is the distance from ``(cx, cy)`` in rim radii (in half-diagonals of the image
        when the camera declares no rim). Ones when ``vignetting`` is None.
        """
        h, w = shape
        if vignetting is None:
            return np.ones(shape, np.float32)
        rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
        scale = self.rim_radius_px if self.rim_radius_px > 0 else math.hypot((w - 1) / 2.0, (h - 1) / 2.0)
        r2 = ((cols - self.cx) ** 2 + (rows - self.cy) ** 2) / scale**2
        return (1.0 + vignetting[0] * r2 + vignetting[1] * r2 * r2).astype(np.float32)

    def to_toml_dict(self) -> dict:
        """The ``[camera]`` fields of this model (``model`` and ``mirror`` included)."""
        d: dict = {"model": "omni", "mirror": self.mirror}
        for f in fields(self):
            d[f.name] = float(getattr(self, f.name))
        return d


@dataclass(frozen=True)
class HyperboloidCamera(_OmniBase):
    """Hyperboloidal-mirror camera of Yagi et al. (2005) (HyperOmni Vision), single viewpoint.

    Attributes:
        a_m, b_m: mirror shape (metres), eq. 1: ``(X^2 + Y^2)/a^2 - Z^2/b^2 = -1``.
        f_px: focal length of the camera looking into the mirror (pixels).
        cx, cy: image of the mirror axis (pixels, column and row).
        height_m: height of the viewpoint (the mirror focus O_M) above the floor (metres).
        rim_radius_px: outer radius of the image circle (mirror rim), pixels; 0 = none.
        hole_radius_px: inner radius (the camera's own reflection), pixels; 0 = none.
    """

    mirror: ClassVar[str] = "hyperboloid"
    a_m: float
    b_m: float
    f_px: float
    cx: float
    cy: float
    height_m: float
    rim_radius_px: float = 0.0
    hole_radius_px: float = 0.0

    @property
    def c_m(self) -> float:
        """Focal distance ``c = sqrt(a^2 + b^2)`` (metres): foci at ``(0, 0, +-c)``."""
        return math.hypot(self.a_m, self.b_m)

    @property
    def xi(self) -> float:
        """Mei's ``xi`` of this mirror: ``2 b c / (b^2 + c^2)``."""
        b, c = self.b_m, self.c_m
        return 2.0 * b * c / (b * b + c * c)

    @property
    def gamma_px(self) -> float:
        """Mei's generalized focal length (pixels): ``f a^2 / (b^2 + c^2)``."""
        b, c = self.b_m, self.c_m
        return self.f_px * self.a_m**2 / (b * b + c * c)

    @property
    def max_elevation_rad(self) -> float:
        """Elevation of the mirror's asymptote, ``asin(b / c)``: nothing above it is seen."""
        return math.asin(self.b_m / self.c_m)

    def radius_of_elevation(self, elevation_rad: np.ndarray) -> np.ndarray:
        """Image radius (pixels) where points at ``elevation_rad`` appear (eq. 3 inverted)."""
        e = np.asarray(elevation_rad, dtype=np.float64)
        b, c = self.b_m, self.c_m
        with np.errstate(invalid="ignore", divide="ignore"):
            r = self.f_px * self.a_m**2 * np.cos(e) / (2.0 * b * c - (b * b + c * c) * np.sin(e))
        return np.where(np.sin(e) < b / c, r, np.nan)

    def elevation_of_radius(self, radius_px: np.ndarray) -> np.ndarray:
        """Elevation (radians) seen at image radius ``radius_px``: Yagi et al.'s (2005) eq. 3.

        ``alpha = atan(((b^2 + c^2) sin g - 2 b c) / ((b^2 - c^2) cos g))`` with ``g`` the
        angle of the camera ray to the image plane, ``tan g = f / r`` (Yamazawa et al. 1993;
        the seed's transcription of eq. 3 writes the ratio inverted). NaN beyond the
        mirror's asymptote.
        """
        r = np.asarray(radius_px, dtype=np.float64)
        b, c = self.b_m, self.c_m
        g = np.arctan2(self.f_px, r)
        alpha = np.arctan2((b * b + c * c) * np.sin(g) - 2.0 * b * c, (b * b - c * c) * np.cos(g))
        # arctan2 with a negative denominator lands in the wrong half-plane: fold back to (-pi/2, pi/2)
        alpha = np.where(alpha > np.pi / 2, alpha - np.pi, np.where(alpha < -np.pi / 2, alpha + np.pi, alpha))
        ok = self.c_m * self.f_px > self.b_m * np.hypot(self.f_px, r)
        return np.where(ok, alpha, np.nan)

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points ``(..., 3)`` (metres) -> image points ``(..., 2)`` (column, row).

        The ray from the point towards O_M meets the mirror at ``M = O_M + lam u`` (``u``
        the unit direction from O_M, ``lam = a^2 / (b - c u_z)``); M is imaged through O_C
        at ``p = f (M_x, M_y) / (M_z + c)`` (M in mirror coordinates). NaN where the
        direction misses the mirror (``u_z >= b / c``) or for the viewpoint itself.
        """
        p = _as_points(points_cam, 3)
        u = _unit(p)
        a, b, c, f = self.a_m, self.b_m, self.c_m, self.f_px
        uz = u[..., 2]
        with np.errstate(invalid="ignore", divide="ignore"):
            lam = a * a / (b - c * uz)
            mz = c + lam * uz  # mirror point height (mirror coordinates: centre at the origin)
            depth = mz + c  # its distance from O_C along the axis
            px = f * lam * u[..., 0] / depth
            py = f * lam * u[..., 1] / depth
        ok = np.isfinite(lam) & (b - c * uz > 1e-12)
        out = np.stack([self.cx - py, self.cy - px], axis=-1)
        out[~ok] = np.nan
        return out

    def ray(self, pixels: np.ndarray) -> np.ndarray:
        """Image points ``(..., 2)`` (column, row) -> unit directions ``(..., 3)`` from O_M.

        The camera ray through image-plane point ``(px, py, f)`` from O_C meets the upper
        sheet at parameter ``t = a^2 / (c f - b sqrt(f^2 + px^2 + py^2))``; the scene is
        seen from O_M along ``M - O_M``. NaN beyond the asymptote. Exact inverse of
        :meth:`project`.
        """
        q = _as_points(pixels, 2)
        px = self.cy - q[..., 1]
        py = self.cx - q[..., 0]
        a, b, c, f = self.a_m, self.b_m, self.c_m, self.f_px
        den = c * f - b * np.sqrt(f * f + px * px + py * py)
        with np.errstate(invalid="ignore", divide="ignore"):
            t = a * a / den
        d = np.stack([t * px, t * py, t * f - 2.0 * c], axis=-1)  # M - O_M, mirror axes
        d = _unit(d)
        d[den <= 1e-12 * c * f] = np.nan
        return d

    def as_mei(self) -> "MeiCamera":
        """The equivalent :class:`MeiCamera` (no distortion): same pixels for every point."""
        g = self.gamma_px
        return MeiCamera(xi=self.xi, fx=g, fy=g, cx=self.cx, cy=self.cy, height_m=self.height_m,
                         rim_radius_px=self.rim_radius_px, hole_radius_px=self.hole_radius_px)


@dataclass(frozen=True)
class MeiCamera(_OmniBase):
    """Mei's unified omnidirectional model, as ``cv2.omnidir`` calibrates and projects it.

    A camera-frame point is rotated into OpenCV's camera frame (:data:`MEI_ROTATION`),
    put on the unit sphere ``Xs``, projected from ``(0, 0, -xi)``: ``x = Xs_x / (Xs_z + xi)``
    (same for y), distorted (``k1, k2`` radial, ``p1, p2`` tangential, OpenCV's formulas) and
    mapped by ``K``: ``u = fx x_d + skew y_d + cx``, ``v = fy y_d + cy``.

    Attributes:
        xi: mirror parameter (dimensionless, >= 0; 0 = pinhole, 1 = parabolic mirror).
        fx, fy: generalized focal lengths (pixels); skew: K[0, 1] (pixels).
        cx, cy: principal point = image of the nadir (pixels).
        k1, k2, p1, p2: distortion (dimensionless).
        height_m: viewpoint height above the floor (metres).
        rim_radius_px, hole_radius_px: image annulus (pixels from (cx, cy)); 0 = none.
    """

    mirror: ClassVar[str] = "mei"
    xi: float
    fx: float
    fy: float
    cx: float
    cy: float
    height_m: float
    skew: float = 0.0
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    rim_radius_px: float = 0.0
    hole_radius_px: float = 0.0

    def camera_matrix(self) -> np.ndarray:
        """``K`` (3 x 3) as ``cv2.omnidir`` takes it."""
        return np.array([[self.fx, self.skew, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def distortion(self) -> np.ndarray:
        """``D = (k1, k2, p1, p2)``."""
        return np.array([self.k1, self.k2, self.p1, self.p2])

    def _distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r2 = x * x + y * y
        rad = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
        xd = x * rad + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
        yd = y * rad + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
        return xd, yd

    def _undistort(self, xd: np.ndarray, yd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Invert :meth:`_distort` by Newton's method (vectorized; converges to ~1e-15)."""
        if not (self.k1 or self.k2 or self.p1 or self.p2):
            return xd, yd
        x, y = xd.copy(), yd.copy()
        k1, k2, p1, p2 = self.k1, self.k2, self.p1, self.p2
        for _ in range(30):
            fx_, fy_ = self._distort(x, y)
            ex, ey = fx_ - xd, fy_ - yd
            r2 = x * x + y * y
            rad = 1.0 + k1 * r2 + k2 * r2 * r2
            drad = 2.0 * k1 + 4.0 * k2 * r2  # d rad / d(r2) * 2
            j11 = rad + x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x
            j12 = x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
            j21 = x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
            j22 = rad + y * y * drad + 6.0 * p1 * y + 2.0 * p2 * x
            det = j11 * j22 - j12 * j21
            with np.errstate(invalid="ignore", divide="ignore"):
                dx = (j22 * ex - j12 * ey) / det
                dy = (-j21 * ex + j11 * ey) / det
            x, y = x - dx, y - dy
            if np.nanmax(np.abs(np.concatenate([dx.ravel(), dy.ravel()])), initial=0.0) < 1e-15:
                break
        return x, y

    def project(self, points_cam: np.ndarray) -> np.ndarray:
        """Camera-frame points ``(..., 3)`` (metres) -> image points ``(..., 2)``; NaN where
        ``Xs_z + xi <= 0`` (behind the model's projection centre) or for the viewpoint."""
        p = _as_points(points_cam, 3) @ MEI_ROTATION.T
        s = _unit(p)
        den = s[..., 2] + self.xi
        with np.errstate(invalid="ignore", divide="ignore"):
            x, y = s[..., 0] / den, s[..., 1] / den
        xd, yd = self._distort(x, y)
        out = np.stack([self.fx * xd + self.skew * yd + self.cx, self.fy * yd + self.cy], axis=-1)
        out[~(den > 1e-12)] = np.nan
        return out

    def ray(self, pixels: np.ndarray) -> np.ndarray:
        """Image points ``(..., 2)`` -> unit directions ``(..., 3)`` in the camera frame.

        Inverts K, the distortion (Newton) and the sphere lift
        ``eta = (xi + sqrt(1 + (1 - xi^2) r^2)) / (r^2 + 1)``, ``Xs = (eta x, eta y, eta - xi)``.
        NaN where no direction maps there (``1 + (1 - xi^2) r^2 < 0``).
        """
        q = _as_points(pixels, 2)
        yd = (q[..., 1] - self.cy) / self.fy
        xd = (q[..., 0] - self.cx - self.skew * yd) / self.fx
        x, y = self._undistort(xd, yd)
        r2 = x * x + y * y
        disc = 1.0 + (1.0 - self.xi**2) * r2
        with np.errstate(invalid="ignore"):
            eta = (self.xi + np.sqrt(disc)) / (r2 + 1.0)
        s = np.stack([eta * x, eta * y, eta - self.xi], axis=-1)
        s[~(disc >= 0)] = np.nan
        return _unit(s) @ MEI_ROTATION


OmniCamera = Union[HyperboloidCamera, MeiCamera]

# Required and optional fields per mirror (all numbers); the rest of a [camera] table is the caller's.
_REQUIRED = {
    "hyperboloid": ("a_m", "b_m", "f_px", "cx", "cy", "height_m"),
    "mei": ("xi", "fx", "fy", "cx", "cy", "height_m"),
}
_POSITIVE = {"a_m", "b_m", "f_px", "fx", "fy", "height_m"}
_NON_NEGATIVE = {"xi", "rim_radius_px", "hole_radius_px"}


def camera_from_table(table: dict, *, ignore: tuple[str, ...] = ("model",)) -> OmniCamera:
    """Build an omni camera from a ``[camera]`` table (``model = "omni"``, ``mirror = ...``).

    ``ignore`` lists keys the caller handles (e.g. ``vignetting``, ``flat_field``); any
    other unknown key is an error. Raises :class:`CameraFieldError` naming the field.
    """
    mirror = table.get("mirror")
    if mirror is None:
        raise CameraFieldError("mirror", f"missing calibration field (one of: {', '.join(MIRRORS)})")
    if mirror not in MIRRORS:
        raise CameraFieldError("mirror", f"unknown mirror {mirror!r} (known: {', '.join(MIRRORS)})")
    cls = HyperboloidCamera if mirror == "hyperboloid" else MeiCamera
    names = [f.name for f in fields(cls)]
    kw: dict = {}
    for name in names:
        if name not in table:
            if name in _REQUIRED[mirror]:
                raise CameraFieldError(name, "missing calibration field")
            continue
        v = table[name]
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise CameraFieldError(name, f"must be a number, got {v!r}")
        v = float(v)
        if not math.isfinite(v):
            raise CameraFieldError(name, f"is {v} (must be finite)")
        if name in _POSITIVE and v <= 0:
            raise CameraFieldError(name, f"must be positive, got {v}")
        if name in _NON_NEGATIVE and v < 0:
            raise CameraFieldError(name, f"must be >= 0, got {v}")
        kw[name] = v
    unknown = sorted(set(table) - set(names) - {"mirror"} - set(ignore))
    if unknown:
        raise CameraFieldError(unknown[0], f"unknown calibration field for mirror = {mirror!r}")
    cam = cls(**kw)
    if cam.rim_radius_px and cam.hole_radius_px >= cam.rim_radius_px:
        raise CameraFieldError("hole_radius_px", f"must be smaller than rim_radius_px ({cam.rim_radius_px})")
    return cam


# --- unwarping ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Unwarp:
    """A precomputed remap table: output pixel -> source image position.

    Attributes:
        map_x, map_y: float32 ``(H, W)`` source column and row of each output pixel
            (-1 where the output pixel sees nothing valid).
        valid: bool ``(H, W)``: the source position lies inside the image annulus.
        interpolation: OpenCV interpolation flag used by :meth:`apply`.
    """

    map_x: np.ndarray
    map_y: np.ndarray
    valid: np.ndarray
    interpolation: int = cv2.INTER_LINEAR
    _fixed: tuple = field(default=(), repr=False, compare=False)

    @classmethod
    def from_positions(cls, cols: np.ndarray, rows: np.ndarray, valid: np.ndarray,
                       interpolation: int = cv2.INTER_LINEAR) -> "Unwarp":
        """Build from float64 source positions; invalid ones are pointed outside the image."""
        mx = np.where(valid, cols, -1.0).astype(np.float32)
        my = np.where(valid, rows, -1.0).astype(np.float32)
        fixed = cv2.convertMaps(mx, my, cv2.CV_16SC2) if interpolation != cv2.INTER_NEAREST else ()
        return cls(mx, my, np.asarray(valid, bool), interpolation, tuple(fixed))

    @property
    def shape(self) -> tuple[int, int]:
        """Output shape ``(H, W)``."""
        return self.map_x.shape

    def apply(self, image: np.ndarray, fill: float = 0.0, exact: bool = False) -> np.ndarray:
        """Unwarp one image (any dtype OpenCV remaps). ``fill`` where nothing is seen.

        By default uses OpenCV's fixed-point tables (positions rounded to 1/32 pixel, about
        twice as fast); ``exact=True`` remaps with the float tables.
        """
        if self._fixed and not exact:
            return cv2.remap(image, self._fixed[0], self._fixed[1], self.interpolation,
                             borderMode=cv2.BORDER_CONSTANT, borderValue=fill)
        return cv2.remap(image, self.map_x, self.map_y, self.interpolation,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=fill)


@dataclass(frozen=True)
class Panorama:
    """A panorama strip's geometry and remap table.

    Attributes:
        unwarp: the remap table; output ``(n_elevations, n_azimuths)``.
        azimuth_rad: ``(W,)`` azimuth of each column (0 = vehicle +x, counter-clockwise).
        elevation_rad: ``(H,)`` elevation of each row, top row highest.
        samples_per_degree: columns (and rows) per degree.
        horizon_row: the row at elevation 0 (the horizon line of Yagi et al. (2005)), or None.
    """

    unwarp: Unwarp
    azimuth_rad: np.ndarray
    elevation_rad: np.ndarray
    samples_per_degree: float
    horizon_row: int | None

    def column_of_azimuth(self, azimuth_rad: np.ndarray) -> np.ndarray:
        """Fractional column of an azimuth (radians, any wrap)."""
        deg = np.degrees(np.asarray(azimuth_rad, float)) % 360.0
        return deg * self.samples_per_degree

    def apply(self, image: np.ndarray, fill: float = 0.0) -> np.ndarray:
        """Unwarp one omni image to the panorama strip."""
        return self.unwarp.apply(image, fill)


def azimuth_elevation_to_directions(azimuth_rad: np.ndarray, elevation_rad: np.ndarray) -> np.ndarray:
    """Unit camera-frame directions ``(..., 3)`` for broadcast azimuths and elevations."""
    az, el = np.broadcast_arrays(np.asarray(azimuth_rad, float), np.asarray(elevation_rad, float))
    ce = np.cos(el)
    return np.stack([ce * np.cos(az), ce * np.sin(az), np.sin(el)], axis=-1)


def _source_positions(camera: OmniCamera, points: np.ndarray, margin_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    uv = camera.project(points)
    valid = np.isfinite(uv).all(axis=-1) & camera.in_image_circle(np.nan_to_num(uv, nan=-1e9), margin_px)
    return uv[..., 0], uv[..., 1], valid


def panorama_unwarp(
    camera: OmniCamera,
    *,
    samples_per_degree: float = 1.0,
    elevation_range_deg: tuple[float, float] = (-10.0, 10.0),
    interpolation: int = cv2.INTER_LINEAR,
    margin_px: float = 1.0,
) -> Panorama:
    """Remap table from an omni image to a panorama strip (azimuth x elevation).

    Column ``j`` holds azimuth ``j / samples_per_degree`` degrees (0 = vehicle +x, counter-
    clockwise, ``360 * samples_per_degree`` columns); row ``i`` elevation
    ``max - i / samples_per_degree`` degrees, from the top of ``elevation_range_deg`` down to
    its bottom. Pixels whose source lies within ``margin_px`` of the annulus' edges are
    invalid (the interpolation would reach outside it).
    """
    if samples_per_degree <= 0:
        raise ValueError(f"samples_per_degree must be positive, got {samples_per_degree}")
    lo, hi = sorted(float(v) for v in elevation_range_deg)
    n_az = int(round(360.0 * samples_per_degree))
    n_el = int(math.floor((hi - lo) * samples_per_degree + 1e-9)) + 1
    az = np.radians(np.arange(n_az) / samples_per_degree)
    el = np.radians(hi - np.arange(n_el) / samples_per_degree)
    d = azimuth_elevation_to_directions(az[None, :], el[:, None])
    cols, rows, valid = _source_positions(camera, d, margin_px)
    horizon = np.flatnonzero(np.abs(np.degrees(el)) < 1e-9)
    return Panorama(Unwarp.from_positions(cols, rows, valid, interpolation), az, el, float(samples_per_degree),
                    int(horizon[0]) if horizon.size else None)


def birdseye_unwarp(
    camera: OmniCamera,
    pixel_size_m: float,
    extent_m: tuple[float, float],
    *,
    height_m: float | None = None,
    interpolation: int = cv2.INTER_LINEAR,
    margin_px: float = 1.0,
) -> Unwarp:
    """Remap table from an omni image to a bird's-eye view of the floor (Gaspar et al. (2000)).

    The output is a rectified ground frame in :mod:`mapstore.grid`'s convention: square
    pixels of ``pixel_size_m`` metres, columns along the vehicle's +x, rows along its -y,
    the centre pixel ``((W-1)/2, (H-1)/2)`` at the pose position (the mirror axis).
    ``extent_m = (along x, along y)`` metres sets ``W = round(ex / s)``, ``H = round(ey / s)``.
    A floor point at vehicle ``(xv, yv)`` is the camera-frame point ``(xv, yv, -height_m)``
    (``height_m`` defaults to the camera's). ``valid`` marks pixels the image annulus sees.
    """
    if pixel_size_m <= 0:
        raise ValueError(f"pixel_size_m must be positive, got {pixel_size_m}")
    w = max(1, int(round(extent_m[0] / pixel_size_m)))
    h = max(1, int(round(extent_m[1] / pixel_size_m)))
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    xv, yv = frame_pixels_to_vehicle(cols, rows, (h, w), pixel_size_m)
    z = -(camera.height_m if height_m is None else float(height_m))
    pts = np.stack([xv, yv, np.full_like(xv, z)], axis=-1)
    src_c, src_r, valid = _source_positions(camera, pts, margin_px)
    return Unwarp.from_positions(src_c, src_r, valid, interpolation)
