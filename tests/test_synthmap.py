"""Synthetic maps published without frames (pipeline.testing.synthmap): what benchmarks of diff and
export stand on must be a well-formed map version like a build's."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import zarr

from mapstore.grid import MapGrid
from mapstore.layout import read_floor
from mapstore.repository import MapRepository
from pipeline.config import load_config
from pipeline.mosaic import downsample2
from pipeline.testing.synthmap import Patch, periodic_texture, publish_raster, shards_for_box, texture_tile_fn


@pytest.fixture(scope="module")
def cfg():
    c = copy.deepcopy(load_config(None))
    c["map"].update(chunk_px=64, shard_px=256)
    return c


def test_periodic_texture_tiles_seamlessly():
    tex = periodic_texture(3, 256)
    assert tex.shape == (256, 256) and tex.dtype == np.float32
    assert 1.0 <= tex.min() and tex.max() <= 254.0 and 20 < tex.std() < 50
    # the step across the wrap-around is no larger than steps inside
    inside = np.abs(np.diff(tex, axis=1)).mean()
    across = np.abs(tex[:, 0] - tex[:, -1]).mean()
    assert across < 1.5 * inside


def test_two_versions(tmp_path, cfg):
    url = str(tmp_path / "map")
    grid = MapGrid(0.0, 1.5, 0.0025, 601, 601)
    tex = periodic_texture(1, 512)
    publish_raster(url, grid, texture_tile_fn(tex, grid), cfg=cfg, tag="one")
    patch = Patch(0.7, 0.7, 0.9, 0.8, delta=30.0)
    shards = shards_for_box(grid, 256, patch.x0, patch.y0, patch.x1, patch.y1)
    assert shards == {(1, 1)}
    publish_raster(url, grid, texture_tile_fn(tex, grid, [patch]), cfg=cfg, tag="two", shards=shards)

    repo = MapRepository.open(url)
    assert repo.changed_chunks("one", "two")["floor/0"] == {(1, 1)}
    a = zarr.open_group(repo.readonly("one").store, mode="r")
    b = zarr.open_group(repo.readonly("two").store, mode="r")
    assert read_floor(a).version == 1 and read_floor(b).version == 2
    l0a, l0b = a["floor/0"][...], b["floor/0"][...]
    assert l0a.min() >= 1  # data everywhere
    r0, r1, c0, c1 = patch.pixel_box(grid)
    changed = np.argwhere(l0a != l0b)
    assert changed[:, 0].min() == r0 and changed[:, 0].max() == r1 - 1
    assert changed[:, 1].min() == c0 and changed[:, 1].max() == c1 - 1
    # updated: version 2 exactly on the tiles the patch reaches
    upd = b["floor/layers/updated"][...]
    want = np.zeros_like(upd)
    want[r0 // 64 : (r1 - 1) // 64 + 1, c0 // 64 : (c1 - 1) // 64 + 1] = 1
    assert np.array_equal(upd == 2, want.astype(bool)) and (upd[~want.astype(bool)] == 1).all()
    # the pyramid follows level 0
    info = read_floor(b)
    for k in range(1, info.levels):
        assert np.array_equal(b[f"floor/{k}"][...], downsample2(b[f"floor/{k - 1}"][...]))
    assert np.isfinite(b["floor/layers/texture"][...]).all() and (b["floor/layers/coverage"][...] == 1).all()
    with pytest.raises(ValueError, match="grid"):
        publish_raster(url, MapGrid(0.0, 1.5, 0.0025, 600, 601), texture_tile_fn(tex, grid), cfg=cfg, shards=set())
