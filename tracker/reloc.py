"""Global relocalization: where on the map is this frame, with no prior (or a wrong one)?

Feature voting, as in ground-texture localization work: an *index* of ORB features (world
position, binary descriptor) over the map, built once (at export time); a live frame's ORB
features are matched against it (Hamming distance, ratio test), a RANSAC rigid fit over the
matches proposes a pose, and the floor tracker (:class:`tracker.floor.FloorTracker`)
verifies it by template correlation before it is called ``ok``. A proposal that does not
verify is never returned as a fix.

Why features rather than Gaspar et al.'s (2000) eigenspace of patches: the vehicle's heading is
arbitrary at start-up, and an eigenspace of floor patches is not rotation invariant (one
would need every heading in the index, or rotation-invariant spectra that discard the
phase a floor texture is recognised by); ORB keypoints carry their own orientation, so one
index serves every heading, and the fit gives the full pose (x, y, theta), not only a
place. Measured in ``bench/bench_tracker.py``.

The index is built at export time and stored in the bundle (``floor/reloc/features``, one
chunk of feature records per level-0 tile; :mod:`mapstore.bundle`), so a vehicle starting
without a prior loads it (30 ms on a 20 x 20 m map) instead of detecting features over the
whole map (4.4 s); :meth:`tracker.bundle_map.TrackerMap.feature_index` loads it, or builds
it with :func:`build_index` from the tiles for a bundle exported without it.

Why the feature definition (:func:`tile_features`) lives here and is *injected* into the
export (``pipeline/cli/export.py`` wraps it in a :class:`mapstore.export.TileDerived`)
rather than living in mapstore: the records must be exactly what this module's query side
expects (same ORB settings, same fixed-point encoding), so the map side and the live side
are defined in one file; mapstore stays free of the tracker's feature choice (its export
knows only "a deterministic function of a tile and 32 px of context") and the dependency
runs one way: pipeline -> tracker and mapstore; tracker -> mapstore.grid/bundle only.

Units: frame pixels, world metres and radians (:mod:`mapstore.grid` conventions).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from mapstore.grid import MapGrid, frame_pixels_to_vehicle
from mapstore.knobs import knob
from tracker.floor import LOST, Fix, FloorTracker
from tracker.params import params_from_dict
from tracker.tiles import TileCache

__all__ = ["RelocParams", "FeatureIndex", "INDEX_PATH", "INDEX_FORMAT", "MARGIN_PX", "RECORD_BYTES", "tile_features",
           "decode_records", "index_attributes", "build_index", "Relocalizer"]


@dataclass(frozen=True)
class RelocParams:
    """Relocalization settings (``[tracker.reloc]`` in ``configs/tracker.toml``)."""

    features_per_tile: int = knob(ge=1, default=48)
    tile_px: int = knob(ge=1, default=256)
    fast_threshold: int = knob(ge=1, le=255, default=12)
    query_features: int = knob(ge=1, default=400)
    ratio: float = knob(gt=0.0, le=1.0, default=0.85)
    ransac_m: float = knob(gt=0.0, default=0.004)
    min_inliers: int = knob(ge=2, default=10)
    max_scale_error: float = knob(ge=0.0, default=0.03)
    candidates: int = knob(ge=1, default=3)
    verify_sigma_m: float = knob(gt=0.0, default=0.005)
    verify_sigma_rad: float = knob(gt=0.0, default=0.01)

    @classmethod
    def from_dict(cls, d: dict) -> "RelocParams":
        return params_from_dict(cls, d, "tracker.reloc")


@dataclass
class FeatureIndex:
    """ORB features of a map: ``xy`` (N, 2) float64 world metres, ``descriptors`` (N, 32)
    uint8, ``angle`` (N,) float32 keypoint orientation (degrees, map image frame)."""

    xy: np.ndarray
    descriptors: np.ndarray
    angle: np.ndarray
    _cells: tuple | None = field(default=None, init=False, repr=False, compare=False)

    def __len__(self) -> int:
        return len(self.xy)

    def near(self, x: float, y: float, radius_m: float) -> np.ndarray:
        """Indices (ascending) of the features within ``radius_m`` of world point (x, y)
        (metres). The features are bucketed once into square cells of ``NEAR_CELL_M``; a
        query reads the cells its square touches, then keeps the disc."""
        if self._cells is None:
            origin = self.xy.min(axis=0) if len(self.xy) else np.zeros(2)
            ij = np.floor((self.xy - origin) / NEAR_CELL_M).astype(np.int64)
            ncol = int(ij[:, 0].max()) + 1 if len(ij) else 1
            key = ij[:, 1] * ncol + ij[:, 0]
            order = np.argsort(key, kind="stable")
            nrow = int(ij[:, 1].max()) + 1 if len(ij) else 0
            self._cells = (origin, ncol, nrow, key[order], order)
        origin, ncol, nrow, keys, order = self._cells
        (i0, j0), (i1, j1) = np.floor((np.array([[x - radius_m, y - radius_m], [x + radius_m, y + radius_m]])
                                       - origin) / NEAR_CELL_M).astype(np.int64)
        i0, i1, j0, j1 = max(i0, 0), min(i1, ncol - 1), max(j0, 0), min(j1, nrow - 1)
        if i0 > i1 or j0 > j1:
            return np.zeros(0, np.int64)
        rows = np.arange(j0, j1 + 1) * ncol
        lo, hi = np.searchsorted(keys, rows + i0, "left"), np.searchsorted(keys, rows + i1, "right")
        cand = np.sort(np.concatenate([order[a:b] for a, b in zip(lo.tolist(), hi.tolist())]))
        d = self.xy[cand] - (x, y)
        return cand[np.einsum("ij,ij->i", d, d) <= radius_m * radius_m]


NEAR_CELL_M = 1.0
"""Side (metres) of the cells :meth:`FeatureIndex.near` buckets the features into."""


def _orb(n: int, fast_threshold: int) -> cv2.ORB:
    # one pyramid level: the camera height is fixed, so is the scale
    return cv2.ORB_create(nfeatures=n, scaleFactor=1.2, nlevels=1, edgeThreshold=31, patchSize=31,
                          fastThreshold=fast_threshold)


# --- the per-tile feature records (stored in bundles, built on the vehicle) --------------------

INDEX_PATH = "floor/reloc/features"
"""Zarr path of the stored index in a bundle (see :mod:`mapstore.bundle`)."""
INDEX_FORMAT = "mosaicmap-orb-records-v1"
MARGIN_PX = 32
"""Context (level-0 pixels) read around a tile: ORB drops keypoints within ``edgeThreshold``
(31 px) of its image's border, so with 32 px every keypoint of the tile's interior survives,
and a keypoint depends only on pixels of the tile and its 8 neighbours."""
RECORD_BYTES = 40
XY_SCALE = 64
"""Fixed point of a record's position: 1/64 px (exact for ORB's integer positions)."""
ANGLE_SCALE = 65536.0 / 360.0
"""Fixed point of a record's angle: 360/65536 degree."""


def tile_features(window: np.ndarray, params: RelocParams) -> np.ndarray:
    """The ORB feature records of one map tile: THE feature definition of the index, used
    by the export (``mosaicmap export``, through :class:`mapstore.export.TileDerived`) and
    by :func:`build_index` on the vehicle, so a stored and a built index are identical.

    Args:
        window: uint8 level-0 pixels (0 = no data) of the tile plus :data:`MARGIN_PX` of
            context on every side: ``(t + 2 m, t + 2 m)`` for a tile of side ``t`` pixels
            (an edge tile's missing pixels and everything outside the map or the export's
            selection are 0).
        params: ``features_per_tile`` (the record capacity) and ``fast_threshold``.

    Returns:
        ``(features_per_tile, RECORD_BYTES)`` uint8 records, the features first (ordered by
        row, then column), unused slots all zero. A record: bytes 0-1 column and 2-3 row of
        the keypoint inside the tile (uint16 little endian, 1/:data:`XY_SCALE` px, from the
        centre of the tile's pixel (0, 0)); 4-5 the keypoint's orientation (uint16, degrees
        x :data:`ANGLE_SCALE`, map image frame); 6 flags (1 = a feature); 7 zero; 8-39 the
        32-byte ORB descriptor. Only keypoints whose 33 x 33 neighbourhood is wholly covered
        are kept (no descriptor reads a no-data pixel).
    """
    m = MARGIN_PX
    t = window.shape[0] - 2 * m
    if t <= 0 or window.shape[1] != window.shape[0]:
        raise ValueError(f"window {window.shape} is not a square tile with {m} px of context")
    out = np.zeros((params.features_per_tile, RECORD_BYTES), np.uint8)
    if not window[m:m + t, m:m + t].any():
        return out
    win = np.ascontiguousarray(window, dtype=np.uint8)
    covered = (win > 0).astype(np.uint8)
    mask = cv2.erode(covered, np.ones((33, 33), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    mask[:m] = 0
    mask[m + t:] = 0
    mask[:, :m] = 0
    mask[:, m + t:] = 0
    if not mask.any():
        return out
    kps, d = _orb(params.features_per_tile, params.fast_threshold).detectAndCompute(win, mask)
    if d is None or not kps:
        return out
    pts = np.array([k.pt for k in kps], float) - m
    q = np.rint(pts * XY_SCALE).astype(np.int64)
    ang = np.rint(np.array([k.angle for k in kps], float) * ANGLE_SCALE).astype(np.int64) % 65536
    order = np.lexsort((q[:, 0], q[:, 1]))[: params.features_per_tile]
    n = len(order)
    fields = np.zeros((n, 3), "<u2")
    fields[:, 0], fields[:, 1], fields[:, 2] = q[order, 0], q[order, 1], ang[order]
    out[:n, 0:6] = fields.view(np.uint8).reshape(n, 6)
    out[:n, 6] = 1
    out[:n, 8:] = d[order]
    return out


def decode_records(records: np.ndarray, tiles_rc: np.ndarray, tile_px: int, grid: MapGrid) -> FeatureIndex:
    """The :class:`FeatureIndex` of stored records.

    Args:
        records: ``(n, F, RECORD_BYTES)`` uint8, tile after tile (:func:`tile_features`).
        tiles_rc: ``(n, 2)`` the tiles' (row, column) indices on ``grid``'s level 0.
        tile_px: the tiles' side (level-0 pixels).
        grid: the level-0 grid (world frame).
    """
    rec = np.ascontiguousarray(records, np.uint8).reshape(-1, records.shape[-2], RECORD_BYTES)
    present = rec[:, :, 6] == 1
    tile_of = np.repeat(np.asarray(tiles_rc, np.int64).reshape(-1, 2), rec.shape[1], axis=0)[present.ravel()]
    r = rec[present]
    if len(r) == 0:
        return FeatureIndex(np.zeros((0, 2)), np.zeros((0, 32), np.uint8), np.zeros(0, np.float32))
    f = np.ascontiguousarray(r[:, 0:6]).view("<u2").astype(np.float64)
    cols = tile_of[:, 1] * tile_px + f[:, 0] / XY_SCALE
    rows = tile_of[:, 0] * tile_px + f[:, 1] / XY_SCALE
    x, y = grid.pixel_to_world(cols, rows)
    return FeatureIndex(np.column_stack([x, y]), np.ascontiguousarray(r[:, 8:]),
                        (f[:, 2] / ANGLE_SCALE).astype(np.float32))


def index_attributes(params: RelocParams, tile_px: int) -> dict:
    """What a stored index records about how it was made (the zarr array's attributes
    ``mosaicmap_reloc``; JSON)."""
    return {"format": INDEX_FORMAT, "tile_px": int(tile_px), "margin_px": MARGIN_PX,
            "features_per_tile": int(params.features_per_tile), "fast_threshold": int(params.fast_threshold),
            "record_bytes": RECORD_BYTES, "xy_scale": XY_SCALE, "angle_scale": "65536/360",
            "detector": "cv2.ORB nlevels=1 edgeThreshold=31 patchSize=31", "opencv": cv2.__version__}


def build_index(tiles: TileCache, grid: MapGrid, params: RelocParams | None = None) -> FeatureIndex:
    """ORB features over every ``params.tile_px`` tile of the map raster (level 0 of
    ``grid``), each tile read with :data:`MARGIN_PX` pixels of context so features near
    tile edges are found once, by the tile holding them (:func:`tile_features`, the same
    records an export stores: with ``tile_px`` = the bundle's tile the two indexes are
    identical). Tiles with no data are skipped; a feature is kept only where the
    descriptor's 31-pixel patch is wholly covered."""
    p = params or RelocParams()
    m, t = MARGIN_PX, p.tile_px
    h, w = grid.shape
    recs, rc = [], []
    for tr in range(-(-h // t)):
        for tc in range(-(-w // t)):
            r0, c0 = tr * t, tc * t
            win = tiles.window(r0 - m, r0 + t + m, c0 - m, c0 + t + m)
            rec = tile_features(win, p)
            if rec[0, 6]:
                recs.append(rec)
                rc.append((tr, tc))
    if not recs:
        return FeatureIndex(np.zeros((0, 2)), np.zeros((0, 32), np.uint8), np.zeros(0, np.float32))
    return decode_records(np.stack(recs), np.array(rc), t, grid)


class Relocalizer:
    """Pose proposals from a :class:`FeatureIndex`, verified by a :class:`FloorTracker`."""

    def __init__(self, index: FeatureIndex, tracker: FloorTracker, params: RelocParams | None = None):
        self.index = index
        self.tracker = tracker
        self.p = params or RelocParams()
        self._orb = _orb(self.p.query_features, self.p.fast_threshold)
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        self.last_seconds = 0.0

    def proposals(self, frame: np.ndarray, valid: np.ndarray | None = None,
                  near: tuple[float, float, float] | None = None) -> list[tuple[np.ndarray, int]]:
        """Up to ``candidates`` poses (x, y, theta) with their RANSAC inlier counts, best
        first. ``near`` (x, y, radius; world metres): match only the index's features
        within the radius of (x, y) (:meth:`FeatureIndex.near`: a search around a
        dead-reckoned pose, a fraction of the cost of the whole index, and fewer look-alikes
        from elsewhere on the floor); None: the whole index."""
        p = self.p
        sel = None if near is None else self.index.near(*near)
        if (len(self.index) if sel is None else len(sel)) < p.min_inliers:
            return []
        mask = None if valid is None else cv2.erode(valid.astype(np.uint8), np.ones((33, 33), np.uint8))
        kps, d = self._orb.detectAndCompute(frame, mask)
        if d is None or len(kps) < p.min_inliers:
            return []
        train = self.index.descriptors if sel is None else self.index.descriptors[sel]
        pairs = self._matcher.knnMatch(d, train, k=2)
        good = [m[0] for m in pairs if len(m) == 2 and m[0].distance < p.ratio * m[1].distance]
        if len(good) < p.min_inliers:
            return []
        q = np.array([kps[m.queryIdx].pt for m in good], float)
        vx, vy = frame_pixels_to_vehicle(q[:, 0], q[:, 1], frame.shape, self.tracker.frame_pixel_size)
        src = np.column_stack([vx, vy])
        ti = np.array([m.trainIdx for m in good], np.int64)
        dst = self.index.xy[ti if sel is None else sel[ti]]
        out: list[tuple[np.ndarray, int]] = []
        remaining = np.ones(len(good), bool)
        for _ in range(p.candidates):
            if remaining.sum() < p.min_inliers:
                break
            # RANSAC in metres, around a local origin (float32 inside OpenCV)
            o = dst[remaining].mean(axis=0)
            m, inl = cv2.estimateAffinePartial2D(src[remaining].astype(np.float32),
                                                 (dst[remaining] - o).astype(np.float32),
                                                 method=cv2.RANSAC, ransacReprojThreshold=p.ransac_m,
                                                 maxIters=2000, confidence=0.999)
            if m is None:
                break
            inl = inl.ravel().astype(bool)
            scale = float(np.hypot(m[0, 0], m[1, 0]))
            n_in = int(inl.sum())
            if n_in < p.min_inliers:
                break
            idx = np.flatnonzero(remaining)
            if abs(scale - 1.0) <= p.max_scale_error:
                out.append((np.array([m[0, 2] + o[0], m[1, 2] + o[1], float(np.arctan2(m[1, 0], m[0, 0]))]), n_in))
            remaining[idx[inl]] = False
        return out

    def locate(self, frame: np.ndarray, valid: np.ndarray | None = None,
               near: tuple[float, float, float] | None = None) -> Fix:
        """A verified fix with no prior: the first proposal the tracker confirms (``ok``),
        else a ``lost`` fix (pose NaN). ``near``: see :meth:`proposals`. ``last_seconds``
        holds the time it took."""
        t0 = time.perf_counter()
        sigma = np.array([self.p.verify_sigma_m, self.p.verify_sigma_m, self.p.verify_sigma_rad])
        tried = 0
        try:
            for pose, n_in in self.proposals(frame, valid, near):
                tried += 1
                fix = self.tracker.fix(frame, pose, sigma, valid)
                if fix.ok:
                    fix.reasons["reloc_inliers"] = n_in
                    return fix
            return Fix(np.full(3, np.nan), np.full((3, 3), np.nan), LOST, reasons={"reloc_proposals": tried})
        finally:
            self.last_seconds = time.perf_counter() - t0
