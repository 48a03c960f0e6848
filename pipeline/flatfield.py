"""Flat-field (vignetting) models for raw frames: from calibration, or estimated from a log.

A flat field is the sensor's relative gain per raw pixel (float32 ``(H, W)``), 1 at the
principal point (or image centre): observed = true x flat field.
"""

from __future__ import annotations

import dataclasses
from typing import Iterable

import cv2
import numpy as np

from pipeline.camera import normalized_radius2, vignetting_gain
from pipeline.drivelog import CameraSpec, DriveLog
from pipeline.errors import BadInput
from pipeline.images import ImageLimits, read_grey


def calibration_flat_field(log: DriveLog, raw_shape: tuple[int, int], *,
                           limits: ImageLimits | None = None) -> np.ndarray | None:
    """The flat field the log's calibration declares (``flat_field`` image, read within
    ``limits``, or ``vignetting``), or None."""
    cam = log.camera
    if cam.flat_field is not None:
        path = log.path / cam.flat_field
        flat = read_grey(path, limits=limits)
        if flat.shape != tuple(raw_shape):
            raise BadInput(path, f"flat-field image is {flat.shape[1]}x{flat.shape[0]}, frames are {raw_shape[1]}x{raw_shape[0]}")
        if (flat <= 0).any():
            raise BadInput(path, "flat-field image has zero or negative pixels")
        centre = ((raw_shape[1] - 1) / 2.0, (raw_shape[0] - 1) / 2.0) if cam.rectified else (cam.cx, cam.cy)
        c = float(cv2.getRectSubPix(flat, (1, 1), centre)[0, 0])
        return (flat / c).astype(np.float32)
    if cam.vignetting is not None:
        return vignetting_gain(cam, raw_shape)
    return None


def estimate_vignetting(frames: Iterable[np.ndarray], camera: CameraSpec) -> tuple[float, float]:
    """Fit the radial vignetting model ``1 + v1 r^2 + v2 r^4`` to the mean of many raw frames.

    Over many frames of a textured floor the per-pixel mean averages the texture out; what
    remains is the mean floor brightness times the sensor's gain pattern. A linear least
    squares fit of ``B + B v1 r^2 + B v2 r^4`` to it gives ``(v1, v2)``.
    """
    acc = None
    n = 0
    for f in frames:
        acc = f.astype(np.float64) if acc is None else acc + f
        n += 1
    if acc is None:
        raise ValueError("no frames to estimate vignetting from")
    return vignetting_from_mean(acc / n, camera)


def vignetting_from_mean(mean: np.ndarray, camera: CameraSpec) -> tuple[float, float]:
    """:func:`estimate_vignetting` from the frames' per-pixel mean (grey levels, raw ``(H, W)``):
    for callers that accumulate the mean themselves (ingest's one sampling pass)."""
    r2 = normalized_radius2(camera, mean.shape)
    a = np.stack([np.ones(r2.size), r2.ravel(), (r2 * r2).ravel()], axis=1)
    (b, bv1, bv2), *_ = np.linalg.lstsq(a, np.asarray(mean, np.float64).ravel(), rcond=None)
    if b <= 0:
        raise ValueError("frames are black: cannot estimate vignetting")
    return float(bv1 / b), float(bv2 / b)


def estimated_flat_field(frames: Iterable[np.ndarray], camera: CameraSpec, shape: tuple[int, int]) -> tuple[np.ndarray, tuple[float, float]]:
    """The flat field of :func:`estimate_vignetting`'s model, and its ``(v1, v2)``."""
    v = estimate_vignetting(frames, camera)
    return flat_field_of(camera, v, shape), v


def flat_field_of(camera: CameraSpec, vignetting: tuple[float, float], shape: tuple[int, int]) -> np.ndarray:
    """The flat field (relative gain, float32 raw ``(H, W)``) of the radial model ``(v1, v2)``."""
    return vignetting_gain(dataclasses.replace(camera, vignetting=tuple(vignetting)), shape)
