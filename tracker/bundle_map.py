"""A map bundle as the tracker sees it: level-0 tiles through a bounded cache.

:func:`open_bundle` opens an exported bundle (:mod:`mapstore.bundle`, numpy + zarr only)
lazily: nothing but the zip directory and the zarr metadata is read until a fix asks for
pixels; tiles are then decoded once and kept in a least-recently-used cache of
``cache_tiles`` tiles (:class:`tracker.tiles.TileCache`; 256 tiles of 256 x 256 px = 16 MiB).
Tiles the bundle does not hold (outside its region or corridor) read as no data.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from mapstore.bundle import Bundle
from mapstore.bundle import open_bundle as _open
from mapstore.grid import MapGrid
from tracker.floor import FloorTracker, FloorTrackerParams
from tracker.tiles import TileCache

__all__ = ["TrackerMap", "open_bundle"]


@dataclass
class TrackerMap:
    """An open bundle for tracking: ``grid`` (level 0, world frame), ``tiles`` (level-0
    intensity, uint8, 0 = no data), ``bundle`` (everything else: manifest, layers)."""

    bundle: Bundle
    tiles: TileCache

    @property
    def grid(self) -> MapGrid:
        return self.bundle.grid

    def floor_tracker(self, frame_pixel_size: float, params: FloorTrackerParams | None = None) -> FloorTracker:
        """A :class:`FloorTracker` over this map for frames of ``frame_pixel_size`` metres."""
        return FloorTracker(self.tiles, self.grid, frame_pixel_size, params)

    def close(self) -> None:
        self.bundle.close()

    def __enter__(self) -> "TrackerMap":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_bundle(path: str | Path, cache_tiles: int = 256) -> TrackerMap:
    """Open the bundle at ``path`` for tracking (see the module docstring). Raises
    :class:`mapstore.bundle.BundleError` when it is not a bundle, ValueError when it holds
    no level-0 intensity."""
    b = _open(path)
    if 0 not in b.levels:
        b.close()
        raise ValueError(f"{path}: the bundle holds no level-0 intensity (levels {list(b.levels)}); "
                         "export it with --levels including 0")

    def read(tr: int, tc: int):
        return b.read_tile(0, tr, tc) if b.has_tile(0, tr, tc) else None

    return TrackerMap(b, TileCache(read, b.grid.shape, b.tile_px, capacity=cache_tiles))
