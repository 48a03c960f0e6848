"""World floor textures for the simulator: procedural "worn concrete" or a photograph.

All rasters are float32 ``(rows, cols)`` in grey levels (0..255 scale) on a
:class:`mapstore.grid.MapGrid` (columns along +x, rows along -y). Sizes given in metres in
the configuration are converted with the grid's pixel size. The final texture is always
band-limited by a Gaussian of ``band_limit_sigma_px`` map pixels, so that cubic
interpolation at subpixel positions is accurate.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from mapstore.grid import MapGrid
from pipeline.errors import BadInput
from pipeline.images import ImageLimits, read_grey, read_raw, write_image

__all__ = [
    "band_limit",
    "smooth_noise",
    "normalize",
    "soft_clip",
    "procedural_texture",
    "photo_texture",
    "write_float_tiff",
    "read_float_tiff",
]

# Fixed-point precision (bits) of OpenCV's anti-aliased drawing coordinates.
_SHIFT = 4
_ONE = 1 << _SHIFT


def band_limit(img: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian blur of ``sigma_px`` pixels (reflecting borders); identity when 0."""
    if sigma_px <= 0:
        return img.astype(np.float32, copy=True)
    return cv2.GaussianBlur(img.astype(np.float32, copy=False), (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)


def smooth_noise(rng: np.random.Generator, shape: tuple[int, int], sigma_px: float) -> np.ndarray:
    """White Gaussian noise low-passed by a Gaussian of ``sigma_px``, rescaled to unit std.

    Large scales are generated on a coarser raster (noise at about 2 px sigma there) and
    upsampled with cubic interpolation, so the cost does not grow with the scale.
    """
    h, w = shape
    factor = max(1, int(sigma_px // 2))
    hs, ws = -(-h // factor) + 4, -(-w // factor) + 4
    n = rng.standard_normal((hs, ws), dtype=np.float32)
    n = cv2.GaussianBlur(n, (0, 0), max(sigma_px / factor, 0.3), borderType=cv2.BORDER_REFLECT)
    if factor > 1:
        # coarse pixel i covers fine pixels around (i - 2) * factor: upsample by remapping
        cols = (np.arange(w, dtype=np.float32) + 0.5) / factor - 0.5 + 2
        rows = (np.arange(h, dtype=np.float32) + 0.5) / factor - 0.5 + 2
        mx, my = np.meshgrid(cols, rows)
        n = cv2.remap(n, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    else:
        n = n[2 : 2 + h, 2 : 2 + w]
    sd = float(n.std())
    return (n - float(n.mean())) / (sd if sd > 0 else 1.0)


def normalize(img: np.ndarray, mean: float, std: float) -> np.ndarray:
    """Affine rescale to the given mean and standard deviation (grey levels)."""
    sd = float(img.std())
    return ((img - float(img.mean())) * (std / (sd if sd > 0 else 1.0)) + mean).astype(np.float32)


def soft_clip(img: np.ndarray, low: float, high: float) -> np.ndarray:
    """Smoothly compress values into ``(low, high)``: identity in the middle half, tanh at the ends."""
    mid, half = (low + high) / 2.0, (high - low) / 2.0
    knee = half / 2.0
    d = img - mid
    a = np.abs(d)
    over = a > knee
    out = d.copy()
    out[over] = np.sign(d[over]) * (knee + knee * np.tanh((a[over] - knee) / knee))
    return (out + mid).astype(np.float32)


def _uniform(rng: np.random.Generator, lo_hi) -> float:
    lo, hi = lo_hi
    return float(rng.uniform(lo, hi))


def _count(density_per_m2: float, area_m2: float) -> int:
    return int(round(density_per_m2 * area_m2))


def _draw_lines(canvas: np.ndarray, polylines: list[np.ndarray], width_px: int) -> None:
    """Anti-aliased polylines (pixel coordinates, float) onto a uint8 canvas (value 255)."""
    pts = [np.round(p * _ONE).astype(np.int32).reshape(-1, 1, 2) for p in polylines]
    if pts:
        cv2.polylines(canvas, pts, False, 255, max(1, int(width_px)), cv2.LINE_AA, _SHIFT)


def _soft_ellipse(shape, centre, axes, angle_deg, edge_px) -> np.ndarray:
    """A float32 mask in [0, 1]: a filled ellipse (pixel units) with a Gaussian-soft edge."""
    m = np.zeros(shape, np.uint8)
    c = (int(round(centre[0] * _ONE)), int(round(centre[1] * _ONE)))
    ax = (max(1, int(round(axes[0] * _ONE))), max(1, int(round(axes[1] * _ONE))))
    cv2.ellipse(m, c, ax, angle_deg, 0, 360, 255, -1, cv2.LINE_AA, _SHIFT)
    m = m.astype(np.float32) / 255.0
    if edge_px > 0.3:
        m = cv2.GaussianBlur(m, (0, 0), edge_px)
    return m


def _soft_polygon(shape, corners_px: np.ndarray, edge_px: float) -> np.ndarray:
    m = np.zeros(shape, np.uint8)
    cv2.fillPoly(m, [np.round(corners_px * _ONE).astype(np.int32)], 255, cv2.LINE_AA, _SHIFT)
    m = m.astype(np.float32) / 255.0
    if edge_px > 0.3:
        m = cv2.GaussianBlur(m, (0, 0), edge_px)
    return m


def _random_rect(rng, shape, size_px_range) -> np.ndarray:
    """Corners (4, 2) (col, row) of a random rotated rectangle inside the raster."""
    h, w = shape
    sx, sy = rng.uniform(*size_px_range, size=2)
    cx, cy = rng.uniform(0, w), rng.uniform(0, h)
    a = rng.uniform(0, np.pi)
    c, s = np.cos(a), np.sin(a)
    local = np.array([[-sx, -sy], [sx, -sy], [sx, sy], [-sx, sy]]) / 2.0
    return np.stack([cx + c * local[:, 0] - s * local[:, 1], cy + s * local[:, 0] + c * local[:, 1]], axis=1)


def procedural_texture(rng: np.random.Generator, grid: MapGrid, cfg: dict, area_m2: float) -> np.ndarray:
    """Procedural worn-concrete texture on ``grid`` (float32 grey levels).

    Layers (sizes in metres from ``cfg`` = ``[simulate.floor.texture]``): multi-scale grain,
    scratches, cracks, spots/stains, low-texture and one-directional patches; then
    normalisation to ``mean``/``std``, soft clipping and the final band limit.

    Args:
        rng: the texture's random stream.
        grid: raster geometry (pixel size in metres).
        cfg: the ``[simulate.floor.texture]`` table.
        area_m2: area (square metres) that feature counts are computed for (the raster's).
    """
    shape = grid.shape
    s = grid.pixel_size
    h, w = shape
    tex = np.zeros(shape, np.float32)
    for scale_m, weight in zip(cfg["grain_scales_m"], cfg["grain_weights"]):
        tex += np.float32(weight) * smooth_noise(rng, shape, scale_m / s)
    tex /= max(float(tex.std()), 1e-6)  # std units from here on

    def lines_layer(n, make, width_px, contrast, signed):
        pad = int(width_px) + 3
        for _ in range(n):
            poly = make()
            x0, y0 = np.floor(poly.min(axis=0)).astype(int) - pad
            x1, y1 = np.ceil(poly.max(axis=0)).astype(int) + pad + 1
            x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
            if x1 <= x0 or y1 <= y0:
                continue
            canvas = np.zeros((y1 - y0, x1 - x0), np.uint8)
            _draw_lines(canvas, [poly - np.array([x0, y0])], width_px)
            c = _uniform(rng, contrast)
            if not signed or rng.random() < 0.5:
                c = -c  # cracks are always dark
            tex[y0:y1, x0:x1] += np.float32(c / 255.0) * canvas.astype(np.float32)

    def scratch():
        length = _uniform(rng, cfg["scratch_length_m"]) / s
        p0 = rng.uniform([0, 0], [w, h])
        a = rng.uniform(0, np.pi)
        return np.array([p0, p0 + length * np.array([np.cos(a), np.sin(a)])])

    def crack():
        length = _uniform(rng, cfg["crack_length_m"]) / s
        step = cfg["crack_step_m"] / s
        n = max(2, int(length / step))
        a = rng.uniform(0, 2 * np.pi) + np.cumsum(rng.normal(0, cfg["crack_turn_rad"], n))
        p0 = rng.uniform([0, 0], [w, h])
        steps = step * np.stack([np.cos(a), np.sin(a)], axis=1)
        return np.vstack([p0, p0 + np.cumsum(steps, axis=0)])

    lines_layer(_count(cfg["scratch_density_per_m2"], area_m2), scratch, cfg["scratch_width_px"],
                cfg["scratch_contrast"], True)
    lines_layer(_count(cfg["crack_density_per_m2"], area_m2), crack, cfg["crack_width_px"],
                cfg["crack_contrast"], False)

    for _ in range(_count(cfg["spot_density_per_m2"], area_m2)):
        r = _uniform(rng, cfg["spot_radius_m"]) / s
        centre = rng.uniform([0, 0], [w, h])
        axes = (r, r * rng.uniform(0.4, 1.0))
        pad = int(r * 1.5 + 4)
        x0, y0 = max(0, int(centre[0]) - pad), max(0, int(centre[1]) - pad)
        x1, y1 = min(w, int(centre[0]) + pad + 1), min(h, int(centre[1]) + pad + 1)
        if x1 <= x0 or y1 <= y0:
            continue
        m = _soft_ellipse((y1 - y0, x1 - x0), (centre[0] - x0, centre[1] - y0), axes,
                          float(rng.uniform(0, 180)), max(0.5, r * 0.3))
        c = _uniform(rng, cfg["spot_contrast"]) * (1 if rng.random() < 0.5 else -1)
        tex[y0:y1, x0:x1] += np.float32(c) * m

    size_px = (cfg["patch_size_m"][0] / s, cfg["patch_size_m"][1] / s)
    edge_px = cfg["patch_edge_m"] / s
    n_low = max(cfg["min_patches"], _count(cfg["low_texture_density_per_m2"], area_m2))
    n_dir = max(cfg["min_patches"], _count(cfg["directional_density_per_m2"], area_m2))
    mean = float(tex.mean())

    def patch_crop():
        """A random rotated rectangle: crop slices and its soft mask on the crop."""
        corners = _random_rect(rng, shape, size_px)
        pad = int(np.ceil(3 * edge_px)) + 2
        x0, y0 = np.maximum(np.floor(corners.min(axis=0)).astype(int) - pad, 0)
        x1, y1 = np.minimum(np.ceil(corners.max(axis=0)).astype(int) + pad + 1, [w, h])
        if x1 <= x0 or y1 <= y0:
            return None, None
        sl = (slice(y0, y1), slice(x0, x1))
        return sl, _soft_polygon((y1 - y0, x1 - x0), corners - np.array([x0, y0]), edge_px)

    for _ in range(n_low):
        sl, m = patch_crop()
        if sl is None:
            continue
        crop = tex[sl]
        smooth = band_limit(crop, cfg["low_texture_sigma_m"] / s)
        low = mean + cfg["low_texture_amplitude"] * (smooth - float(smooth.mean())) / max(float(smooth.std()), 1e-6)
        tex[sl] = crop * (1 - m) + low * m
    for _ in range(n_dir):
        sl, m = patch_crop()
        a = rng.uniform(0, np.pi)
        if sl is None:
            continue
        ch, cw = m.shape
        length = 2 * (ch + cw) + 8
        prof = smooth_noise(rng, (1, length), cfg["directional_scale_m"] / s)[0]
        rows, cols = np.mgrid[0:ch, 0:cw].astype(np.float32)
        u = cols * np.float32(np.cos(a)) + rows * np.float32(np.sin(a)) + np.float32(cw + 4)
        stripes = np.interp(u.ravel(), np.arange(length, dtype=np.float32), prof).reshape(m.shape)
        tex[sl] = tex[sl] * (1 - m) + (mean + stripes.astype(np.float32)) * m

    return _finish(tex, cfg)


def _finish(tex: np.ndarray, cfg: dict) -> np.ndarray:
    """Normalise so the band-limited result has ``mean``/``std``, soft clip, band-limit."""
    sigma = cfg["band_limit_sigma_px"]
    blurred_std = float(band_limit(tex, sigma).std())
    tex = (tex - float(tex.mean())) * np.float32(cfg["std"] / max(blurred_std, 1e-6)) + np.float32(cfg["mean"])
    tex = soft_clip(tex, cfg["clip_low"], cfg["clip_high"])
    return band_limit(tex, sigma)


def photo_texture(path: str | Path, grid: MapGrid, cfg: dict) -> np.ndarray:
    """A photograph as world texture on ``grid`` (float32 grey levels).

    The photograph's physical width is ``cfg["photo_width_m"]`` (mirror-tiled to cover the
    raster), or with 0 it is scaled to just cover the raster. Downscaling is anti-aliased;
    the result is normalised and band-limited like the procedural texture.
    """
    grey = read_grey(path)  # BadInput naming the file when unreadable
    ph, pw = grey.shape
    h, w = grid.shape
    if cfg["photo_width_m"] > 0:
        photo_px = cfg["photo_width_m"] / pw  # metres per photo pixel
        zoom = photo_px / grid.pixel_size  # grid pixels per photo pixel
    else:
        zoom = max(w / pw, h / ph)
    if zoom < 1.0:
        grey = cv2.GaussianBlur(grey, (0, 0), 0.5 * np.sqrt(1.0 / zoom**2 - 1.0), borderType=cv2.BORDER_REFLECT)
    # grid pixel (c, r) <- photo pixel ((c + 0.5) / zoom - 0.5, ...), centred, mirrored
    cols = ((np.arange(w, dtype=np.float64) - (w - 1) / 2.0) / zoom + (pw - 1) / 2.0).astype(np.float32)
    rows = ((np.arange(h, dtype=np.float64) - (h - 1) / 2.0) / zoom + (ph - 1) / 2.0).astype(np.float32)
    mx, my = np.meshgrid(cols, rows)
    tex = cv2.remap(grey, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT_101)
    return _finish(tex, cfg)


def write_float_tiff(path: str | Path, img: np.ndarray) -> None:
    """Write a float32 single-channel TIFF (uncompressed, fixed DateTime: reproducible bytes)."""
    write_image(path, np.asarray(img, np.float32), {"compression": "none", "DateTime": "2000:01:01 00:00:00"})


def read_float_tiff(path: str | Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """Read a single-channel image as float32 ``(H, W)`` in its stored units.

    ``shape``: the raster the file must hold (a simulated world's grid): the caps checked
    before decoding are then its pixels and their float32 bytes (plus 1 MiB for the TIFF's
    header and tags), not the drive-log images' ``[ingest]`` caps, which a world of more
    than ~11 x 11 m at 2.5 mm exceeds; without it, the default caps."""
    limits = None
    if shape is not None:
        h, w = (int(v) for v in shape)
        limits = ImageLimits(max_pixels=h * w, max_bytes=4 * h * w + (1 << 20),
                             pixels_cap=f"its grid's {w} x {h} px", bytes_cap=f"its grid's {w} x {h} px hold as float32")
    try:
        return read_raw(path, limits=limits)
    except BadInput as e:
        raise BadInput(path, f"cannot read world texture: {e.what}") from None
