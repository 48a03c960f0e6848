"""pipeline.shardfile: whole shards and chunks written straight to a local zarr v3 array's files."""

from __future__ import annotations

import numpy as np
import pytest
import zarr

from pipeline.shardfile import DirectWriter, write_region


def _pair(tmp_path, **kw):
    """The same array in two local stores: one written by zarr, one directly."""
    out = []
    for name in ("zarr", "direct"):
        g = zarr.open_group(str(tmp_path / name), mode="w")
        out.append(g.create_array("a", **kw))
    return out


def test_sharded_uint8_shards_read_back_as_zarr_writes_them(tmp_path):
    kw = dict(shape=(700, 530), dtype="uint8", chunks=(64, 64), shards=(256, 256), fill_value=0,
              compressors=zarr.codecs.ZstdCodec(level=3))
    ref, arr = _pair(tmp_path, **kw)
    writer = DirectWriter.for_array(arr)
    assert writer is not None and writer.sharded and writer.shard == (256, 256) and writer.chunk == (64, 64)
    rng = np.random.default_rng(1)
    data = rng.integers(1, 256, (700, 530)).astype(np.uint8)
    data[:128, :] = 0  # empty chunks: not stored
    data[300:310, 10:20] = 0
    for i in range(3):
        for j in range(3):
            r0, c0 = 256 * i, 256 * j
            part = data[r0 : r0 + 256, c0 : c0 + 256]  # the edge shards are partial
            ref[r0 : r0 + part.shape[0], c0 : c0 + part.shape[1]] = part
            write_region(arr, writer, r0, c0, part)
    assert np.array_equal(arr[...], data) and np.array_equal(arr[...], ref[...])
    # An all-empty shard replacing one with data removes its file, as zarr does.
    shard = tmp_path / "direct" / "a" / "c" / "1" / "1"
    assert shard.exists()
    writer.write((1, 1), np.zeros((256, 256), np.uint8))
    assert not shard.exists() and not arr[256:512, 256:512].any()
    # Shard (0, 0): its two top rows of chunks are empty, absent from its index.
    raw = (tmp_path / "direct" / "a" / "c" / "0" / "0").read_bytes()
    index = np.frombuffer(raw[-(16 * 16 + 4) : -4], "<u8").reshape(4, 4, 2)
    assert (index[:2] == 2**64 - 1).all() and (index[2:] != 2**64 - 1).all()
    assert np.array_equal(arr[:256, :256], data[:256, :256])


@pytest.mark.parametrize("dtype, fill", [("float32", float("nan")), ("uint16", 0), ("int32", 0)])
def test_unsharded_chunks_read_back(tmp_path, dtype, fill):
    kw = dict(shape=(40, 27), dtype=dtype, chunks=(16, 16), fill_value=fill, compressors=zarr.codecs.ZstdCodec(level=3))
    ref, arr = _pair(tmp_path, **kw)
    writer = DirectWriter.for_array(arr)
    assert writer is not None and not writer.sharded
    rng = np.random.default_rng(2)
    data = (rng.random((40, 27)) * 1000).astype(dtype)
    if dtype == "float32":
        data[:16, :16] = np.nan  # an empty chunk
        data[20, 20] = np.nan
    for i in range(3):
        for j in range(2):
            part = data[16 * i : 16 * i + 16, 16 * j : 16 * j + 16]
            write_region(arr, writer, 16 * i, 16 * j, part)
            ref[16 * i : 16 * i + part.shape[0], 16 * j : 16 * j + part.shape[1]] = part
    assert np.array_equal(arr[...], data, equal_nan=True) and np.array_equal(arr[...], ref[...], equal_nan=True)
    assert (dtype == "float32") != (tmp_path / "direct" / "a" / "c" / "0" / "0").exists()


def test_other_regions_and_arrays_go_through_zarr(tmp_path):
    arr = zarr.open_group(str(tmp_path / "g"), mode="w").create_array(
        "a", shape=(100, 100), dtype="uint8", chunks=(32, 32), shards=(64, 64), fill_value=0)
    writer = DirectWriter.for_array(arr)
    part = np.full((10, 10), 7, np.uint8)
    write_region(arr, writer, 5, 5, part)  # not a whole shard: zarr writes it
    assert (arr[5:15, 5:15] == 7).all() and arr[...].sum() == 700
    with pytest.raises(ValueError, match="shard"):
        writer.write((0, 0), part)
    mem = zarr.create_array(zarr.storage.MemoryStore(), shape=(8, 8), chunks=(4, 4), dtype="uint8")
    assert DirectWriter.for_array(mem) is None
    crc = zarr.open_group(str(tmp_path / "c"), mode="w").create_array(
        "a", shape=(8, 8), chunks=(4, 4), dtype="uint8", compressors=zarr.codecs.GzipCodec())
    assert DirectWriter.for_array(crc) is None
