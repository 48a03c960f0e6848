"""mapstore.routes: the /routes part of the map layout."""

import numpy as np
import pytest
import zarr

from mapstore.routes import RouteRecord, delete_route, list_routes, read_route, write_route


def _record(m=2500, spd=1.0):
    rng = np.random.default_rng(0)
    lines = rng.integers(0, 256, (m, int(360 * spd)), dtype=np.uint8)
    s = np.arange(m) * 0.02
    poses = np.column_stack([s, np.zeros(m), np.full(m, 0.1)]).astype(np.float32)
    return RouteRecord(lines, poses, s0_m=0.0, spacing_m=0.02, samples_per_degree=spd, version=3,
                       sources=[{"log_id": "a", "frames": m}], meta={"runs": 2})


def test_roundtrip_and_chunks(tmp_path):
    root = zarr.open_group(str(tmp_path / "m.zarr"), mode="w")
    rec = _record()
    write_route(root, "aisle-1", rec, rows_per_chunk=1000)
    assert list_routes(root) == ["aisle-1"]
    back = read_route(zarr.open_group(str(tmp_path / "m.zarr"), mode="r"), "aisle-1")
    np.testing.assert_array_equal(back.lines, rec.lines)
    np.testing.assert_array_equal(back.poses, rec.poses)
    assert (back.spacing_m, back.samples_per_degree, back.version) == (0.02, 1.0, 3)
    assert back.sources == [{"log_id": "a", "frames": 2500}] and back.meta == {"runs": 2}
    assert root["routes/aisle-1/lines"].chunks == (1000, 360)
    assert back.length_m == pytest.approx(49.98)
    write_route(root, "aisle-1", _record(10))  # replaced whole
    assert read_route(root, "aisle-1").rows == 10
    delete_route(root, "aisle-1")
    assert list_routes(root) == []


def test_bad_records_and_ids(tmp_path):
    root = zarr.open_group(str(tmp_path / "m.zarr"), mode="w")
    with pytest.raises(ValueError, match="route id"):
        write_route(root, "a/b", _record(5))
    with pytest.raises(ValueError, match="azimuths"):
        RouteRecord(np.zeros((3, 100), np.uint8), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="poses"):
        RouteRecord(np.zeros((3, 360), np.uint8), np.zeros((2, 3)))
    bad = np.zeros((3, 3))
    bad[1, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        RouteRecord(np.zeros((3, 360), np.uint8), bad)
    with pytest.raises(KeyError, match="no route"):
        read_route(root, "missing")


def test_route_attrs_without_arrays(tmp_path):
    root = zarr.open_group(str(tmp_path / "m.zarr"), mode="w")
    write_route(root, "a", _record(20))
    from mapstore.routes import route_attrs

    attrs = route_attrs(root, "a")
    assert attrs["version"] == 3 and attrs["rows"] == 20 and attrs["sources"] == [{"log_id": "a", "frames": 20}]
    with pytest.raises(KeyError):
        route_attrs(root, "b")
