"""Omni logs at ingest: bird's-eye floor frames and horizon lines, one decode pass.

An omni frame (``[camera] model = "omni"``, :mod:`tracker.omnicam`) gives

- a **bird's-eye floor frame** (Gaspar et al. (2000): a scaled orthographic view of the floor plane,
  perspective removed): the floor point at vehicle-frame ``(xv, yv)`` (metres) is the
  camera-frame point ``(xv, yv, -height_m)``; :func:`tracker.omnicam.birdseye_unwarp`
  builds the remap table once per log into a square frame in :mod:`mapstore.grid`'s frame
  convention (columns along the vehicle's +x, rows along its -y, the centre pixel at the
  pose position = the mirror axis) at the map pixel size. Its valid mask keeps the floor
  annulus ``inner_m <= rho <= outer_m`` (:func:`floor_annulus`, ``[omni]`` of
  configs/omni.toml): the frames store, register, optimize and render treat these frames
  exactly like rectified downward frames;
- its **horizon line** (:class:`tracker.orp.HorizonSampler` with the ``[tracker.orp]``
  sampling: the vehicle's own), written per log to ``horizons/<k:03d>.npz``
  (:func:`write_horizons`, the route build's input).

Both come from the raw image after the log's declared flat field (``flat_field`` image or
``vignetting``; omni logs are not estimated: the image circle, the camera's reflection and
the walls would bias the floor-texture average the estimate relies on).
"""

from __future__ import annotations

import json
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from mapstore.grid import frame_centre
from pipeline.camera import INTERPOLATION, vignetting_gain
from pipeline.drivelog import DriveLog
from pipeline.errors import BadInput
from pipeline.fsutil import sha256_files
from pipeline.images import ImageLimits, read_grey
from pipeline.resample import ExactSampler
from tracker.omnicam import OmniCamera, birdseye_unwarp
from tracker.orp import HorizonSampler

log = logging.getLogger(__name__)

__all__ = [
    "HORIZONS_DIR",
    "HORIZON_KEYS",
    "OmniFloorParams",
    "ground_pixel_size",
    "floor_annulus",
    "omni_flat_field",
    "inverse_flat_field",
    "flat_corrected",
    "CorrectedHorizonLines",
    "BirdseyeRectifier",
    "horizon_sampler",
    "horizons_path",
    "write_horizons",
    "read_horizons",
    "write_log_horizons",
]

HORIZONS_DIR = "horizons"
# Ground radii (metres) sampled to find the annulus; fine enough for millimetre radii.
_RADIUS_STEP_M = 0.002
_AZIMUTHS = 16


@dataclass(frozen=True)
class OmniFloorParams:
    """The floor annulus settings (``[omni]`` of configs/omni.toml).

    Attributes:
        hole_margin_px: image pixels outside the camera's reflection (``hole_radius_px``)
            where the floor starts.
        outer_radius_m: largest ground radius (metres from the mirror axis) kept.
        max_pixel_ratio: the annulus ends where the radial ground pixel reaches this
            multiple of ``max(map pixel, finest ground pixel in the annulus)``.
    """

    hole_margin_px: float = 4.0
    outer_radius_m: float = 1.0
    max_pixel_ratio: float = 1.6

    @classmethod
    def from_config(cls, table: dict) -> "OmniFloorParams":
        """From the ``[omni]`` table, read through its schema (:mod:`pipeline.schema`: ranges
        checked, a ValueError naming the key)."""
        from pipeline.schema import settings
        from pipeline.schema_omni import OmniConfig

        o = settings(OmniConfig, table)
        return cls(o.hole_margin_px, o.outer_radius_m, o.max_pixel_ratio)


def _floor_points(radii_m: np.ndarray, azimuths: np.ndarray, height_m: float) -> np.ndarray:
    """Camera-frame floor points ``(R, A, 3)`` at ground radii (metres) and azimuths (radians)."""
    r, a = np.meshgrid(radii_m, azimuths, indexing="ij")
    return np.stack([r * np.cos(a), r * np.sin(a), np.full_like(r, -height_m)], axis=-1)


def ground_pixel_size(camera: OmniCamera, radii_m: np.ndarray, *, height_m: float | None = None,
                      n_azimuths: int = _AZIMUTHS) -> tuple[np.ndarray, np.ndarray]:
    """Floor metres per image pixel at ground radii ``radii_m`` (metres from the mirror axis).

    Returns ``(radial, tangential)``, each ``(R,)``: the floor distance one image pixel spans
    along the radius and across it, the worst (largest) over ``n_azimuths`` azimuths (NaN
    where the floor is not imaged). Finite differences of :meth:`project` at 1 mm.
    """
    h = camera.height_m if height_m is None else float(height_m)
    r = np.asarray(radii_m, float)
    az = np.arange(n_azimuths) * (2 * np.pi / n_azimuths)
    d = 1e-3
    pts = _floor_points(r, az, h)
    p0 = camera.project(pts)
    pr = camera.project(_floor_points(r + d, az, h))
    across = pts.copy()  # 1 mm across the radius (along the azimuth's tangent)
    across[..., 0] -= d * np.sin(az)[None, :]
    across[..., 1] += d * np.cos(az)[None, :]
    pt = camera.project(across)
    with np.errstate(invalid="ignore", divide="ignore"):
        radial = d / np.linalg.norm(pr - p0, axis=-1)
        tangential = d / np.linalg.norm(pt - p0, axis=-1)
    return np.max(radial, axis=1), np.max(tangential, axis=1)


@dataclass(frozen=True)
class Annulus:
    """The floor annulus of a bird's-eye frame (metres from the mirror axis on the floor).

    Attributes:
        inner_m, outer_m: ground radii kept (inclusive).
        ground_pixel_m: the camera's ground pixel over the annulus (metres): the geometric
            mean of the radial and tangential ground pixels at the annulus' middle radius
            (a floor map's pixel should be near it or somewhat finer: configs/omni.toml).
        finest_m: the smallest ground pixel in the annulus (metres; at its inner edge).
        limited_by: what set ``outer_m``: "outer_radius_m", "resolution" or "rim".
    """

    inner_m: float
    outer_m: float
    ground_pixel_m: float
    finest_m: float
    limited_by: str


def floor_annulus(camera: OmniCamera, pixel_size: float, params: OmniFloorParams,
                  height_m: float | None = None) -> Annulus:
    """The floor annulus the camera sees well, for a map of ``pixel_size`` metres per pixel.

    Inner radius: the smallest ground radius imaged outside ``hole_radius_px +
    hole_margin_px`` at every azimuth. Outer radius: the smallest of ``outer_radius_m``, the
    radius where the radial ground pixel reaches ``max_pixel_ratio x max(pixel_size,
    finest)`` and the largest radius imaged inside ``rim_radius_px - hole_margin_px``.
    Raises ValueError when nothing of the floor is left.
    """
    h = camera.height_m if height_m is None else float(height_m)
    radii = np.arange(_RADIUS_STEP_M, max(params.outer_radius_m, 0.0) + 2 * _RADIUS_STEP_M, _RADIUS_STEP_M)
    az = np.arange(_AZIMUTHS) * (2 * np.pi / _AZIMUTHS)
    uv = camera.project(_floor_points(radii, az, h))
    ok = np.isfinite(uv).all(-1) & camera.in_image_circle(np.nan_to_num(uv, nan=-1e9), params.hole_margin_px)
    seen = ok.all(axis=1)
    if not seen.any():
        raise ValueError("the camera sees no floor within outer_radius_m outside its own reflection")
    i0 = int(np.argmax(seen))
    i1 = i0 + (int(np.argmin(seen[i0:])) if not seen[i0:].all() else len(seen) - i0) - 1
    inner, outer_rim = float(radii[i0]), float(radii[i1])
    radial, tang = ground_pixel_size(camera, radii[i0 : i1 + 1], height_m=h)
    finest = float(np.nanmin(np.minimum(radial, tang)))
    limit = params.max_pixel_ratio * max(pixel_size, finest)
    over = np.flatnonzero(~(radial <= limit))
    outer_res = float(radii[i0 + over[0] - 1]) if over.size and over[0] > 0 else (inner if over.size else math.inf)
    outer = min(params.outer_radius_m, outer_res, outer_rim)
    limited = ("outer_radius_m" if outer == params.outer_radius_m else
               "resolution" if outer == outer_res else "rim")
    if outer < inner + 2 * pixel_size:
        raise ValueError(f"the floor annulus {inner:.3f} .. {outer:.3f} m is empty (outer radius limited by {limited})")
    mid = 0.5 * (inner + outer)
    rm, tm = ground_pixel_size(camera, np.array([mid]), height_m=h)
    return Annulus(inner, outer, float(np.sqrt(rm[0] * tm[0])), finest, limited)


def omni_flat_field(lg: DriveLog, raw_shape: tuple[int, int], mode: str, *,
                    limits: ImageLimits | None = None) -> tuple[np.ndarray | None, dict]:
    """The declared flat field of an omni log (relative gain per raw pixel, 1 at the mirror
    axis' image) per ``[ingest.flatfield] mode``, and its description for the manifest."""
    if mode not in ("auto", "calibration", "none"):
        raise BadInput("config[ingest.flatfield.mode]", f"unknown mode {mode!r} (auto, calibration, none)")
    cam = lg.camera
    if mode == "none":
        return None, {"source": "none"}
    if cam.flat_field is not None:
        path = lg.path / cam.flat_field
        flat = read_grey(path, limits=limits)  # within [ingest] caps
        if flat.shape != tuple(raw_shape):
            raise BadInput(path, f"flat-field image is {flat.shape[1]}x{flat.shape[0]}, frames are "
                                 f"{raw_shape[1]}x{raw_shape[0]}")
        if (flat <= 0).any():
            raise BadInput(path, "flat-field image has zero or negative pixels")
        c = float(cv2.getRectSubPix(flat, (1, 1), (cam.omni.cx, cam.omni.cy))[0, 0])
        return (flat / c).astype(np.float32), {"source": "flat_field image"}
    if cam.vignetting is not None:
        return vignetting_gain(cam, raw_shape), {"source": "calibration vignetting"}
    return None, {"source": "none (omni logs use the calibration only)"}


def inverse_flat_field(flat_field: np.ndarray | None) -> np.ndarray | None:
    """``1 / flat_field`` (gain floored at 1e-3), float32 raw ``(H, W)``: what multiplies a raw
    frame to correct it (:func:`flat_corrected`); None when there is no flat field."""
    return None if flat_field is None else (1.0 / np.maximum(flat_field, 1e-3)).astype(np.float32)


def flat_corrected(raw: np.ndarray, inv_flat: np.ndarray | None) -> np.ndarray:
    """A raw omni frame (grey levels, any dtype) divided pixel by pixel by the flat field
    (``inv_flat`` from :func:`inverse_flat_field`, or None: no correction), float32: the image
    ingest unwarps to bird's-eye frames and samples horizon lines from."""
    img = raw.astype(np.float32, copy=False)
    return img * inv_flat if inv_flat is not None else img


class CorrectedHorizonLines:
    """Horizon lines of raw omni frames after the flat field, exactly as ingest computes them.

    ``self(raw) == sampler.line(flat_corrected(raw, inverse_flat_field(flat_field)))`` (the
    line ingest writes to the horizons file; bit for bit): the inverse gain is made once, and
    each frame corrects only the raw window the sampler's remap reads (its source positions
    plus the interpolation kernel's reach, ``_KERNEL_PAD_PX``) into a float32 buffer that is
    zero elsewhere (pixels outside the window get zero weight in the remap). The vehicle's
    path (``mosaicmap track`` on omni logs); one buffer: not thread-safe.

    Attributes:
        sampler: the :class:`tracker.orp.HorizonSampler` (the route's sampling).
        window: raw ``(rows, cols)`` slices corrected per frame.
    """

    _KERNEL_PAD_PX = 4  # Lanczos-4 reaches 3 pixels below and 4 above; 1/32 px fixed-point rounding

    def __init__(self, sampler: HorizonSampler, raw_shape: tuple[int, int], flat_field: np.ndarray | None):
        self.sampler = sampler
        self.raw_shape = tuple(int(v) for v in raw_shape)
        if flat_field is not None and tuple(flat_field.shape) != self.raw_shape:
            raise ValueError(f"flat field {flat_field.shape} does not match raw frames {self.raw_shape}")
        u = sampler.panorama.unwarp
        h, w = self.raw_shape
        mx, my = u.map_x[u.valid], u.map_y[u.valid]
        if mx.size:
            pad = self._KERNEL_PAD_PX
            r0, r1 = max(int(np.floor(my.min())) - pad, 0), min(int(np.ceil(my.max())) + pad + 1, h)
            c0, c1 = max(int(np.floor(mx.min())) - pad, 0), min(int(np.ceil(mx.max())) + pad + 1, w)
        else:
            r0 = r1 = c0 = c1 = 0
        self.window = (slice(r0, r1), slice(c0, c1))
        inv = inverse_flat_field(flat_field)
        self._inv = None if inv is None else np.ascontiguousarray(inv[self.window])
        self._buf = np.zeros(self.raw_shape, np.float32)

    def __call__(self, raw: np.ndarray) -> np.ndarray:
        """The horizon line ``(A,)`` float32 (grey levels) of one raw frame ``(H, W)``."""
        if raw.shape != self.raw_shape:
            raise ValueError(f"raw frame {raw.shape} does not match {self.raw_shape}")
        src, out = raw[self.window], self._buf[self.window]
        if self._inv is None:
            out[...] = src
        else:
            np.multiply(src, self._inv, out=out, dtype=np.float32)
        return self.sampler.line(self._buf)


class BirdseyeRectifier:
    """Raw omni image -> bird's-eye floor frame at the map pixel size (Gaspar et al. (2000)).

    The remap table, the valid mask and the raw floor mask are built once per log. The frame
    is square, ``2 x outer_m`` metres wide, centred on the mirror axis (the pose position),
    in :mod:`mapstore.grid`'s frame convention, like :class:`pipeline.camera.Rectifier`'s.

    Attributes:
        annulus: the floor annulus (:func:`floor_annulus`).
        out_shape: frame shape ``(H, W)``.
        valid: bool ``(H, W)``: pixels in the annulus whose source lies in the image
            annulus (that source area eroded by ``erode_px``).
        raw_floor: bool raw ``(H, W)``: the raw pixels that see the floor annulus (the
            exposure figures of the quality checks are taken over them).
        prefilter_sigma: Gaussian sigma (raw pixels) applied before resampling when the
            map pixel is coarser than the camera's finest ground pixel (anti-aliasing).
        crop: the raw window (row and column slices) the resampling reads.
    """

    def __init__(self, camera: OmniCamera, raw_shape: tuple[int, int], pixel_size: float, params: OmniFloorParams,
                 *, interpolation: str = "lanczos4", erode_px: int = 2, flat_field: np.ndarray | None = None):
        self.camera = camera
        self.raw_shape = tuple(raw_shape)
        self.pixel_size = float(pixel_size)
        self.annulus = floor_annulus(camera, pixel_size, params)
        n = 2 * int(math.ceil(self.annulus.outer_m / pixel_size)) + 3  # odd: the axis on a pixel centre
        # The image annulus bounds the source only where the ring does not: at the rim (or
        # the frame's corners); the ring's inner edge lies hole_margin_px inside it.
        self.unwarp = birdseye_unwarp(camera, pixel_size, (n * pixel_size, n * pixel_size), margin_px=1.0)
        self.out_shape = self.unwarp.shape
        h, w = self.out_shape
        rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
        cx, cy = frame_centre(self.out_shape)
        rho = np.hypot(cols - cx, rows - cy) * pixel_size
        ring = (rho >= self.annulus.inner_m) & (rho <= self.annulus.outer_m)
        seen = self.unwarp.valid & self._inside_raw(self.unwarp.map_x, self.unwarp.map_y)
        if erode_px > 0:  # only where the source ends: the ring's edges lie inside the image annulus
            k = np.ones((2 * erode_px + 1, 2 * erode_px + 1), np.uint8)
            seen = cv2.erode(seen.astype(np.uint8), k, borderValue=0).astype(bool)
        valid = ring & seen
        if not valid.any():
            raise ValueError("the bird's-eye frame has no valid pixel")
        self.valid = valid
        # Resampling reads only the raw window around the floor annulus (plus the kernel's
        # reach): the crop's remap tables, made once.
        mx, my = self.unwarp.map_x[valid], self.unwarp.map_y[valid]
        pad = 6
        c0, r0 = max(int(np.floor(mx.min())) - pad, 0), max(int(np.floor(my.min())) - pad, 0)
        c1 = min(int(np.ceil(mx.max())) + pad + 1, self.raw_shape[1])
        r1 = min(int(np.ceil(my.max())) + pad + 1, self.raw_shape[0])
        self.crop = (slice(r0, r1), slice(c0, c1))
        self._map_x = np.where(valid, self.unwarp.map_x - c0, 0.0).astype(np.float32)
        self._map_y = np.where(valid, self.unwarp.map_y - r0, 0.0).astype(np.float32)
        self.raw_floor = self._raw_floor_mask()
        shrink = pixel_size / self.annulus.finest_m
        self.prefilter_sigma = 0.5 * math.sqrt(shrink**2 - 1.0) if shrink > 1.05 else 0.0
        self.interpolation = INTERPOLATION[interpolation]
        self.inv_flat = inverse_flat_field(flat_field)

    def _inside_raw(self, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
        h, w = self.raw_shape
        return (map_x >= 0.5) & (map_x <= w - 1.5) & (map_y >= 0.5) & (map_y <= h - 1.5)

    def _raw_floor_mask(self) -> np.ndarray:
        h, w = self.raw_shape
        rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
        d = self.camera.ray(np.stack([cols, rows], axis=-1))
        with np.errstate(invalid="ignore", divide="ignore"):
            t = -self.camera.height_m / d[..., 2]
            rho = t * np.hypot(d[..., 0], d[..., 1])
        ok = (d[..., 2] < 0) & (rho >= self.annulus.inner_m) & (rho <= self.annulus.outer_m)
        return ok & self.camera.image_mask(self.raw_shape)

    def correct(self, raw: np.ndarray) -> np.ndarray:
        """The raw frame (grey levels) divided by the flat field, float32."""
        return flat_corrected(raw, self.inv_flat)

    def __call__(self, corrected: np.ndarray) -> np.ndarray:
        """Bird's-eye frame (float32 grey levels, 0 outside ``valid``) of a corrected raw frame."""
        img = np.ascontiguousarray(corrected[self.crop])
        if self.prefilter_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), self.prefilter_sigma)
        mx, my = self._map_x, self._map_y
        if self.interpolation in (cv2.INTER_CUBIC, cv2.INTER_LANCZOS4):
            out = ExactSampler(img, interpolation=self.interpolation)(mx, my)
        else:
            out = cv2.remap(img, mx, my, self.interpolation, borderMode=cv2.BORDER_REPLICATE)
        out[~self.valid] = 0.0
        return out

    def describe(self) -> dict:
        """The geometry for the manifest and the report (metres, pixels)."""
        a = self.annulus
        return {"inner_radius_m": a.inner_m, "outer_radius_m": a.outer_m, "outer_limited_by": a.limited_by,
                "ground_pixel_m": a.ground_pixel_m, "finest_ground_pixel_m": a.finest_m,
                "frame_shape": list(self.out_shape), "valid_pixels": int(self.valid.sum()),
                "prefilter_sigma_px": self.prefilter_sigma}


def horizon_sampler(camera: OmniCamera, orp: dict) -> HorizonSampler:
    """The vehicle's horizon sampling from the ``[tracker.orp]`` table."""
    return HorizonSampler(camera, float(orp["samples_per_degree"]), float(orp["horizon_band_deg"]),
                          int(orp["oversample"]))


def horizons_path(out_dir: Path, index: int) -> Path:
    """``out_dir/horizons/<index:03d>.npz``: the horizon lines of the ingest's log ``index``."""
    return Path(out_dir) / HORIZONS_DIR / f"{index:03d}.npz"


def write_horizons(path: Path, lines: np.ndarray, t: np.ndarray, frame: np.ndarray, odometry: np.ndarray,
                   meta: dict) -> None:
    """Write a horizon lines file (the horizon lines file contract) atomically (temp name, rename).

    Arrays: ``lines`` float32 (N, A) grey levels; ``t`` float64 (N,) seconds; ``frame`` int32
    (N,) row in frames.csv; ``odometry`` float64 (N, 3) x, y (metres), theta (radians) in the
    log's odometry frame; ``meta`` a 0-d str array of JSON.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    n = len(t)
    a = int(np.asarray(lines).shape[-1]) if np.asarray(lines).ndim == 2 else int(round(360 * meta["samples_per_degree"]))
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as f:
        np.savez(
            f,
            lines=np.asarray(lines, np.float32).reshape(n, a),
            t=np.asarray(t, np.float64).reshape(n),
            frame=np.asarray(frame, np.int32).reshape(n),
            odometry=np.asarray(odometry, np.float64).reshape(n, 3),
            meta=np.array(json.dumps(meta, sort_keys=True)),
        )
    os.replace(tmp, path)


HORIZON_KEYS = ("lines", "t", "frame", "odometry", "meta")


def read_horizons(path: Path) -> dict:
    """A horizon lines file (:func:`write_horizons`) as a dict of its
    arrays, ``meta`` decoded from JSON. Raises :class:`BadInput` (one line naming the file)
    when it lacks an array, its meta is not JSON, or its shapes disagree: ``lines`` (N, A)
    with N >= 2, ``t`` and ``frame`` (N,), ``odometry`` (N, 3)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in HORIZON_KEYS if k not in z.files]
            if missing:
                raise BadInput(path, f"horizon file lacks {', '.join(missing)}")
            out = {k: z[k] for k in ("lines", "t", "frame", "odometry")}
            meta_text = str(z["meta"][()])
    except (OSError, ValueError) as e:  # not an npz, or a pickled array
        raise BadInput(path, f"unreadable horizon file: {e}") from None
    try:
        out["meta"] = json.loads(meta_text)
    except json.JSONDecodeError as e:
        raise BadInput(path, f"horizon file meta is not JSON: {e}") from None
    lines, odo = out["lines"], out["odometry"]
    n = len(lines) if lines.ndim == 2 else -1
    if n < 2 or odo.shape != (n, 3) or out["t"].shape != (n,) or out["frame"].shape != (n,):
        raise BadInput(path, f"horizon file: lines {lines.shape}, t {out['t'].shape}, frame {out['frame'].shape} "
                             f"and odometry {odo.shape} do not match (N >= 2 lines (N, A), N poses (N, 3))")
    return out


def write_log_horizons(lg: DriveLog, path: Path, orp: dict, route_id: str | None = None) -> int:
    """The horizon lines file of a log straight from its frames (no bird's-eye views, no
    flat field, no quality checks): the fast path tests and benchmarks of the route build use
    where the floor is not wanted. ``route_id`` overrides the log's. Returns the lines written."""
    from mapstore.grid import interpolate_trajectory

    hs = horizon_sampler(lg.camera.omni, orp)
    lines = hs.lines(read_grey(lg.image_path(i)) for i in range(len(lg.frame_images)))
    meta = horizons_meta(lg, orp)
    if route_id is not None:
        meta["route_id"] = route_id
    t = np.asarray(lg.frame_t, np.float64)
    write_horizons(path, lines, t, np.arange(len(lines)), interpolate_trajectory(lg.odometry, t), meta)
    return len(lines)


def horizons_meta(lg: DriveLog, orp: dict) -> dict:
    """The ``meta`` JSON of a log's horizon lines file (contract 2)."""
    return {
        "log_id": lg.log_id,
        "path": str(lg.path.resolve()),
        "sha256": sha256_files(lg.files()),
        "route_id": lg.route_id,
        "samples_per_degree": float(orp["samples_per_degree"]),
        "horizon_band_deg": float(orp["horizon_band_deg"]),
        "oversample": int(orp["oversample"]),
        "camera": lg.camera.omni.to_toml_dict(),
    }
