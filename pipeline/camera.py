"""The downward camera model shared by the simulator (forward rendering) and ingest (rectification).

Frames: a raw image pixel ``(u, v)`` (column, row) sees the floor point whose vehicle-frame
coordinates are ``xv = h * xn``, ``yv = -h * yn`` where ``(xn, yn)`` are the undistorted
normalized image coordinates (OpenCV's radial-tangential model) and ``h`` the optical
centre's height above the floor (metres). The principal point therefore sees the pose
position, and the raw image's column axis is the vehicle's +x, its row axis the vehicle's
-y, as for rectified frames (:mod:`mapstore.grid`).

Omni cameras (``model = "omni"``) have their geometry in :mod:`tracker.omnicam` and their
bird's-eye rectification in :mod:`pipeline.omni_ingest`; only the photometric functions
here (:func:`normalized_radius2`, :func:`vignetting_gain`) apply to them.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from mapstore.grid import frame_centre, frame_pixels_to_vehicle, vehicle_to_frame_pixels
from pipeline.drivelog import CameraSpec
from pipeline.resample import ExactSampler


def normalized_radius2(camera: CameraSpec, shape: tuple[int, int]) -> np.ndarray:
    """Squared distance of every raw pixel from the principal point, in focal lengths
    (intrinsics) or half-diagonals (rectified images), or for omni cameras from the mirror
    axis' image in rim radii (half-diagonals without a rim): the ``r^2`` of the vignetting model."""
    h, w = shape
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    if camera.is_omni:
        om = camera.omni
        scale = om.rim_radius_px if om.rim_radius_px > 0 else np.hypot((w - 1) / 2.0, (h - 1) / 2.0)
        return ((cols - om.cx) ** 2 + (rows - om.cy) ** 2) / scale**2
    if camera.rectified:
        cx, cy = frame_centre(shape)
        scale2 = ((w - 1) / 2.0) ** 2 + ((h - 1) / 2.0) ** 2
        return ((cols - cx) ** 2 + (rows - cy) ** 2) / scale2
    return ((cols - camera.cx) / camera.fx) ** 2 + ((rows - camera.cy) / camera.fy) ** 2


def vignetting_gain(camera: CameraSpec, shape: tuple[int, int]) -> np.ndarray:
    """Relative sensor gain ``1 + v1 r^2 + v2 r^4`` per raw pixel, float32 ``(H, W)``.

    ``r`` is the distance from the principal point in focal lengths (intrinsics) or in
    half-diagonals (rectified images), for omni cameras from the mirror axis' image in rim
    radii (as :meth:`tracker.omnicam.HyperboloidCamera.vignetting_gain`). Ones when the
    camera declares no vignetting.
    """
    if camera.vignetting is None:
        return np.ones(shape, np.float32)
    v1, v2 = camera.vignetting
    r2 = normalized_radius2(camera, shape)
    return (1.0 + v1 * r2 + v2 * r2 * r2).astype(np.float32)


def raw_pixel_ground_offsets(camera: CameraSpec, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Vehicle-frame floor coordinates (metres) seen by every raw pixel: ``(xv, yv)``, each ``(H, W)``.

    Used by the simulator to render raw (distorted) frames.
    """
    h, w = shape
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    if camera.rectified:
        return frame_pixels_to_vehicle(cols, rows, shape, camera.pixel_size_m)
    pts = np.stack([cols.ravel(), rows.ravel()], axis=-1).reshape(-1, 1, 2)
    und = cv2.undistortPointsIter(
        pts,
        camera.camera_matrix(),
        camera.distortion(),
        None,
        None,
        (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12),
    ).reshape(h, w, 2)
    return camera.height_m * und[..., 0], -camera.height_m * und[..., 1]


def rectified_shape(camera: CameraSpec, raw_shape: tuple[int, int], pixel_size: float) -> tuple[int, int]:
    """Shape ``(H, W)`` of the rectified frame covering about the raw image's footprint."""
    gx, gy = camera.ground_pixel_size
    return max(1, round(raw_shape[0] * gy / pixel_size)), max(1, round(raw_shape[1] * gx / pixel_size))


def nadir_pixel_offset(rotation: np.ndarray, height_m: float, pixel_size: float) -> tuple[float, float]:
    """Where the point below the camera lies in a tilt-corrected frame, relative to the
    frame's centre: ``(columns, rows)`` in map pixels.

    A frame turned to a nadir view by ``rotation`` (camera -> nadir camera coordinates,
    :func:`pipeline.ground_plane.nadir_rotation`) is centred on the ground point of the camera's
    optical axis, which keeps the footprint in the frame; the camera's own position (GPS) is
    below its optical centre, ``height_m x tan(tilt)`` away.
    """
    a = np.asarray(rotation, np.float64) @ (0.0, 0.0, 1.0)
    f = height_m / pixel_size
    return -f * a[0] / a[2], -f * a[1] / a[2]


def rectify_maps(
    camera: CameraSpec,
    raw_shape: tuple[int, int],
    pixel_size: float,
    out_shape: tuple[int, int] | None = None,
    rotation: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Remap tables (float32 ``(Ho, Wo)`` each) from rectified-frame pixels to raw pixels.

    The rectified frame follows :mod:`mapstore.grid`'s frame convention at ``pixel_size``
    metres per pixel, centred on the pose. With ``rotation`` (3 x 3, camera -> nadir camera
    coordinates; cameras with intrinsics only) the frame is the nadir view of a tilted
    camera, centred on its optical axis' ground point (:func:`nadir_pixel_offset`).
    """
    if out_shape is None:
        out_shape = rectified_shape(camera, raw_shape, pixel_size)
    ho, wo = out_shape
    if camera.rectified:
        rows, cols = np.mgrid[0:ho, 0:wo].astype(np.float64)
        xv, yv = frame_pixels_to_vehicle(cols, rows, out_shape, pixel_size)
        u, v = vehicle_to_frame_pixels(xv, yv, raw_shape, camera.pixel_size_m)
        return u.astype(np.float32), v.astype(np.float32)
    cxo, cyo = frame_centre(out_shape)
    f = camera.height_m / pixel_size
    if rotation is not None:
        dx, dy = nadir_pixel_offset(rotation, camera.height_m, pixel_size)
        cxo, cyo = cxo + dx, cyo + dy
    new_k = np.array([[f, 0, cxo], [0, f, cyo], [0, 0, 1.0]])
    r = None if rotation is None else np.asarray(rotation, np.float64)
    map_x, map_y = cv2.initUndistortRectifyMap(
        camera.camera_matrix(), camera.distortion(), r, new_k, (wo, ho), cv2.CV_32FC1
    )
    return map_x, map_y


INTERPOLATION = {"cubic": cv2.INTER_CUBIC, "lanczos4": cv2.INTER_LANCZOS4, "linear": cv2.INTER_LINEAR}


class Rectifier:
    """Raw image (float32, grey levels) -> rectified ground frame at the map pixel size.

    Builds its remap tables once (per camera, raw size and camera height) and reuses them.
    Applies the flat field (relative gain per raw pixel) before resampling, and a Gaussian
    pre-filter when rectification shrinks the image, so that downsampling does not alias.
    With per-frame ``heights`` (metres; cameras whose height varies) each frame is
    rectified at its own height into the frame size of the reference height; with per-frame
    ``rotations`` (:mod:`pipeline.ground_plane`) each is turned to a nadir view.

    A log of rectified images at the map pixel size (tiles, or a map pixel left automatic)
    maps onto itself: every pixel is kept as it is and valid (no resampling, so nothing
    to erode; a 12 px overlap strip keeps its 12 px).

    Attributes:
        out_shape: rectified frame shape ``(H, W)``.
        valid: bool ``(H, W)``, True where the rectified pixel comes from inside the raw
            image (for every height and rotation given).
        identity: True when the rectification is the identity (see above).
    """

    MAX_TABLES = 4

    def __init__(
        self,
        camera: CameraSpec,
        raw_shape: tuple[int, int],
        pixel_size: float,
        *,
        interpolation: str = "cubic",
        erode_px: int = 2,
        flat_field: np.ndarray | None = None,
        heights: np.ndarray | None = None,
        rotations: np.ndarray | None = None,
    ):
        self.camera = camera
        self.raw_shape = tuple(raw_shape)
        self.pixel_size = pixel_size
        self.out_shape = rectified_shape(camera, raw_shape, pixel_size)
        self.interpolation = INTERPOLATION[interpolation]
        self.erode_px = erode_px
        self._maps: dict[float | None, tuple[np.ndarray, np.ndarray]] = {}
        map_x, map_y = self._maps_for(None)
        rows, cols = np.mgrid[0 : self.out_shape[0], 0 : self.out_shape[1]]
        self.identity = bool(camera.rectified and self.out_shape == self.raw_shape
                             and np.abs(map_x - cols).max() < 1e-4 and np.abs(map_y - rows).max() < 1e-4)
        valid = np.ones(self.out_shape, bool) if self.identity else self._valid(map_x, map_y)
        self.rotations = None if rotations is None or camera.rectified else np.asarray(rotations, np.float64)
        if self.rotations is not None:
            # Every frame's own footprint: the valid area is where all of them hold pixels.
            for i, r in enumerate(self.rotations):
                cam = camera if heights is None else dataclasses.replace(camera, height_m=float(heights[i]))
                valid &= self._valid(*rectify_maps(cam, self.raw_shape, pixel_size, self.out_shape, r))
        elif heights is not None and not camera.rectified:
            # The footprint shrinks with the height: the lowest frame bounds the valid area.
            valid &= self._valid(*rectify_maps(dataclasses.replace(camera, height_m=float(np.min(heights))),
                                               self.raw_shape, pixel_size, self.out_shape))
        self.valid = valid
        gx, gy = camera.ground_pixel_size
        shrink = pixel_size / min(gx, gy)
        if heights is not None and not camera.rectified:
            shrink *= camera.height_m / float(np.min(heights))
        self.prefilter_sigma = 0.5 * np.sqrt(shrink**2 - 1.0) if shrink > 1.05 else 0.0
        self.inv_flat = None if flat_field is None else (1.0 / np.maximum(flat_field, 1e-3)).astype(np.float32)

    @staticmethod
    def _key(height: float | None) -> float | None:
        return None if height is None else round(float(height), 3)  # millimetre steps

    def _maps_for(self, key: float | None) -> tuple[np.ndarray, np.ndarray]:
        maps = self._maps.get(key)
        if maps is None:
            cam = self.camera if key is None else dataclasses.replace(self.camera, height_m=key)
            maps = rectify_maps(cam, self.raw_shape, self.pixel_size, self.out_shape)
            if len(self._maps) >= self.MAX_TABLES:  # heights vary per frame: keep a few
                self._maps.pop(next(k for k in self._maps if k is not None))
            self._maps[key] = maps
        return maps

    def _valid(self, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
        h, w = self.raw_shape
        inside = (map_x >= 0.5) & (map_x <= w - 1.5) & (map_y >= 0.5) & (map_y <= h - 1.5)
        if self.erode_px > 0:
            k = np.ones((2 * self.erode_px + 1, 2 * self.erode_px + 1), np.uint8)
            inside = cv2.erode(inside.astype(np.uint8), k, borderValue=0).astype(bool)
        return inside

    def __call__(self, raw: np.ndarray, height: float | None = None, frame: int | None = None) -> np.ndarray:
        """Rectify one raw frame (at ``height`` metres when the camera height varies; turned
        to a nadir view by ``rotations[frame]`` when the rectifier has rotations)."""
        img = raw.astype(np.float32, copy=False)
        if self.inv_flat is not None:
            img = img * self.inv_flat
        if self.identity:
            return np.array(img, np.float32, copy=True)
        if self.prefilter_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), self.prefilter_sigma)
        if self.rotations is not None and frame is not None:
            cam = self.camera if height is None else dataclasses.replace(self.camera, height_m=float(height))
            map_x, map_y = rectify_maps(cam, self.raw_shape, self.pixel_size, self.out_shape, self.rotations[frame])
        else:
            map_x, map_y = self._maps_for(None if self.camera.rectified else self._key(height))
        if self.interpolation in (cv2.INTER_CUBIC, cv2.INTER_LANCZOS4):
            # Exact positions: OpenCV's 1/32-pixel rounding would add a fixed sub-pixel
            # distortion pattern, coherent where the remap is near a translation.
            out = ExactSampler(img, interpolation=self.interpolation)(map_x, map_y)
        else:
            out = cv2.remap(img, map_x, map_y, self.interpolation, borderMode=cv2.BORDER_REPLICATE)
        out[~self.valid] = 0.0
        return out
