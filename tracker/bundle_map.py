"""A map bundle as the tracker sees it: level-0 tiles through a bounded cache, and the
relocalization index.

:func:`open_bundle` opens an exported bundle (:mod:`mapstore.bundle`, numpy + zarr only)
lazily: nothing but the zip directory and the zarr metadata is read until a fix asks for
pixels; tiles are then decoded once and kept in a least-recently-used cache of
``cache_tiles`` tiles (:class:`tracker.tiles.TileCache`; 256 tiles of 256 x 256 px = 16 MiB).
Tiles the bundle does not hold (outside its region or corridor) read as no data.

:meth:`TrackerMap.feature_index` loads the relocalization index the export stored
(``floor/reloc/features``: one chunk of ORB records per level-0 tile, made by
:func:`tracker.reloc.tile_features`), and builds the same index from the tiles, with a
warning, for a bundle exported without it (``--no-reloc-index``, or older bundles).

Trust: :func:`open_bundle` loads a bundle only when its signature (``manifest.sig``,
:mod:`mapstore.signing`) checks against one of the trusted public keys; every member is
then checked against the signed manifest when it is first read, so a damaged or forged
tile, index chunk or metadata is refused (a :class:`mapstore.bundle.BundleError` naming
it), never used. ``insecure=True`` (development only) also loads unsigned bundles. Reads
are bounded either way (:class:`mapstore.bundle.BundleLimits`).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterable

import numpy as np

from mapstore.bundle import DEFAULT_LIMITS, SIGNATURE, Bundle, BundleError, BundleLimits, zstd_codec
from mapstore.bundle import open_bundle as _open
from mapstore.signing import PublicKey
from mapstore.grid import MapGrid
from tracker.floor import FloorTracker, FloorTrackerParams
from tracker.reloc import (INDEX_FORMAT, INDEX_PATH, MARGIN_PX, RECORD_BYTES, FeatureIndex, Relocalizer, RelocParams,
                           build_index, decode_records)
from tracker.tiles import TileCache

__all__ = ["TrackerMap", "open_bundle", "RelocIndexMissing"]


class RelocIndexMissing(UserWarning):
    """The bundle holds no (usable) relocalization index: it is built from the tiles."""


@dataclass
class TrackerMap:
    """An open bundle for tracking: ``grid`` (level 0, world frame), ``tiles`` (level-0
    intensity, uint8, 0 = no data), ``bundle`` (everything else: manifest, layers)."""

    bundle: Bundle
    tiles: TileCache
    _index: FeatureIndex | None = field(default=None, init=False, repr=False)
    index_source: str | None = field(default=None, init=False)
    """``stored`` or ``built`` once :meth:`feature_index` ran."""

    @property
    def grid(self) -> MapGrid:
        return self.bundle.grid

    def floor_tracker(self, frame_pixel_size: float, params: FloorTrackerParams | None = None) -> FloorTracker:
        """A :class:`FloorTracker` over this map for frames of ``frame_pixel_size`` metres."""
        return FloorTracker(self.tiles, self.grid, frame_pixel_size, params)

    def stored_index(self) -> FeatureIndex | None:
        """The relocalization index stored in the bundle (world metres), or None when it
        holds none or one of an unknown format. Reads every index chunk once (about 2 kB
        per level-0 tile; 30 ms for the 1024 tiles of a 20 x 20 m map)."""
        if self.bundle.store.index.find(f"{INDEX_PATH}/zarr.json") is None:
            return None
        arr = self.bundle.root[INDEX_PATH]
        meta = dict(arr.attrs.get("mosaicmap_reloc", {}))
        if (meta.get("format") != INDEX_FORMAT or meta.get("tile_px") != self.bundle.tile_px
                or meta.get("margin_px") != MARGIN_PX or arr.ndim != 4 or arr.shape[3] != RECORD_BYTES):
            return None
        rc, rec = _read_tile_records(self.bundle, arr)
        present = rec[:, 0, 6] == 1  # features fill a tile's slots from the first
        return decode_records(rec[present], rc[present], self.bundle.tile_px, self.grid)

    def feature_index(self, params: RelocParams | None = None) -> FeatureIndex:
        """The relocalization index (kept after the first call): the stored one, else
        (with a :class:`RelocIndexMissing` warning) :func:`tracker.reloc.build_index` over
        the bundle's tiles with ``params`` (its ``tile_px`` replaced by the bundle's tile,
        so the result equals what an export stores). ``index_source`` says which."""
        if self._index is None:
            idx = self.stored_index()
            self.index_source = "stored"
            if idx is None:
                warnings.warn(f"{self.bundle.path}: no relocalization index stored (exported with "
                              "--no-reloc-index or before it existed): building it from the level-0 tiles "
                              "(seconds for a large map)", RelocIndexMissing, stacklevel=2)
                p = replace(params or RelocParams(), tile_px=self.bundle.tile_px)
                idx = build_index(self.tiles, self.grid, p)
                self.index_source = "built"
            self._index = idx
        return self._index

    def relocalizer(self, frame_pixel_size: float, params: RelocParams | None = None,
                    floor_params: FloorTrackerParams | None = None) -> Relocalizer:
        """A :class:`Relocalizer` over this map's index (:meth:`feature_index`) verified by
        a floor tracker for frames of ``frame_pixel_size`` metres."""
        return Relocalizer(self.feature_index(params), self.floor_tracker(frame_pixel_size, floor_params), params)

    def close(self) -> None:
        self.bundle.close()

    def __enter__(self) -> "TrackerMap":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _read_tile_records(bundle: Bundle, arr) -> tuple[np.ndarray, np.ndarray]:
    """``(tiles (n, 2) row/col, records (n, F, RECORD_BYTES))`` of the index chunks the
    bundle holds. Fast path: the chunks' zstd frames read straight from the zip and decoded
    with numcodecs (zarr's own codec), ~20 us a tile; zarr's array read costs ~0.1 ms per
    chunk (its per-chunk machinery), 0.13 s for the 1024 tiles of a 20 x 20 m map. Any
    other codec chain goes through zarr."""
    shape = arr.shape
    codecs = [type(c).__name__ for c in arr.metadata.codecs]
    if codecs == ["BytesCodec", "ZstdCodec"]:
        prefix = f"{INDEX_PATH}/c/"
        names = [n for n in bundle.store.index.entries() if n.startswith(prefix)]
        rc = np.array([[int(v) for v in n[len(prefix):].split("/")[:2]] for n in names], np.int64).reshape(-1, 2)
        order = np.lexsort((rc[:, 1], rc[:, 0]))
        rc = rc[order]
        zstd = zstd_codec()
        bundle.store.index.expect(names)  # (a signed bundle: their manifest entries in one pass)
        rec = np.empty((len(names), shape[2], shape[3]), np.uint8)
        for k, i in enumerate(order):
            data = bundle.store.read_checked(names[i])  # bounds (declared decoded size) and trust
            try:
                rec[k] = np.frombuffer(zstd.decode(data), np.uint8).reshape(shape[2:])
            except (RuntimeError, ValueError, TypeError) as e:
                raise BundleError(f"member {names[i]}", f"unreadable ({type(e).__name__}: {e})") from None
        return rc, rec
    full = arr[...]
    rc = np.argwhere(full.any(axis=(2, 3)))
    return rc, full[rc[:, 0], rc[:, 1]]


def open_bundle(path: str | Path, cache_tiles: int = 256, *, keys: Iterable[PublicKey] = (), insecure: bool = False,
                limits: BundleLimits = DEFAULT_LIMITS) -> TrackerMap:
    """Open the bundle at ``path`` for tracking (see the module docstring).

    ``keys``: the trusted public keys; the bundle's signature must check against one of
    them. ``insecure``: development only: without keys, or when the bundle is unsigned,
    open it unchecked (bounds still apply). Raises
    :class:`mapstore.bundle.BundleError` when it is not a bundle, is unsigned, forged or
    damaged (``part`` names the member), ValueError when it holds no level-0 intensity."""
    keys = tuple(keys)
    if not keys and not insecure:
        raise BundleError(SIGNATURE, "no trusted key configured: a vehicle loads only signed bundles "
                                     "(track --key KEY.pub or [tracker.bundle] trusted_keys; --insecure for "
                                     "development)")
    try:
        b = _open(path, keys=keys or None, limits=limits)
    except BundleError as e:
        if not (insecure and e.part == SIGNATURE and e.what.startswith("missing")):
            raise
        b = _open(path, limits=limits)
    if not b.signed:
        try:
            b.store.index.entries()  # unsigned: every member name checked at open
        except BundleError:
            b.close()
            raise
    if 0 not in b.levels:
        b.close()
        raise ValueError(f"{path}: the bundle holds no level-0 intensity (levels {list(b.levels)}); "
                         "export it with --levels including 0")

    def read(tr: int, tc: int):
        return b.read_tile(0, tr, tc) if b.has_tile(0, tr, tc) else None

    return TrackerMap(b, TileCache(read, b.grid.shape, b.tile_px, capacity=cache_tiles))
