"""The nightly build end to end: render, publish, incremental update, gates, schedulers."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import zarr
from click.testing import CliRunner

from mapstore.grid import MapGrid
from mapstore.layout import read_floor, read_poses
from mapstore.repository import MapRepository
from pipeline.cli import cli
from pipeline.evaluate import mosaic_vs_world
from pipeline.simulate.texture import read_float_tiff
from conftest import invoke, SMALL_MAP_TOML as SMALL


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    root = tmp_path_factory.mktemp("site")
    cfg = root / "small.toml"
    cfg.write_text(SMALL)
    day1, day2 = root / "day1", root / "day2"
    r = invoke("simulate", "floor", day1, "--area", "1.5x1.5", "--seed", "5", "--quiet")
    assert r.exit_code == 0, r.output
    r = invoke("simulate", "floor", day2, "--world", day1, "--route", "loop", "--changes", "2", "--seed", "6",
               "--illumination", "0.8", "--quiet")
    assert r.exit_code == 0, r.output
    repo = root / "map"
    r = invoke("build", day1, "--map", repo, "-w", root / "w1", "--config", cfg, "--report", root / "r1.json",
               "--tag", "day1", "--quiet")
    assert r.exit_code == 0, r.output
    return {"root": root, "cfg": cfg, "day1": day1, "day2": day2, "repo": repo,
            "r1": json.loads((root / "r1.json").read_text())}


def _fresh_workdir(site, dst: Path) -> Path:
    """A copy of day 1's work directory up to optimize (render and publish redone)."""
    import shutil

    shutil.copytree(site["root"] / "w1", dst, ignore=shutil.ignore_patterns("render", "publish", ".lock"))
    return dst


def _has_floor(repo: Path) -> bool:
    if not repo.exists():
        return False
    try:
        return "floor" in _floor(repo)
    except zarr.errors.GroupNotFoundError:
        return False


def _floor(repo: Path, version: str | None = None) -> zarr.Group:
    return zarr.open_group(MapRepository.open(str(repo)).readonly(version).store, mode="r")


def test_first_build_publishes_a_tagged_version(site):
    rep = site["r1"]
    assert rep["publish"]["version"] == 1 and rep["publish"]["tag"] == "day1"
    root = _floor(site["repo"], "day1")
    info = read_floor(root)
    assert info.version == 1 and info.levels >= 3
    poses = read_poses(root)
    assert len(poses) == rep["optimization"]["frames"] and set(poses.version.tolist()) == {1}
    assert poses.sources[0]["log_id"] and len(poses.sources[0]["sha256"]) == 64
    meta = MapRepository.open(str(site["repo"])).log()[0]["metadata"]
    assert meta["version"] == 1 and len(meta["config_hash"]) >= 16 and meta["logs"][0]["sha256"]
    assert meta["report"]["links"]["accepted"] == rep["links"]["accepted"]
    # the render's time by phase, the layers' two costly ones apart (bench_render_floor)
    phases = rep["render"]["phase_seconds"]
    assert set(phases) == {"seams", "read", "warp", "blend_finish", "layers", "texture", "uniqueness", "write", "level1"}
    assert phases["uniqueness"] > 0 and phases["texture"] > 0 and phases["warp"] > 0
    # OME-Zarr multiscales: one dataset per level, each half the size of the one below
    ome = root["floor"].attrs["ome"]["multiscales"][0]["datasets"]
    assert [d["path"] for d in ome] == [str(k) for k in range(info.levels)]
    for k in range(1, info.levels):
        assert root[f"floor/{k}"].shape == tuple(-(-s // 2) for s in root[f"floor/{k - 1}"].shape)


def test_level0_matches_the_simulated_world(site):
    root = _floor(site["repo"], "day1")
    info = read_floor(root)
    tex = read_float_tiff(site["day1"] / "world" / "texture.tif")
    tex_grid = MapGrid.from_attrs(json.loads((site["day1"] / "world" / "grid.json").read_text()))
    q = mosaic_vs_world(root["floor/0"][...], info.grid, tex, tex_grid)
    assert q["ncc"] > 0.98 and q["psnr_db"] > 30, q


def test_pyramid_level_is_the_block_mean_of_the_level_below(site):
    root = _floor(site["repo"], "day1")
    l0 = root["floor/0"][...].astype(float)
    l1 = root["floor/1"][...].astype(float)
    h, w = (l0.shape[0] // 2) * 2, (l0.shape[1] // 2) * 2
    blocks = l0[:h, :w].reshape(h // 2, 2, w // 2, 2)
    full = (blocks > 0).all(axis=(1, 3))
    mean = blocks.mean(axis=(1, 3))
    assert np.abs(np.rint(mean[full]) - l1[: h // 2, : w // 2][full]).max() <= 1


def test_layers_are_filled_where_covered(site):
    root = _floor(site["repo"], "day1")
    cov = root["floor/layers/coverage"][...]
    tex = root["floor/layers/texture"][...]
    uniq = root["floor/layers/uniqueness"][...]
    upd = root["floor/layers/updated"][...]
    assert cov.max() >= 2 and np.isfinite(tex[cov > 0]).mean() > 0.9
    inner = np.isfinite(uniq)
    assert inner.sum() > 0.5 * (cov > 0).sum() and np.median(uniq[inner]) > 0.3
    assert set(np.unique(upd).tolist()) <= {0, 1} and (upd == 1).any()
    # cells along shard borders see their neighbours (rendered with a halo): no gaps there
    per = 256 // 16
    border = np.zeros(uniq.shape, bool)
    border[per::per, :] = border[per - 1::per, :] = True
    border[:, per::per] = border[:, per - 1::per] = True
    deep = cv2.erode((cov > 0).astype(np.uint8), np.ones((5, 5), np.uint8), borderValue=0) > 0
    assert np.isfinite(uniq[border & deep]).mean() > 0.95 and np.isfinite(tex[border & deep]).all()


def test_every_stage_writes_its_declared_outputs(site):
    """A stage's files are the ones it declares (pipeline.stages.workspace.OUTPUTS, whose names
    enter its cache fingerprint), beside its manifest."""
    from pipeline.stages.workspace import MANIFEST, OUTPUTS

    conditional = {"map_links.csv", "horizons"}  # over a published map only; omni logs only
    for stage in ("ingest", "register", "optimize", "render", "publish"):
        found = {p.name for p in (site["root"] / "w1" / stage).iterdir()}
        assert MANIFEST in found
        declared = set(OUTPUTS[stage])
        assert found - {MANIFEST} <= declared and declared - found <= conditional, (stage, found, declared)


def test_second_day_is_an_incremental_update(site):
    root = site["root"]
    r = invoke("build", site["day2"], "--map", site["repo"], "-w", root / "w2", "--config", site["cfg"],
               "--report", root / "r2.json", "--quiet")
    assert r.exit_code == 0, r.output
    rep = json.loads((root / "r2.json").read_text())
    assert rep["map"]["base_version"] == 1 and rep["publish"]["version"] == 2
    assert rep["links"]["map_accepted"] >= 0.5 * rep["links"]["map_candidates"] > 0
    # anchored to the map: day-2 poses land on the world frame as day 1's did
    assert rep["ground_truth"]["pose_rms_px"] < 0.5
    repo = MapRepository.open(str(site["repo"]))
    changed = repo.changed_chunks("day1", rep["publish"]["tag"])
    touched = json.loads((root / "w2" / "render" / "touched.json").read_text())["shards"]
    assert changed["floor/0"] == {tuple(t) for t in touched["0"]}
    grid0 = read_floor(_floor(site["repo"], "day1")).grid
    all0 = {(i, j) for i in range(-(-grid0.height // 256)) for j in range(-(-grid0.width // 256))}
    assert changed["floor/0"] <= all0
    v2 = _floor(site["repo"])
    poses = read_poses(v2)
    assert set(poses.version.tolist()) == {1, 2} and len(poses.sources) == 2
    upd = v2["floor/layers/updated"][...]
    assert (upd == 2).any()
    # the log lists both versions, newest first, with their tags
    r = invoke("log", site["repo"])
    assert r.exit_code == 0 and r.output.index(rep["publish"]["tag"]) < r.output.index("day1")
    assert "links" in r.output and "residual RMS" in r.output


def test_a_log_already_in_the_map_is_refused(site, tmp_path):
    # Day 1 is in the map since the first build; building it onto the map again is bad
    # input. (Another tag format makes this a different build from the first one, which a
    # rerun of would find itself already published instead.)
    cfg = tmp_path / "other.toml"
    cfg.write_text(SMALL + '\n[publish]\ntag_format = "again-{n}"\n')
    r = invoke("build", site["day1"], "--map", site["repo"], "-w", tmp_path / "w", "--config", cfg, "--quiet")
    assert r.exit_code == 2 and "already in the map" in r.output and "day1" in r.output


def test_rerun_into_another_repository_reuses_the_stages(site, tmp_path):
    r = invoke("build", site["day1"], "--map", tmp_path / "map", "-w", _fresh_workdir(site, tmp_path / "w"),
               "--config", site["cfg"], "--quiet")
    assert r.exit_code == 0, r.output
    # nothing before render depends on which (empty) repository receives the map
    assert "ingest: skipped" in r.output and "optimize: skipped" in r.output and "publish: done" in r.output


def test_failed_gate_does_not_publish(site, tmp_path):
    cfg = tmp_path / "strict.toml"
    cfg.write_text(SMALL + "\n[publish]\nmax_residual_rms_px = 0.000001\n")
    repo = tmp_path / "map"
    r = invoke("build", site["day1"], "--map", repo, "-w", _fresh_workdir(site, tmp_path / "w"), "--config", cfg,
               "--quiet")
    assert r.exit_code == 1 and "quality gate" in r.output and "max_residual_rms_px" in r.output
    assert not _has_floor(repo)


def test_schedulers_write_identical_maps(site, tmp_path):
    """threads (default), sync, processes and a dask.distributed cluster: the same bytes in every array."""
    from distributed import LocalCluster

    arrays = {}
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cluster:
        for name, sched in (("sync", "sync"), ("processes", "processes"), ("distributed", cluster.scheduler_address)):
            repo = tmp_path / f"map-{name}"
            work = _fresh_workdir(site, tmp_path / f"w-{name}")
            r = invoke("build", site["day1"], "--map", repo, "-w", work, "--config", site["cfg"],
                       "--scheduler", sched, "--quiet")
            assert r.exit_code == 0, r.output
            arrays[name] = _floor(repo)
    ref = _floor(site["repo"], "day1")
    for name in ("floor/0", "floor/1", "floor/2", "floor/layers/coverage", "floor/layers/texture",
                 "floor/layers/uniqueness", "floor/layers/updated"):
        for sched, root in arrays.items():
            np.testing.assert_array_equal(root[name][...], ref[name][...], err_msg=f"{name} with {sched}")


def test_killed_publish_leaves_the_map_untouched_and_resumes(site, tmp_path, monkeypatch):
    import icechunk

    repo = tmp_path / "map"
    work = _fresh_workdir(site, tmp_path / "w")
    calls = {"n": 0}
    real_commit = icechunk.Session.commit

    class Killed(BaseException):  # a kill is not an error the CLI could report (it catches Exception)
        pass

    def dying_commit(self, *a, **k):
        calls["n"] += 1
        raise Killed("the process dies in the middle of the commit")

    monkeypatch.setattr(icechunk.Session, "commit", dying_commit)
    with pytest.raises(Killed):
        CliRunner().invoke(cli, ["build", str(site["day1"]), "--map", str(repo), "-w", str(work),
                                 "--config", str(site["cfg"]), "--quiet"], catch_exceptions=False)
    assert calls["n"] == 1
    monkeypatch.setattr(icechunk.Session, "commit", real_commit)
    assert not _has_floor(repo)
    assert not (work / "publish").exists() and (work / "render" / "manifest.json").exists()
    r = invoke("build", site["day1"], "--map", repo, "-w", work, "--config", site["cfg"], "--quiet")
    assert r.exit_code == 0, r.output
    assert "render: skipped" in r.output and "publish: done" in r.output


def test_grid_plan_grows_right_and_down_only_and_honours_the_site_extent():
    from pipeline.errors import BadInput, JobFailed
    from pipeline.stages.render import plan_grid

    boxes = np.array([[1.0, 1.0, 2.0, 2.0]])
    g = plan_grid(boxes, 0.01, 0.5, None)
    assert np.isclose(g.x0, 0.5) and np.isclose(g.y0, 2.5)
    grown = plan_grid(np.array([[1.0, 0.0, 4.0, 2.0]]), 0.01, 0.5, g)
    assert (grown.x0, grown.y0) == (g.x0, g.y0) and grown.width > g.width and grown.height > g.height
    with pytest.raises(JobFailed, match="outside the published map"):
        plan_grid(np.array([[0.0, 1.0, 1.0, 2.0]]), 0.01, 0.5, g)
    site = plan_grid(boxes, 0.01, 0.5, None, [-10.0, -5.0, 30.0, 20.0])
    assert np.isclose(site.x0, -10.0) and np.isclose(site.y0, 20.0) and site.width == 4001
    with pytest.raises(BadInput, match="site_extent_m"):
        plan_grid(boxes, 0.01, 0.5, None, [1.0, 2.0])
