"""The library under ``mosaicmap export``, ``verify`` and ``apply-delta`` (pipeline.export_run),
called directly as a program would (no click): its reports, summaries and errors."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest

from mapstore.bundle import read_manifest, verify_bundle
from mapstore.grid import MapGrid
from pipeline.config import load_config
from pipeline.errors import BadInput
from pipeline.export_run import (apply_delta_file, apply_delta_summary, export_map, export_summary,
                                 read_corridor_csv, size_text, verify_file, verify_problem, verify_summary)
from pipeline.testing.synthmap import Patch, periodic_texture, publish_repainted

GRID = MapGrid(0.0, 1.0, 0.0025, 384, 400)  # 0.96 x 1.0 m
PATCH = Patch(0.3, 0.4, 0.45, 0.55, delta=40.0)  # version v2 repaints this box


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """A two-version map (v2 repaints PATCH), 64-px chunks in 128-px shards."""
    root = tmp_path_factory.mktemp("export_run")
    cfg = copy.deepcopy(load_config(None))
    cfg["map"].update({"chunk_px": 64, "shard_px": 128, "layer_cell_px": 16})
    url = str(root / "map")
    tex = periodic_texture(3, 256)
    publish_repainted(url, GRID, tex, PATCH, cfg=cfg)
    return {"root": root, "url": url, "cfg": load_config(None)}


def test_export_verify_and_delta_round_trip(site, tmp_path):
    """A full bundle of v1, a delta v1 -> v2 and apply-delta: the patched bundle is v2's
    bundle; each report agrees with the file it describes."""
    cfg, url = site["cfg"], site["url"]
    old, new, delta, patched = (tmp_path / n for n in ("v1.zip", "v2.zip", "delta.zip", "patched.zip"))
    rep = export_map(url, old, cfg=cfg, version="v1", levels=[], quiet=True)
    m = read_manifest(old)
    assert rep["kind"] == "full" and rep["format"] == "bundle" and rep["path"] == str(old)
    assert rep["bytes"] == old.stat().st_size and rep["members"] == len(m["members"]) + 1
    assert rep["version"] == m["version"] and rep["version"]["number"] == 1
    assert rep["content_sha256"] == m["content_sha256"] and rep["signed_by"] is None
    assert rep["levels"] == list(range(len(rep["levels"]))) and len(rep["levels"]) >= 3  # [] = every level
    assert rep["layers"] == list(cfg["export"]["layers"])  # None = the configured layers
    assert rep["reloc_index"] is not None and rep["reloc_index"]["tiles"] > 0  # level 0 exported to a bundle
    text = export_summary(rep)
    assert text.startswith(f"bundle {old}: {rep['members']} members") and "version 1 (" in text
    assert size_text(rep["bytes"]) in text and "\n" not in text

    export_map(url, new, cfg=cfg, levels=[], quiet=True)
    rep = export_map(url, delta, cfg=cfg, levels=[], since="v1", quiet=True)
    assert rep["kind"] == "delta" and rep["base"]["number"] == 1 and rep["version"]["number"] == 2
    assert 0 < rep["changed_tiles"] < rep["selected_tiles"]
    assert rep["changed_fraction"] == pytest.approx(rep["changed_tiles"] / rep["selected_tiles"])
    assert export_summary(rep).startswith(f"delta {delta}:") and "since version 1" in export_summary(rep)

    v = verify_file(delta)
    assert v["ok"] and v["problems"] == [] and v["kind"] == "delta" and v["base"]["number"] == 1
    assert v["signature_checked"] is False and verify_problem(v) is None
    assert "OK: delta bundle" in verify_summary(v) and "signature not checked" in verify_summary(v)

    a = apply_delta_file(old, delta, patched)
    assert a["content_sha256"] == read_manifest(new)["content_sha256"] == read_manifest(patched)["content_sha256"]
    assert a["delta_ratio"] == pytest.approx(delta.stat().st_size / patched.stat().st_size)
    assert apply_delta_summary(a).startswith(f"{patched}: version 2 (") and "= v1.zip + delta.zip" in \
        apply_delta_summary(a)


def test_verify_file_reports_a_bad_bundle_without_raising(site, tmp_path):
    good = tmp_path / "good.zip"
    export_map(site["url"], good, cfg=site["cfg"], region=[0.1, 0.1, 0.3, 0.3], quiet=True)
    data = bytearray(good.read_bytes())
    data[len(data) // 2] ^= 0xFF
    bad = tmp_path / "bad.zip"
    bad.write_bytes(bytes(data))
    rep = verify_file(bad)
    assert rep["ok"] is False and rep["problems"] == verify_bundle(bad) and rep["bytes"] == len(data)
    assert "kind" not in rep  # nothing of a broken manifest is trusted
    line = verify_problem(rep)
    assert line.startswith(rep["problems"][0])
    assert ("more problem" in line) == (len(rep["problems"]) > 1)
    with pytest.raises(BadInput, match="file not found"):
        verify_file(tmp_path / "absent.zip")


def test_ome_zarr_report_names_the_images_to_open(site, tmp_path):
    out = tmp_path / "ome"
    rep = export_map(site["url"], out, cfg=site["cfg"], fmt="ome-zarr", layers=["intensity", "texture"], quiet=True)
    assert rep["format"] == "ome-zarr" and rep["reloc_index"] is None  # never by default in a directory
    assert rep["bytes"] == sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    assert set(rep["open"]) >= {"intensity", "texture"} and all(Path(p).is_dir() for p in rep["open"].values())
    lines = export_summary(rep).splitlines()
    assert lines[0].startswith(f"OME-Zarr directory {out}:") and lines[1].startswith("open in an OME-Zarr viewer")
    assert lines[2:] == [f"  {name}: {p}" for name, p in rep["open"].items()]


@pytest.mark.parametrize("kw, where, what", [
    ({"region": [0, 0, 0.2, 0.2], "corridor": "path"}, "--region", "not both"),
    ({"width_m": 0.3}, "--width", "--corridor only"),
    ({"since": "v1", "fmt": "ome-zarr"}, "--since", "not with --format ome-zarr"),
    ({"sign_key": "key", "fmt": "ome-zarr"}, "--sign", "signs bundles and deltas"),
    ({"fmt": "tiff"}, "--format", "expected one of bundle, ome-zarr"),
    ({"levels": [1], "reloc_index": True}, "--reloc-index", "intensity level 0"),
    ({"layers": ["texture"], "fmt": "ome-zarr"}, "--layers", "needs the intensity layer"),
    ({"region": [5, 5, 6, 6]}, "--region", "outside the map"),
    ({"since": "v2", "version": "v1"}, "--since", "not an ancestor"),
    ({"version": "nope"}, "{url}", "unknown version"),
])
def test_export_map_refuses_naming_the_option(site, tmp_path, kw, where, what):
    path = tmp_path / "path.csv"
    path.write_text("x,y\n0.1,0.1\n0.5,0.5\n")
    kw = {k: path if v == "path" else tmp_path / "k" if v == "key" else v for k, v in kw.items()}
    out = tmp_path / "out.zip"
    with pytest.raises(BadInput) as e:
        export_map(site["url"], out, cfg=site["cfg"], quiet=True, **kw)
    assert e.value.where == where.replace("{url}", site["url"]) and what in e.value.what, str(e.value)
    assert not out.exists()


def test_corridor_export_and_the_corridor_csv(site, tmp_path):
    path = tmp_path / "path.csv"
    path.write_text("t,x,y,theta\n0,0.1,0.5,0\n1,0.8,0.5,0\n\n")  # a drive log's columns work too
    np.testing.assert_allclose(read_corridor_csv(path), [[0.1, 0.5], [0.8, 0.5]])
    rep = export_map(site["url"], tmp_path / "c.zip", cfg=site["cfg"], corridor=path, quiet=True)
    sel = rep["selection"]
    assert sel["kind"] == "corridor" and sel["width_m"] == site["cfg"]["export"]["corridor_width_m"]  # the default
    rep = export_map(site["url"], tmp_path / "c.zip", cfg=site["cfg"], corridor=path, width_m=0.2, quiet=True)
    x0, y0, x1, y1 = rep["bounds_m"]
    assert rep["selection"]["width_m"] == 0.2 and y1 - y0 < 0.3  # a band along the path, not the whole map
    assert y0 <= 0.4 + 1e-6 and y1 >= 0.6 - 1e-6
    for text, where in (("x,y\n0,0\n1\n", ":3"), ("a,b\n0,0\n", ":1"), ("x,y\n0,0\n", "")):
        path.write_text(text)
        with pytest.raises(BadInput) as e:
            read_corridor_csv(path)
        assert e.value.where == f"{path}{where}", str(e.value)
