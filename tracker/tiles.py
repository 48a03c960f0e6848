"""Windows of a tiled map raster through a bounded cache of decoded tiles.

The tracker reads small windows (tens of pixels) around predicted template positions, fix
after fix over the same few tiles: decoding a zstd tile costs far more than cutting a window
from it, so decoded tiles are kept in a least-recently-used cache of ``capacity`` tiles
(``capacity x tile_px^2`` bytes for uint8: 256 tiles of 256 px = 16 MiB).

Pixels are addressed in the raster's own (row, column) integers, as
:class:`mapstore.grid.MapGrid` numbers them; outside the raster and in tiles the source does
not hold, the window holds ``fill`` (0 = no data for intensity).
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Callable

import numpy as np

__all__ = ["TileCache", "ArrayTiles"]

TileReader = Callable[[int, int], "np.ndarray | None"]


class TileCache:
    """LRU cache of the tiles of one raster of ``shape`` (rows, cols) cut in ``tile_px``
    squares; ``read_tile(tr, tc)`` returns tile (tr, tc) (edge tiles may be smaller) or
    None when the source holds no data there. Not thread-safe (one tracker, one thread)."""

    def __init__(self, read_tile: TileReader, shape: tuple[int, int], tile_px: int, capacity: int = 256,
                 dtype=np.uint8, fill=0):
        if capacity < 1:
            raise ValueError("capacity must be >= 1 tile")
        self._read = read_tile
        self.shape = (int(shape[0]), int(shape[1]))
        self.tile_px = int(tile_px)
        self.capacity = int(capacity)
        self.dtype = np.dtype(dtype)
        self.fill = fill
        self._tiles: OrderedDict[tuple[int, int], np.ndarray | None] = OrderedDict()
        self._full: dict[tuple[int, int], bool] = {}  # tile holds data (no fill value) everywhere
        self.hits = 0
        self.misses = 0
        self.reads_ahead = 0  # tiles read by warm(), ahead of the fixes

    def tile(self, tr: int, tc: int) -> np.ndarray | None:
        key = (tr, tc)
        t = self._tiles.get(key, False)
        if t is not False:
            self._tiles.move_to_end(key)
            self.hits += 1
            return t
        self.misses += 1
        t = self._read(tr, tc)
        self._tiles[key] = t
        if len(self._tiles) > self.capacity:
            self._tiles.popitem(last=False)
        return t

    def resize(self, capacity: int) -> None:
        """Keep at most ``capacity`` (>= 1) tiles from now on (the least recently used go first)."""
        if capacity < 1:
            raise ValueError("capacity must be >= 1 tile")
        self.capacity = int(capacity)
        while len(self._tiles) > self.capacity:
            self._tiles.popitem(last=False)

    def warm(self, r0: int, r1: int, c0: int, c1: int) -> int:
        """Read every tile of ``[r0, r1) x [c0, c1)`` (raster pixels, clipped to the raster)
        that is not cached, at most ``capacity`` of them; returns how many were read. Cached
        tiles are left where they are in the LRU order and counted neither hit nor miss."""
        h, w = self.shape
        a0, a1, b0, b1 = max(r0, 0), min(r1, h), max(c0, 0), min(c1, w)
        if a0 >= a1 or b0 >= b1:
            return 0
        t, n = self.tile_px, 0
        for tr in range(a0 // t, (a1 - 1) // t + 1):
            for tc in range(b0 // t, (b1 - 1) // t + 1):
                if (tr, tc) not in self._tiles and n < self.capacity:
                    self._tiles[(tr, tc)] = self._read(tr, tc)
                    n += 1
                    self.reads_ahead += 1
                    if len(self._tiles) > self.capacity:
                        self._tiles.popitem(last=False)
        return n

    def full(self, r0: int, r1: int, c0: int, c1: int) -> bool:
        """Whether every raster pixel of ``[r0, r1) x [c0, c1)`` holds data (none is the
        fill value; False when the box reaches beyond the raster). Decided per tile and
        remembered, so a box inside wholly covered tiles costs a few dictionary lookups."""
        h, w = self.shape
        if r0 < 0 or c0 < 0 or r1 > h or c1 > w or r0 >= r1 or c0 >= c1:
            return False
        t = self.tile_px
        for tr in range(r0 // t, (r1 - 1) // t + 1):
            for tc in range(c0 // t, (c1 - 1) // t + 1):
                f = self._full.get((tr, tc))
                if f is None:
                    tile = self.tile(tr, tc)
                    f = self._full[(tr, tc)] = tile is not None and bool((tile != self.fill).all())
                if not f:
                    return False
        return True

    def window(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """Raster pixels ``[r0, r1) x [c0, c1)``; the box may reach beyond the raster."""
        out = np.full((r1 - r0, c1 - c0), self.fill, self.dtype)
        h, w = self.shape
        a0, a1, b0, b1 = max(r0, 0), min(r1, h), max(c0, 0), min(c1, w)
        if a0 >= a1 or b0 >= b1:
            return out
        t = self.tile_px
        for tr in range(a0 // t, (a1 - 1) // t + 1):
            for tc in range(b0 // t, (b1 - 1) // t + 1):
                tile = self.tile(tr, tc)
                if tile is None:
                    continue
                y0, x0 = tr * t, tc * t
                s0, s1 = max(a0, y0), min(a1, y0 + tile.shape[0])
                u0, u1 = max(b0, x0), min(b1, x0 + tile.shape[1])
                if s0 < s1 and u0 < u1:
                    out[s0 - r0 : s1 - r0, u0 - c0 : u1 - c0] = tile[s0 - y0 : s1 - y0, u0 - x0 : u1 - x0]
        return out


class ArrayTiles(TileCache):
    """A TileCache over an in-memory array (tests, small maps): tiles are views."""

    def __init__(self, array: np.ndarray, tile_px: int = 256):
        a = np.asarray(array)

        def read(tr: int, tc: int) -> np.ndarray:
            return a[tr * tile_px : (tr + 1) * tile_px, tc * tile_px : (tc + 1) * tile_px]

        super().__init__(read, a.shape, tile_px, capacity=1 << 30, dtype=a.dtype)
