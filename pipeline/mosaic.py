"""Render one output shard of a floor mosaic: pure numpy / OpenCV, no file I/O.

Rectified frames (float32 grey levels 0..255 of shape ``(H, W)`` with a bool valid mask, at
``frame_pixel_size`` metres per pixel, posed at their image centre; see ``mapstore.grid``)
are warped into the level-0 pixels of a :class:`~mapstore.grid.MapGrid` and blended with
feathered weights. Every coordinate convention (frame pixels, grid pixels, pyramid levels)
comes from ``mapstore.grid``; nothing here re-derives one.

Boxes
    A *box* is a level-0 grid pixel rectangle ``(r0, r1, c0, c1)``: rows ``r0 <= r < r1``,
    columns ``c0 <= c < c1`` (half-open, rows first). A shard's box is clipped to the grid.

Stored intensity
    uint8 where 0 means NO DATA (not covered); covered pixels hold 1..255.

Rendering one shard::

    acc, wacc = zeros(box shape, float32), zeros(box shape, float32)
    count = zeros(box shape, uint16)
    for each frame assigned to the shard (assign_to_shards over frame_boxes):
        accumulate_frame(acc, wacc, count, box, grid, image, weight, pose, ...)
    intensity = finish(acc, wacc)     # or composite_over(old, finish(acc, wacc), wacc)
    level 1, 2, ... = downsample2(...)
    coverage_layer(count, ...), texture_layer(intensity, ...), uniqueness_layer(intensity, ...)
"""

from __future__ import annotations

import math
import threading

import cv2
import numpy as np
from numpy.lib.stride_tricks import as_strided

from mapstore.grid import MapGrid, frame_pixels_to_world
from pipeline.quality import texture_score_map

__all__ = [
    "INTERPOLATIONS",
    "frame_boxes",
    "assign_to_shards",
    "shard_box",
    "feather_weight",
    "feather_from_distance",
    "edge_distance",
    "interpolation_margin_px",
    "accumulate_frame",
    "weight_ones_box",
    "finish",
    "composite_over",
    "downsample2",
    "coverage_layer",
    "texture_layer",
    "uniqueness_layer",
    "reduced_uniqueness_params",
    "uniqueness_cells",
    "release_scratch",
]

Box = tuple[int, int, int, int]

#: ``[render] interpolation`` names -> OpenCV interpolation flags.
INTERPOLATIONS: dict[str, int] = {
    "linear": cv2.INTER_LINEAR,
    "cubic": cv2.INTER_CUBIC,
    "lanczos4": cv2.INTER_LANCZOS4,
}

# Half-width (pixels) of each OpenCV interpolation kernel: the source pixels read for a
# point p lie within this Chebyshev distance of floor(p) or floor(p) + 1.
_KERNEL_HALF_WIDTH_PX = {cv2.INTER_NEAREST: 1, cv2.INTER_LINEAR: 1, cv2.INTER_CUBIC: 2, cv2.INTER_LANCZOS4: 4}

# Frame footprint extents (frame pixels beyond the outer pixel centres): the pixel edges, and
# the reach of a bilinearly warped weight with a zero border (nonzero up to 1 px outside).
_PIXEL_EDGE_PX = 0.5
_LINEAR_REACH_PX = 1.0

# Grey-level variance (grey levels^2) below which a template or window counts as flat.
_FLAT_VARIANCE = 1e-6

# Bytes of one batch of the uniqueness layer's Hankel copies: ~40 cells of a 17 px template
# over +-8 px (16-32 measured equally fast), ~270 of a 9 px template over +-4 px (faster
# than 32-110: fewer calls).
_UNIQUENESS_BATCH_BYTES = 3 << 19
# Image pixels per pass of the uniqueness layer (a band of whole cell rows: its integral
# images and transposed copy stay a few MB).
_UNIQUENESS_SLAB_PX = 1 << 19


# --- frames, boxes and shards ------------------------------------------------------------


def _frame_corners(frame_shape: tuple[int, int], extent_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Frame pixel (columns, rows) of the 4 corners of a frame of ``(H, W)``, ``extent_px``
    frame pixels outside its outer pixel centres."""
    h, w = frame_shape[:2]
    lo_c, hi_c = -extent_px, w - 1 + extent_px
    lo_r, hi_r = -extent_px, h - 1 + extent_px
    return np.array([lo_c, hi_c, hi_c, lo_c]), np.array([lo_r, lo_r, hi_r, hi_r])


def _bounding_box(cols: np.ndarray, rows: np.ndarray, pad_px: int) -> np.ndarray:
    """Half-open int64 ``(r0, r1, c0, c1)`` of the grid pixels whose centres lie within the
    bounding box of fractional grid (cols, rows) of shape ``(4, ...)``, grown by ``pad_px``."""
    r0 = np.floor(rows.min(axis=0)) - pad_px
    r1 = np.floor(rows.max(axis=0)) + 1 + pad_px
    c0 = np.floor(cols.min(axis=0)) - pad_px
    c1 = np.floor(cols.max(axis=0)) + 1 + pad_px
    return np.stack([r0, r1, c0, c1], axis=-1).astype(np.int64)


def frame_boxes(
    grid: MapGrid,
    poses: np.ndarray,
    frame_shape: tuple[int, int],
    frame_pixel_size: float | np.ndarray,
    pad_px: int = 2,
) -> np.ndarray:
    """Level-0 grid pixel boxes of frames' footprints (not clipped to the grid).

    Args:
        grid: the level-0 map grid.
        poses: (N, 3) frame poses ``x, y, theta`` (metres, radians, world frame).
        frame_shape: ``(H, W)`` of the rectified frames (pixels).
        frame_pixel_size: metres per rectified frame pixel, or (N,) per frame (similarity
            poses: the nominal pixel size x each frame's scale).
        pad_px: level-0 pixels added on every side (interpolation support, rounding).

    Returns:
        (N, 4) int64 half-open boxes ``(r0, r1, c0, c1)`` holding the grid pixel centres
        inside the frames' outer pixel edges (their 4 corners mapped as by
        :meth:`MapGrid.frame_to_grid_affine`), grown by ``pad_px``.
    """
    poses = np.asarray(poses, dtype=float).reshape(-1, 3)
    cols, rows = _frame_corners(frame_shape, _PIXEL_EDGE_PX)
    # (4, 1) corners against (N,) poses -> (4, N) world and grid coordinates.
    x, y = frame_pixels_to_world(poses.T, cols[:, None], rows[:, None], frame_shape, frame_pixel_size)
    gc, gr = grid.world_to_pixel(x, y)
    return _bounding_box(gc, gr, pad_px).reshape(-1, 4)


def assign_to_shards(
    boxes: np.ndarray, grid_shape: tuple[int, int], shard_px: int
) -> dict[tuple[int, int], np.ndarray]:
    """Frames touching each shard.

    Args:
        boxes: (N, 4) level-0 boxes ``(r0, r1, c0, c1)`` (e.g. from :func:`frame_boxes`).
        grid_shape: level-0 grid ``(rows, columns)``.
        shard_px: shard side in level-0 pixels; shard (i, j) holds rows
            ``i * shard_px ...`` and columns ``j * shard_px ...``.

    Returns:
        ``{(i, j): sorted int64 frame indices}`` for every shard touched by a box after
        clipping it to the grid, keys in row-major order. Boxes wholly outside touch none.
    """
    b = np.asarray(boxes, dtype=np.int64).reshape(-1, 4)
    h, w = grid_shape
    r0, r1 = np.clip(b[:, 0], 0, h), np.clip(b[:, 1], 0, h)
    c0, c1 = np.clip(b[:, 2], 0, w), np.clip(b[:, 3], 0, w)
    keep = np.nonzero((r1 > r0) & (c1 > c0))[0]
    i0, i1 = r0[keep] // shard_px, (r1[keep] - 1) // shard_px
    j0, j1 = c0[keep] // shard_px, (c1[keep] - 1) // shard_px
    ni, nj = i1 - i0 + 1, j1 - j0 + 1
    n = ni * nj  # shards per box
    frame = np.repeat(keep.astype(np.int64), n)
    k = np.arange(int(n.sum()), dtype=np.int64) - np.repeat(np.cumsum(n) - n, n)  # rank within box
    njr = np.repeat(nj, n)
    si = np.repeat(i0, n) + k // njr
    sj = np.repeat(j0, n) + k % njr
    order = np.lexsort((frame, sj, si))
    si, sj, frame = si[order], sj[order], frame[order]
    if not frame.size:
        return {}
    starts = np.flatnonzero(np.r_[True, (si[1:] != si[:-1]) | (sj[1:] != sj[:-1])])
    ends = np.r_[starts[1:], frame.size]
    return {(int(si[s]), int(sj[s])): frame[s:e] for s, e in zip(starts, ends)}


def shard_box(ij: tuple[int, int], grid_shape: tuple[int, int], shard_px: int) -> Box:
    """Level-0 box ``(r0, r1, c0, c1)`` of shard ``(i, j)``, clipped to the grid.

    Raises ValueError for a shard outside the grid.
    """
    i, j = ij
    h, w = grid_shape
    r0, c0 = i * shard_px, j * shard_px
    if i < 0 or j < 0 or r0 >= h or c0 >= w:
        raise ValueError(f"shard {ij} lies outside a {h} x {w} px grid of {shard_px} px shards")
    return r0, min(r0 + shard_px, h), c0, min(c0 + shard_px, w)


def _box_intersect(a: Box, b: Box) -> Box | None:
    """Intersection of two half-open boxes, or None when empty."""
    r0, r1 = max(a[0], b[0]), min(a[1], b[1])
    c0, c1 = max(a[2], b[2]), min(a[3], b[3])
    return (r0, r1, c0, c1) if r1 > r0 and c1 > c0 else None


# --- warping and blending ----------------------------------------------------------------


def interpolation_margin_px(interpolation: int) -> float:
    """Margin (frame pixels) for :func:`feather_weight` so that wherever a frame's warped
    weight is nonzero, the ``interpolation`` kernel reads valid frame pixels only.

    The image kernel reaches ``s`` pixels (Chebyshev) from a pixel with nonzero weight; a
    pixel whose Euclidean distance to the nearest invalid pixel exceeds ``s * sqrt(2)``
    has none within that reach.
    """
    s = _KERNEL_HALF_WIDTH_PX[interpolation & cv2.INTER_MAX]
    return float(math.ceil(s * math.sqrt(2.0)) - 1)


def edge_distance(valid: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
    """float32 of ``valid``'s shape: ``d - 1 - margin_px`` with ``d`` the Euclidean distance
    (frame pixels) from a pixel to the nearest invalid pixel, the image border counting as
    one (the outermost valid ring has d = 1). Positive where :func:`feather_weight` with the
    same margin is nonzero, at least ``feather_px`` where it is 1."""
    v = cv2.copyMakeBorder(np.asarray(valid).astype(np.uint8), 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)
    d = cv2.distanceTransform(v, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[1:-1, 1:-1]
    d -= 1.0 + margin_px
    return d


def feather_weight(valid: np.ndarray, feather_px: float, margin_px: float = 0.0) -> np.ndarray:
    """Blend weight of a frame's pixels, float32 in [0, 1] of ``valid``'s shape.

    With ``d`` the Euclidean distance (frame pixels) from a pixel to the nearest invalid
    pixel, the image border counting as one (the outermost valid ring has d = 1), the
    weight is 0 for ``d <= 1 + margin_px`` (so 0 outside ``valid`` and on the image border)
    and rises as the smoothstep of ``(d - 1 - margin_px) / feather_px`` (:func:`edge_distance`)
    to 1 at ``feather_px`` further in, so that seams between frames fade. ``margin_px`` keeps
    the interpolation kernel off invalid pixels (see :func:`interpolation_margin_px`).
    """
    return feather_from_distance(edge_distance(valid, margin_px), feather_px)


def feather_from_distance(edge_dist: np.ndarray, feather_px: float) -> np.ndarray:
    """:func:`feather_weight` from a frame's :func:`edge_distance` (frame pixels; left as it
    is), for a caller that needs both."""
    if feather_px <= 0:
        return (edge_dist > 0).astype(np.float32)
    t = np.clip(edge_dist * np.float32(1.0 / feather_px), 0.0, 1.0)
    return (t * t * (3.0 - 2.0 * t)).astype(np.float32, copy=False)


def weight_ones_box(weight: np.ndarray) -> Box | None:
    """A frame-pixel box ``(r0, r1, c0, c1)`` (half-open) where ``weight`` is exactly 1, as
    large as a few greedy steps find (the whole inside of a :func:`feather_weight` of a
    rectangular valid mask), or None when it holds no such pixel."""
    ones = np.asarray(weight) == 1.0
    rows, cols = np.flatnonzero(ones.any(axis=1)), np.flatnonzero(ones.any(axis=0))
    if not rows.size:
        return None
    r0, r1, c0, c1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
    while r0 < r1 and c0 < c1:
        sub = ones[r0:r1, c0:c1]
        if sub.all():
            return r0, r1, c0, c1
        # drop the outer row or column holding the most pixels below 1
        bad = [np.count_nonzero(~sub[0]), np.count_nonzero(~sub[-1]), np.count_nonzero(~sub[:, 0]),
               np.count_nonzero(~sub[:, -1])]
        side = int(np.argmax(bad))
        if side == 0:
            r0 += 1
        elif side == 1:
            r1 -= 1
        elif side == 2:
            c0 += 1
        else:
            c1 -= 1
    return None


def _inside_box(s2f: np.ndarray, ones: Box, size: tuple[int, int]) -> Box | None:
    """The largest centred box of output pixels ``(r0, r1, c0, c1)`` (of an output of ``size``
    = (columns, rows)) whose bilinear samples under the output -> frame affine ``s2f`` read
    only frame pixels of the box ``ones`` (with 1/16 px to spare for OpenCV's 1/32 px
    positions), or None."""
    fr0, fr1, fc0, fc1 = ones
    lo_u, hi_u = fc0 + 1.0 / 16, fc1 - 1 - 1.0 / 16  # sample positions whose 2 x 2 taps lie inside
    lo_v, hi_v = fr0 + 1.0 / 16, fr1 - 1 - 1.0 / 16
    if hi_u <= lo_u or hi_v <= lo_v:
        return None
    (l00, l01, t0), (l10, l11, t1) = s2f.tolist()  # (Python floats: a few of them, no arrays)
    # the frame box's centre in output pixels, and the half sizes (p, q) of the output box
    # whose corners reach both pairs of the frame box's sides: |L00| p + |L01| q = hu, ...
    det0 = l00 * l11 - l01 * l10
    a, b, c, d = abs(l00), abs(l01), abs(l10), abs(l11)
    det = a * d - b * c
    if abs(det0) < 1e-12 or abs(det) < 1e-9:
        return None
    ru, rv = 0.5 * (lo_u + hi_u) - t0, 0.5 * (lo_v + hi_v) - t1
    cx, cy = (l11 * ru - l01 * rv) / det0, (l00 * rv - l10 * ru) / det0
    hu, hv = 0.5 * (hi_u - lo_u), 0.5 * (hi_v - lo_v)
    p, q = (hu * d - hv * b) / det, (hv * a - hu * c) / det
    if p <= 0 or q <= 0:
        return None
    r0, r1 = max(int(math.ceil(cy - q)), 0), min(int(math.floor(cy + q)) + 1, size[1])
    c0, c1 = max(int(math.ceil(cx - p)), 0), min(int(math.floor(cx + p)) + 1, size[0])
    return (r0, r1, c0, c1) if r1 > r0 and c1 > c0 else None


def _warp_weight(weight: np.ndarray, s2f: np.ndarray, size: tuple[int, int], ones: Box | None) -> np.ndarray:
    """The frame's weight warped bilinearly (output -> frame affine ``s2f``, zero border) over
    an output of ``size`` (columns, rows). Where every sample reads the frame's box ``ones``
    of weights 1 (:func:`weight_ones_box`) the output is 1 without warping; only the band
    around it is warped (most of a frame is inside its feather)."""
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    weight = np.asarray(weight, np.float32)
    inside = None if ones is None else _inside_box(s2f, ones, size)
    if inside is None:
        return cv2.warpAffine(weight, s2f, size, flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    r0, r1, c0, c1 = inside
    w = np.empty((size[1], size[0]), np.float32)
    w[r0:r1, c0:c1] = 1.0
    for a0, a1, b0, b1 in ((0, r0, 0, size[0]), (r1, size[1], 0, size[0]), (r0, r1, 0, c0), (r0, r1, c1, size[0])):
        if a1 > a0 and b1 > b0:
            m = s2f.copy()
            m[:, 2] += s2f[:, :2] @ np.array([b0, a0], float)  # the band's pixel (0, 0) is output (b0, a0)
            band = w[a0:a1, b0:b1]
            out = cv2.warpAffine(weight, m, (b1 - b0, a1 - a0), dst=band, flags=flags,
                                 borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
            if out is not band and not np.shares_memory(out, band):  # OpenCV could not write through the view
                band[...] = out
    return w


def accumulate_frame(
    acc: np.ndarray,
    wacc: np.ndarray,
    count: np.ndarray,
    box: Box,
    grid: MapGrid,
    image: np.ndarray,
    weight: np.ndarray,
    pose: np.ndarray,
    frame_pixel_size: float,
    gain: float,
    interpolation: int,
    intensity_scale: float = 1.0,
    *,
    weight_ones: Box | None = None,
    region: tuple[Box, np.ndarray] | None = None,
) -> None:
    """Warp one frame into a box's accumulators, in place.

    Over the part of the box the frame's footprint covers, with ``w`` the frame's weight
    warped bilinearly and ``v`` its image warped with ``interpolation`` (both 0 outside
    the frame), in grey levels::

        acc += w * v * intensity_scale / gain,   wacc += w,   count += (w > 0)

    Only the frame's own bounding box (clipped to the box) is warped. The frame is scaled to
    grey levels / gain in float32 first (one pass over the frame; e.g. the frames store's
    uint16 fixed point with ``intensity_scale`` 1/256), so that the warped values are added
    with their weights in one pass (``cv2.accumulateProduct``).

    The image's border is constant 0, not replicated: OpenCV's warps run ~3x slower over
    pixels reaching a replicated border (measured on a frame turned by 0.3 rad), and with
    a weight from :func:`feather_weight` given :func:`interpolation_margin_px` the kernel
    never reaches the border (nor invalid pixels) where ``w > 0``.

    Args:
        acc, wacc: float32 accumulators of the box's shape (grey levels x weight, weight).
        count: uint16 number of frames with nonzero weight per pixel, box's shape.
        box: level-0 box ``(r0, r1, c0, c1)`` the accumulators cover.
        grid: the level-0 map grid.
        image: rectified frame ``(H, W)``: grey levels / ``intensity_scale`` (float32,
            uint16 or uint8; other types converted to float32).
        weight: the frame's blend weight ``(H, W)`` (:func:`feather_weight`).
        pose: frame pose ``x, y, theta`` (metres, radians, world frame).
        frame_pixel_size: metres per frame pixel.
        gain: the frame's gain (its grey levels are divided by it); > 0.
        interpolation: OpenCV flag for the image (:data:`INTERPOLATIONS`).
        intensity_scale: grey levels per unit of ``image``.
        weight_ones: a box of ``weight`` holding only 1 (:func:`weight_ones_box`): the
            output pixels sampling only it get weight 1 without a warp.
        region: ``(level-0 box, float32 of its shape)``: the frame is warped only over that
            box, its warped weight multiplied there by those factors (the seam composite's
            :func:`pipeline.seams.pixel_weights`); None = over its whole footprint, factor 1.
    """
    if not gain > 0:
        raise ValueError(f"frame gain must be > 0, got {gain}")
    r0, r1, c0, c1 = box
    if acc.shape != (r1 - r0, c1 - c0) or wacc.shape != acc.shape or count.shape != acc.shape:
        raise ValueError(f"accumulators {acc.shape}, {wacc.shape}, {count.shape} do not match box {box}")
    if weight.shape != image.shape:
        raise ValueError(f"weight {weight.shape} does not match image {image.shape}")
    f2g = grid.frame_to_grid_affine(pose, image.shape, frame_pixel_size)
    cols, rows = _frame_corners(image.shape, _LINEAR_REACH_PX)
    gc, gr = f2g @ np.stack([cols, rows, np.ones_like(cols)])
    sub = _box_intersect(tuple(int(v) for v in _bounding_box(gc, gr, 0)), box)
    if sub is not None and region is not None:
        sub = _box_intersect(sub, region[0])
    if sub is None:
        return
    sr0, sr1, sc0, sc1 = sub
    f2s = f2g.copy()
    f2s[:, 2] -= (sc0, sr0)  # frame -> sub-rectangle pixels
    s2f = cv2.invertAffineTransform(f2s)
    size = (sc1 - sc0, sr1 - sr0)
    w = _warp_weight(weight, s2f, size, weight_ones)
    if region is not None:
        q0, _, p0, _ = region[0]
        cv2.multiply(w, region[1][sr0 - q0 : sr1 - q0, sc0 - p0 : sc1 - p0], dst=w)
    # grey levels / gain as float32 (one pass over the frame, smaller than its box), warped,
    # then weighted and added in one pass
    k = float(intensity_scale) / gain
    image, s2f_image = _crop_to_reach(image, s2f, size, interpolation)
    if image.dtype == np.float32 and k == 1.0:
        src = image
    elif image.dtype in (np.uint8, np.uint16, np.float32):
        src = cv2.multiply(image, k, dtype=cv2.CV_32F)
    else:
        src = np.asarray(image, np.float32) * np.float32(k)
    v = cv2.warpAffine(src, s2f_image, size, flags=interpolation | cv2.WARP_INVERSE_MAP,
                       borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    rs, cs = slice(sr0 - r0, sr1 - r0), slice(sc0 - c0, sc1 - c0)
    dst = acc[rs, cs]
    if cv2.accumulateProduct(v, w, dst) is not dst:  # OpenCV could not write through the view
        dst += v * w
    _add_into(wacc[rs, cs], w)
    n = count[rs, cs]
    np.add(n, w > 0, out=n, casting="unsafe")


def _crop_to_reach(image: np.ndarray, s2f: np.ndarray, size: tuple[int, int],
                   interpolation: int) -> tuple[np.ndarray, np.ndarray]:
    """``(image, s2f)`` cut to the frame pixels an output of ``size`` (columns, rows) under
    the output -> frame affine ``s2f`` reads with ``interpolation``, with the affine moved
    to the cut (integer shifts: the same samples); the whole image when that is most of it.

    The seam composite warps a frame over a fraction of its footprint: converting only
    that part to float32 saves most of the conversion."""
    w, h = size
    u, v = s2f @ np.array([[0.0, w - 1, 0.0, w - 1], [0.0, 0.0, h - 1, h - 1], [1.0, 1.0, 1.0, 1.0]])
    reach = _KERNEL_HALF_WIDTH_PX[interpolation & cv2.INTER_MAX] + 1
    ih, iw = image.shape
    u0, u1 = max(int(math.floor(u.min())) - reach, 0), min(int(math.floor(u.max())) + reach + 2, iw)
    v0, v1 = max(int(math.floor(v.min())) - reach, 0), min(int(math.floor(v.max())) + reach + 2, ih)
    if u1 <= u0 or v1 <= v0 or (u1 - u0) * (v1 - v0) > 0.8 * iw * ih:
        return image, s2f
    moved = s2f.copy()
    moved[:, 2] -= (u0, v0)
    return image[v0:v1, u0:u1], moved


def _add_into(dst: np.ndarray, a: np.ndarray) -> None:
    """``dst += a`` for a float32 view ``dst`` (OpenCV's add, faster than numpy's here)."""
    if cv2.add(dst, a, dst=dst) is not dst:  # OpenCV could not write through the view
        np.add(dst, a, out=dst)


def finish(acc: np.ndarray, wacc: np.ndarray, *, out: np.ndarray | None = None, in_place: bool = False) -> np.ndarray:
    """uint8 intensity of accumulators: ``round(acc / wacc)`` (halves to even) clipped to
    1..255 where ``wacc > 0``, else 0 (no data).

    ``out``: a contiguous uint8 array of their shape to write into (else a new one);
    ``in_place``: ``acc`` (contiguous) may be overwritten (no block-sized temporary)."""
    # OpenCV: the quotient (0 where wacc == 0), raised to 1, then rounded half to even and
    # saturated at 255 by the conversion; uncovered pixels zeroed through a mask (255 where
    # wacc > 0), built in the quotient's buffer once the quotient is converted.
    q = cv2.divide(acc, wacc, dst=acc if in_place else None)
    cv2.max(q, 1.0, dst=q)
    out = cv2.convertScaleAbs(q, dst=out)
    mask = q.view(np.uint8).ravel()[: out.size].reshape(out.shape)
    cv2.compare(wacc, 0.0, cv2.CMP_GT, dst=mask)
    cv2.bitwise_and(out, mask, dst=out)
    return out


def composite_over(old: np.ndarray, new: np.ndarray, wacc: np.ndarray) -> np.ndarray:
    """New intensity over an existing map's (uint8, 0 = no data), for an incremental build.

    ``alpha = clip(wacc, 0, 1)`` with ``wacc`` the new frames' weight sum. The result is
    ``new`` where only it has data, ``old`` where ``new`` has none, and elsewhere
    ``round(alpha * new + (1 - alpha) * old)`` clipped to 1..255. uint8.
    """
    alpha = np.clip(wacc, 0.0, 1.0).astype(np.float32, copy=False)
    mixed = alpha * new.astype(np.float32) + (1.0 - alpha) * old.astype(np.float32)
    mixed = np.clip(np.rint(mixed, out=mixed), 1, 255).astype(np.uint8)
    return np.where(new == 0, old, np.where(old == 0, new, mixed)).astype(np.uint8, copy=False)


# --- pyramid and reduced-resolution layers -------------------------------------------------


def downsample2(img: np.ndarray) -> np.ndarray:
    """Next pyramid level of a uint8 no-data-0 image.

    Output pixel (r, c) is the mean of the covered (non-zero) pixels of the input block
    rows ``2r, 2r+1``, columns ``2c, 2c+1`` (as :meth:`MapGrid.coarsened` by 2; a partial
    block at the bottom / right edge counts the pixels it has), rounded half up, 1..255;
    0 where the block holds no covered pixel. Shape ``ceil(h / 2) x ceil(w / 2)``.
    """
    h, w = img.shape
    if h % 2 or w % 2:
        img = np.pad(img, ((0, h % 2), (0, w % 2)))
    size = (img.shape[1] // 2, img.shape[0] // 2)
    # OpenCV's 2x area average of uint8 is (sum + 2) >> 2: the rounded mean where the 4
    # pixels are covered, 0 where none is. Blocks with 1 to 3 no-data pixels (a coverage
    # edge: 64..191 in the 2x area average of the no-data mask at 255) are redone.
    out = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
    holes = cv2.resize(cv2.compare(img, 0, cv2.CMP_EQ), size, interpolation=cv2.INTER_AREA)
    edge = cv2.findNonZero(cv2.inRange(holes, 1, 254))
    if edge is not None:
        c, r = edge[:, 0, 0], edge[:, 0, 1]
        q = np.stack([img[2 * r, 2 * c], img[2 * r, 2 * c + 1], img[2 * r + 1, 2 * c], img[2 * r + 1, 2 * c + 1]])
        s = q.astype(np.int32).sum(axis=0)
        n = np.count_nonzero(q, axis=0)
        out[r, c] = (2 * s + n) // (2 * n)  # round(s / n), halves up
    return out


def _cells(a: np.ndarray, cell_px: int, fill) -> np.ndarray:
    """``a`` padded with ``fill`` to whole cells, viewed as ``(rows, cols, cell_px**2)``."""
    h, w = a.shape
    nr, nc = -(-h // cell_px), -(-w // cell_px)
    if (nr * cell_px, nc * cell_px) != (h, w):
        a = np.pad(a, ((0, nr * cell_px - h), (0, nc * cell_px - w)), constant_values=fill)
    return a.reshape(nr, cell_px, nc, cell_px).swapaxes(1, 2).reshape(nr, nc, cell_px * cell_px)


def _box_sums(integral: np.ndarray, side: int) -> np.ndarray:
    """Sums over every ``side`` x ``side`` window of an integral image's source, indexed
    by the window's top-left pixel."""
    return integral[side:, side:] - integral[:-side, side:] - integral[side:, :-side] + integral[:-side, :-side]


def coverage_layer(count: np.ndarray, cell_px: int) -> np.ndarray:
    """uint16 per cell of ``cell_px`` x ``cell_px`` level-0 pixels (partial edge cells
    included, shape ``ceil(h / cell_px) x ceil(w / cell_px)``): the most frames covering
    any pixel of the cell."""
    h, w = count.shape
    nr, nc = -(-h // cell_px), -(-w // cell_px)
    c = count if (nr * cell_px, nc * cell_px) == (h, w) else np.pad(count, ((0, nr * cell_px - h), (0, nc * cell_px - w)))
    # over each band of cell_px rows first (whole rows at a time), then along them
    return c.reshape(nr, cell_px, nc * cell_px).max(axis=1).reshape(nr, nc, cell_px).max(axis=2).astype(np.uint16)


def _interior(a: np.ndarray, halo_px: int) -> np.ndarray:
    return a[halo_px : a.shape[0] - halo_px, halo_px : a.shape[1] - halo_px] if halo_px else a


def texture_layer(
    intensity: np.ndarray, cell_px: int, window_px: int, sigma_px: float, *, halo_px: int = 0,
    sample_px: int = 1,
) -> np.ndarray:
    """Kelly's (2000) texture score per cell: float32, (grey levels / pixel)^2.

    The median, over a cell's covered pixels, of
    :func:`pipeline.quality.texture_score_map` (``window_px``, ``sigma_px``). No-data
    pixels are first filled with the mean of the covered pixels within ``window_px`` (the
    covered mean where there are none), so that coverage edges do not read as steps.
    NaN for cells without a covered pixel.

    ``sample_px > 1`` takes the median over the pixels of a lattice of that step inside
    each cell (rows and columns ``sample_px // 2 + k * sample_px`` from the cell's corner;
    a partial edge cell without a lattice row or column uses its last one): the score is
    a ``window_px`` box mean, smooth at that scale, so (cell_px / sample_px)^2 samples give
    nearly the same median as every pixel for a fraction of the sorting.

    Args:
        intensity: uint8, 0 = no data: the box, plus ``halo_px`` pixels of its
            surroundings on every side (context for the score; no cells there).
        cell_px: cell side (level-0 pixels); partial cells at the bottom / right included.
        sample_px: lattice step (pixels), a divisor of ``cell_px``; 1 = every pixel.
    """
    if sample_px < 1 or cell_px % sample_px:
        raise ValueError(f"sample_px must divide cell_px ({cell_px}), got {sample_px}")
    shape = intensity.shape
    # Block-sized temporaries from per-thread buffers (a fresh 2080 x 2080 float32 array
    # costs ~4000 page faults; a render calls this for every shard).
    f = _scratch("texture.f", shape, np.float32)
    work = tuple(_scratch(f"texture.{i}", shape, np.float32) for i in range(3))
    np.copyto(f, intensity)
    covered = cv2.compare(intensity, 0, cv2.CMP_GT, dst=_scratch("texture.covered", shape, np.uint8))
    if cv2.countNonZero(covered) < covered.size:
        k = (window_px, window_px)
        num = cv2.boxFilter(f, -1, k, dst=work[0], normalize=False)
        ones = np.bitwise_and(covered, 1, out=_scratch("texture.ones", shape, np.uint8))
        den = cv2.boxFilter(ones, cv2.CV_32F, k, dst=work[1], normalize=False)  # covered pixels per window
        fallback = cv2.mean(f, mask=covered)[0]  # 0 when nothing is covered
        local = cv2.divide(num, den, dst=num)
        local[den < 0.5] = fallback
        cv2.copyTo(local, cv2.bitwise_not(covered), f)  # the covered pixels as they are
    score = _interior(texture_score_map(f, window_px, sigma_px, work=work), halo_px)
    inside = _interior(covered, halo_px)  # 255 = covered
    if sample_px == 1:
        return _nanmedian_cells(np.where(inside, score, np.float32(np.nan)), cell_px)
    h, w = score.shape
    per = cell_px // sample_px  # lattice points per cell side
    # rows and columns sample_px // 2 + k sample_px (the last pixel's for partial cells)
    rows = np.minimum(np.arange(-(-h // cell_px) * per) * sample_px + sample_px // 2, h - 1)
    cols = np.minimum(np.arange(-(-w // cell_px) * per) * sample_px + sample_px // 2, w - 1)
    pick = (slice(sample_px // 2, None, sample_px),) * 2
    if score[pick].shape != (len(rows), len(cols)):  # a partial cell with no lattice row or column
        pick = np.ix_(rows, cols)
    lattice = score[pick]
    lattice = np.where(inside[pick], lattice, np.float32(np.nan))
    out = _nanmedian_cells(lattice, per)
    if not np.isnan(out).any():
        return out
    # Cells with covered pixels but none on the lattice (coverage edges): every pixel.
    ii = cv2.integral(inside.view(np.uint8))
    ri, ci = np.minimum(np.arange(out.shape[0] + 1) * cell_px, h), np.minimum(np.arange(out.shape[1] + 1) * cell_px, w)
    cells = ii[np.ix_(ri[1:], ci[1:])] - ii[np.ix_(ri[:-1], ci[1:])] - ii[np.ix_(ri[1:], ci[:-1])] + ii[np.ix_(ri[:-1], ci[:-1])]
    missed = np.isnan(out) & (cells > 0)
    for i, j in zip(*np.nonzero(missed)):
        sl = (slice(i * cell_px, (i + 1) * cell_px), slice(j * cell_px, (j + 1) * cell_px))
        out[i, j] = np.median(score[sl][inside[sl] > 0])
    return out


# Per thread (ident): name -> a byte buffer of :func:`_scratch`; :func:`release_scratch` drops them.
_SCRATCH: dict[int, dict[str, np.ndarray]] = {}


def _scratch(name: str, shape: tuple[int, ...], dtype) -> np.ndarray:
    """An uninitialised array of ``shape`` and ``dtype`` from this thread's buffer ``name``,
    grown when too small and reused by the next call (its pages faulted in once)."""
    dtype = np.dtype(dtype)
    n = int(np.prod(shape)) * dtype.itemsize
    bufs = _SCRATCH.setdefault(threading.get_ident(), {})
    buf = bufs.get(name)
    if buf is None or buf.size < n:
        buf = bufs[name] = np.empty(max(n, 1), np.uint8)
    return buf[:n].view(dtype).reshape(shape)


def release_scratch() -> None:
    """Drop every thread's :func:`_scratch` buffers (e.g. when a render is done)."""
    _SCRATCH.clear()


def _nanmedian_cells(a: np.ndarray, cell_px: int) -> np.ndarray:
    """Median of each cell's non-NaN values (NaN where none), float32."""
    c = _cells(a, cell_px, np.nan)
    k = c.shape[-1]
    if not np.isnan(c).any():  # every cell full: its two middle values
        v = np.partition(c, [(k - 1) // 2, k // 2], axis=-1)
        return (0.5 * (v[..., (k - 1) // 2] + v[..., k // 2])).astype(np.float32)
    v = np.sort(c, axis=-1)  # NaNs sort last
    n = np.count_nonzero(~np.isnan(v), axis=-1)[..., None]
    lo = np.take_along_axis(v, np.maximum(n - 1, 0) // 2, axis=-1)[..., 0]
    hi = np.take_along_axis(v, n // 2, axis=-1)[..., 0]  # NaN where n == 0
    return (0.5 * (lo + hi)).astype(np.float32)


def uniqueness_layer(
    intensity: np.ndarray,
    cell_px: int,
    template_px: int,
    search_radius_px: int,
    exclusion_px: int,
    *,
    halo_px: int = 0,
    where: np.ndarray | None = None,
) -> np.ndarray:
    """Kelly's (2000) uniqueness C1 - C2 per cell, float32.

    At each cell's centre pixel (``cell_px // 2`` into it) a ``template_px`` square
    template (from ``template_px // 2`` before the centre) is correlated with the image at
    every shift within ``+-search_radius_px`` (normalized cross-correlation, as
    ``cv2.matchTemplate`` TM_CCOEFF_NORMED; 0 against a flat window). C1 is the
    correlation at zero shift (1 up to rounding), C2 the highest at Chebyshev distance
    >= ``exclusion_px`` from it. NaN where the template or the searched window is not
    wholly covered (holds a 0 or leaves the array) or the template is flat.

    Vectorized over cells (a band of cell rows at a time): window statistics from integral images;
    the correlations' numerators for all shifts as one small matrix product per cell
    (batched) of the zero-mean template with a Hankel copy of its window. About 2x faster
    than ``cv2.matchTemplate`` cell by cell (measured on 2048 x 2048 px, 16 px cells).

    Args:
        intensity: uint8, 0 = no data: the box, plus ``halo_px`` pixels of its
            surroundings on every side (windows may reach into it; no cells there).
        cell_px: cell side (level-0 pixels); partial cells at the bottom / right included.
        where: bool per cell (the output's shape): only these cells are measured (the others
            NaN); a cell's value does not depend on which others are measured.
    """
    t, rad = int(template_px), int(search_radius_px)
    if not 0 < exclusion_px <= rad:
        raise ValueError(f"exclusion_px must be in 1..search_radius_px ({rad}), got {exclusion_px}")
    s, span, n_px = 2 * rad + 1, t + 2 * rad, t * t  # shifts per axis, window side, template pixels
    nr = max(0, -(-(intensity.shape[0] - 2 * halo_px) // cell_px))
    nc = max(0, -(-(intensity.shape[1] - 2 * halo_px) // cell_px))
    out = np.full((nr, nc), np.nan, np.float32)
    if not out.size:
        return out
    # Window top-left of cell (0, 0) in intensity pixels; pad with no-data so that every
    # window lies inside the array (windows reaching the padding are rejected).
    off = halo_px + cell_px // 2 - t // 2 - rad
    lo = max(0, -off)
    hi_r = max(0, off + (nr - 1) * cell_px + span - intensity.shape[0])
    hi_c = max(0, off + (nc - 1) * cell_px + span - intensity.shape[1])
    img = np.pad(intensity, ((lo, hi_r), (lo, hi_c))) if lo or hi_r or hi_c else intensity
    o = off + lo  # window top-left of cell (0, 0) in img: row and column
    if where is not None:
        # Some cells: their windows (each all a cell reads) gathered side by side into a
        # compact image, measured there as cells of one window each, and put back.
        if where.shape != out.shape:
            raise ValueError(f"where {where.shape} does not match the cells {out.shape}")
        st = img.strides
        tiles = as_strided(img[o:, o:], (nr, nc, span, span), (cell_px * st[0], cell_px * st[1], st[0], st[1]))
        picked = tiles[where]
        n = len(picked)
        if n:
            side = int(math.ceil(math.sqrt(n)))
            rows = -(-n // side)
            compact = np.zeros((rows * side, span, span), np.uint8)
            compact[:n] = picked
            compact = compact.reshape(rows, side, span, span).transpose(0, 2, 1, 3).reshape(rows * span, side * span)
            out[where] = uniqueness_layer(compact, span, t, rad, exclusion_px).ravel()[:n]
        return out

    # Windows are taken about mid-grey: the same correlations, less float32 rounding. A fixed
    # level (not the box's mean) keeps a cell's value independent of the rest of the box, so
    # re-rendering a shard leaves its unchanged cells bit-identical (small deltas).
    level = np.float32(128.0)
    dy, dx = np.divmod(np.arange(s * s), s)
    far = np.maximum(np.abs(dy - rad), np.abs(dx - rad)) >= exclusion_px
    flat = np.sqrt(_FLAT_VARIANCE * n_px)  # sqrt(n_px * variance) of a flat patch
    # Buffers reused across batches: Hankel copies of the windows and their products.
    batch = max(1, min(nr * nc, _UNIQUENESS_BATCH_BYTES // (4 * t * s * span)))
    x = np.empty((batch, t, s * span), np.float32)
    g = np.empty((batch, t, s, span), np.float32)
    rows_per_slab = max(1, _UNIQUENESS_SLAB_PX // (img.shape[1] * cell_px))
    for i0 in range(0, nr, rows_per_slab):
        m = min(rows_per_slab, nr - i0)  # cell rows in this slab
        y = o + i0 * cell_px  # window top row of its first cell row
        slab = img[y : y + (m - 1) * cell_px + span]
        # Cells whose window is wholly covered: no-data pixels per window from an integral image.
        zi = cv2.integral(cv2.compare(slab, 0, cv2.CMP_EQ, dst=_scratch("uniq.nodata", slab.shape, np.uint8)),
                          sdepth=cv2.CV_32S, sum=_scratch("uniq.zi", (slab.shape[0] + 1, slab.shape[1] + 1), np.int32))
        r_, c_ = np.arange(m) * cell_px, o + np.arange(nc) * cell_px
        todo = (zi[np.ix_(r_ + span, c_ + span)] - zi[np.ix_(r_, c_ + span)] - zi[np.ix_(r_ + span, c_)]
                + zi[np.ix_(r_, c_)]) == 0
        if not todo.any():
            continue
        # sqrt(n_px * variance) of the template-sized window at every top-left pixel (exact
        # sums and sums of squares of uint8 grey levels, float64), then its reciprocal, 0
        # where the window is flat (a correlation of 0 there).
        # (boxFilter's sums at anchor (0, 0) are indexed by the window's top-left pixel; the
        # rows and columns past the last whole window hold border values, never read.)
        b1 = cv2.boxFilter(slab, cv2.CV_64F, (t, t), dst=_scratch("uniq.b1", slab.shape, np.float64), anchor=(0, 0),
                           normalize=False)
        wn = cv2.sqrBoxFilter(slab, cv2.CV_64F, (t, t), dst=_scratch("uniq.wn", slab.shape, np.float64), anchor=(0, 0),
                              normalize=False)
        cv2.subtract(wn, cv2.multiply(b1, b1, dst=_scratch("uniq.b1sq", slab.shape, np.float64), scale=1.0 / n_px),
                     dst=wn)
        cv2.sqrt(cv2.max(wn, 0.0, dst=wn), dst=wn)
        rwn = _scratch("uniq.rwn", slab.shape, np.float32)
        np.copyto(rwn, wn, casting="same_kind")
        cv2.threshold(cv2.divide(1.0, rwn, dst=rwn), 1.0 / flat, 0.0, cv2.THRESH_TOZERO_INV, dst=rwn)
        # Per cell: the template's mean and norm (its window at zero shift), the window
        # norms' reciprocals indexed [cell row, cell, dy, dx].
        cen = (slice(rad, rad + m * cell_px, cell_px), slice(o + rad, o + rad + nc * cell_px, cell_px))
        tnorm = wn[cen][:m, :nc]
        rtn = np.where(tnorm > flat, 1.0 / np.maximum(tnorm, flat), 0.0).astype(np.float32)
        rs = rwn.strides
        rwnorm = as_strided(rwn[:, o:], (m, nc, s, s), (cell_px * rs[0], cell_px * rs[1], rs[1], rs[0]))
        ss = slab.strides
        tmpl = as_strided(slab[rad:, o + rad :], (m, nc, t, t), (cell_px * ss[0], cell_px * ss[1], ss[0], ss[1]))
        tz = np.subtract(tmpl, (b1[cen][:m, :nc] / n_px).astype(np.float32)[..., None, None], dtype=np.float32,
                         out=_scratch("uniq.tz", (m, nc, t, t), np.float32))
        # Numerators sum_p tz(p) * window(p + shift) in batches that stay in cache, from each
        # cell row's band transposed, minus the level (frt[row, column, r] = slab[row *
        # cell_px + r, column] - level): the Hankel copy x[l, dx, r] = window[r, dx + l] =
        # frt[row, dx + l, r] is, for each l, one contiguous run of frt; the product
        # g[k, dx, r] = sum_l tz[k, l] x[l, dx, r] one small matrix product per cell; and
        # num[dx, dy] = sum_k g[k, dx, k + dy].
        st = cv2.transpose(slab)
        frt = _scratch("uniq.frt", (m, st.shape[0], span), np.float32)
        np.copyto(frt, as_strided(st, (m, st.shape[0], span), (cell_px * st.strides[1], st.strides[0], st.strides[1])))
        frt -= level
        ts = frt.strides
        windows = as_strided(frt[:, o:], (m, nc, t, s * span), (ts[0], cell_px * ts[1], ts[1], ts[2]))
        tzf = tz.reshape(m * nc, t, t)
        # The cells to measure, flattened (row-major over the slab's m x nc cells), in
        # batches: each batch's windows copied into x, one batched matrix product, the
        # diagonal sums; then the normalization and the peaks of those cells only.
        cells = np.flatnonzero((todo & (tnorm > flat)).ravel())
        if not cells.size:
            continue
        num = _scratch("uniq.num", (cells.size, s, s), np.float32)
        if cells.size == m * nc:  # every cell: batches of whole cell rows, or of parts of one
            per = max(1, batch // nc)
            parts = ([(a, min(a + per, m), 0, nc) for a in range(0, m, per)] if nc <= batch else
                     [(a, a + 1, j, min(j + batch, nc)) for a in range(m) for j in range(0, nc, batch)])
        else:  # some cells: gathered, batch by batch
            parts = [(k, min(k + batch, cells.size)) for k in range(0, cells.size, batch)]
        k0 = 0
        for part in parts:
            if len(part) == 4:
                a0, a1, j0, j1 = part
                b = (a1 - a0) * (j1 - j0)
                np.copyto(x[:b].reshape(a1 - a0, j1 - j0, t, s * span), windows[a0:a1, j0:j1])
                tsel = tzf[a0 * nc + j0 : (a1 - 1) * nc + j1]
            else:
                sel = cells[part[0] : part[1]]
                b = sel.size
                a_, j_ = np.divmod(sel, nc)
                np.copyto(x[:b], windows[a_, j_])
                tsel = tzf[sel]
            np.matmul(tsel, x[:b], out=g[:b].reshape(b, t, s * span))
            nb = num[k0 : k0 + b]
            np.copyto(nb, g[:b, 0, :, :s])
            for k in range(1, t):
                nb += g[:b, k, :, k : k + s]
            k0 += b
        a_, j_ = np.divmod(cells, nc)
        ncc = np.multiply(num, rwnorm[a_, j_], out=num)
        ncc *= rtn.ravel()[cells][:, None, None]
        ncc = ncc.reshape(cells.size, s * s)
        np.clip(ncc, -1.0, 1.0, out=ncc)
        out[i0 : i0 + m].reshape(-1)[cells] = ncc[:, rad * s + rad] - ncc[:, far].max(axis=-1)
    return out



def reduced_uniqueness_params(template_px: int, search_radius_px: int, exclusion_px: int) -> tuple[int, int, int]:
    """The uniqueness search on the 2x-reduced mosaic for one of level-0 pixels (as the
    tracker's coarse search reduces it): a template of ``2 ((template_px // 2 + 1) // 2) + 1``
    reduced pixels (9 for 17), the search radius and the exclusion halved, rounded up
    (+-4 and 2 for +-8 and 3)."""
    return 2 * ((template_px // 2 + 1) // 2) + 1, -(-search_radius_px // 2), -(-exclusion_px // 2)


def uniqueness_cells(
    intensity: np.ndarray,
    cell_px: int,
    template_px: int,
    search_radius_px: int,
    exclusion_px: int,
    *,
    level: int = 0,
    halo_px: int = 0,
    reduced: np.ndarray | None = None,
    recheck: tuple[float, float] | tuple[()] = (),
) -> np.ndarray:
    """The map's uniqueness layer per level-0 cell (``[render] uniqueness_level``).

    ``level`` 0: :func:`uniqueness_layer` of the level-0 ``intensity`` (a box plus
    ``halo_px`` pixels around it). ``level`` 1: the same measure on the 2x-reduced mosaic,
    ``reduced`` (:func:`downsample2` of ``intensity``, computed when not given; the box's
    top-left level-0 pixel must lie at an even row and column of the grid, so that these
    are the map's level-1 pixels), with the level-0 cell, template, radius and exclusion
    reduced by :func:`reduced_uniqueness_params`: a cell of ``cell_px`` level-0 pixels is
    ``cell_px / 2`` reduced ones, its centre the reduced pixel ``cell_px // 4`` into it
    (level-0 pixels ``cell_px // 2`` and the next). About 10x fewer multiply-adds per
    cell; the same cells and shape as level 0. ``cell_px`` and ``halo_px`` must be even.
    ``recheck`` ``(lo, hi)``: on level 1, the cells whose value lies in ``[lo, hi)`` are
    measured again on level 0 and take that value (where level 0 has one): near Kelly's
    0.2 the two levels can disagree on the side (level 1 reads ~0.05-0.09 higher, by up to
    0.3), elsewhere they do not; ``()`` = no recheck.
    """
    if level == 0:
        return uniqueness_layer(intensity, cell_px, template_px, search_radius_px, exclusion_px, halo_px=halo_px)
    if level != 1:
        raise ValueError(f"uniqueness level must be 0 or 1, got {level}")
    if cell_px % 2 or halo_px % 2:
        raise ValueError(f"uniqueness on level 1 needs an even cell and halo (level-0 px), got {cell_px} and {halo_px}")
    if reduced is None:
        reduced = downsample2(intensity)
    t1, r1, e1 = reduced_uniqueness_params(template_px, search_radius_px, exclusion_px)
    u = uniqueness_layer(reduced, cell_px // 2, t1, r1, e1, halo_px=halo_px // 2)
    if recheck:
        lo, hi = recheck
        near = (u >= lo) & (u < hi)  # (False where NaN)
        if near.any():
            u0 = uniqueness_layer(intensity, cell_px, template_px, search_radius_px, exclusion_px, halo_px=halo_px,
                                  where=near)
            np.copyto(u, u0, where=near & ~np.isnan(u0))
    return u
