"""Inputs as real users bring them, built with the defaults (issue: real inputs).

Tile grids from ``mosaicmap simulate tiles`` (known true positions): 16-bit tiles using
1/50 of the range register like their 8-bit copies; 3 % overlap strips with a stage error
larger than the strip register. A floor log whose prior is wrong (one lane's heading
flipped by pi, or a 5 % scale error with a loose heading) is corrected by its links.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from pipeline.cli import cli
from pipeline.importers.tiles import read_tile_configuration, tile_positions_from_poses
from pipeline.links import read_links

PX = 0.001  # metres per tile pixel given to import-tiles


def _cli(*args) -> None:
    r = CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)
    assert r.exit_code == 0, r.output


def _grid_build(tmp: Path, name: str, *sim_args: str, stage_error: float) -> tuple[Path, Path]:
    """Simulate a tile grid, import it (with its truth) and build it to optimize; returns
    (grid folder, work dir)."""
    grid, log, work = tmp / f"{name}_grid", tmp / f"{name}_log", tmp / f"{name}_work"
    _cli("simulate", "tiles", grid, *sim_args, "--stage-error", stage_error, "--quiet")
    _cli("import-tiles", grid / "TileConfiguration.txt", log, "--pixel-size", PX, "--stage-error", stage_error,
         "--truth", grid / "TileConfiguration.truth.txt", "--quiet")
    _cli("build", log, "-w", work, "--until", "optimize", "--quiet", "--report", tmp / f"{name}.json")
    return grid, work


def _positions(grid: Path, work: Path, tile: int) -> tuple[np.ndarray, np.ndarray]:
    """(ours, truth) tile positions (N, 2) in pixels, ours shifted by the mean offset."""
    truth = np.array([(x, y) for _, x, y in read_tile_configuration(grid / "TileConfiguration.truth.txt")])
    p = np.genfromtxt(work / "poses.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    ours = tile_positions_from_poses(np.column_stack([p["x"], p["y"], p["theta"]]), (tile, tile), PX)
    return ours - (ours - truth).mean(axis=0), truth


def _accepted(work: Path) -> dict[tuple[int, int], np.ndarray]:
    return {(lk.a, lk.b): lk.rel for lk in read_links(work / "optimize" / "links.csv") if lk.status == "accepted"}


def test_16_bit_tiles_at_a_fiftieth_of_the_range_register_like_8_bit(tmp_path):
    """A grid stored as 16-bit values 700..2011 (1/50 of the range) and its 8-bit stretched
    copy build with the defaults alike: ingest normalizes the 16-bit log's used range, and
    every link comes out within 0.01 px of the 8-bit one."""
    import cv2

    g16 = tmp_path / "g16"
    _cli("simulate", "tiles", g16, "--grid", "3x3", "--tile", "256", "--overlap", "0.12", "--seed", "4", "--bits", "16",
         "--value-range", "700,2011", "--stage-error", 8, "--quiet")
    g8 = tmp_path / "g8"
    g8.mkdir()
    for f in g16.iterdir():
        if f.suffix == ".tif":
            raw = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
            assert raw.dtype == np.uint16 and 600 <= raw.min() and raw.max() <= 2100
            # (the tiles' gains take a few values past the range: the copy spans them all)
            v = (raw.astype(np.float64) - 600.0) * 255.0 / 1500.0
            cv2.imwrite(str(g8 / f.name), np.clip(np.round(v), 0, 255).astype(np.uint8))
        else:
            (g8 / f.name).write_bytes(f.read_bytes())
    works = []
    for g in (g8, g16):
        log, work = tmp_path / f"{g.name}_log", tmp_path / f"{g.name}_work"
        _cli("import-tiles", g / "TileConfiguration.txt", log, "--pixel-size", PX, "--stage-error", 8, "--quiet")
        _cli("build", log, "-w", work, "--until", "optimize", "--quiet")
        works.append(work)
    l8, l16 = (_accepted(w) for w in works)
    assert len(l8) == 12 and set(l8) == set(l16)
    worst = max(float(np.hypot(*(l8[k][:2] - l16[k][:2]))) / PX for k in l8)
    assert worst <= 0.01, worst


def test_three_percent_overlap_with_a_stage_error_beyond_the_strip(tmp_path):
    """512 px tiles overlapping by 3 % (15 px) with +-40 px of stage error (so that many
    neighbours do not overlap at all): at least 95 % of the neighbours that truly overlap by
    12 px or more are linked, and the tiles they join land within 0.1 px RMS of the truth
    (after a translation fit over the largest group of tiles so joined; tiles joined to
    nothing are placed by their stage positions, which no tool can improve)."""
    grid, work = _grid_build(tmp_path, "g3", "--grid", "6x5", "--tile", "512", "--overlap", "0.03", "--seed", "2",
                             stage_error=40)
    ours, truth = _positions(grid, work, 512)
    meta = json.loads((grid / "grid.json").read_text())
    colrow = {i: (t["col"], t["row"]) for i, t in enumerate(meta["tiles"])}
    links = _accepted(work)
    need, linked = [], 0
    for i in colrow:
        for j in colrow:
            (ci, ri), (cj, rj) = colrow[i], colrow[j]
            if j <= i or abs(ci - cj) + abs(ri - rj) != 1:
                continue
            d = np.abs(truth[j] - truth[i])
            strip = 512 - (d[0] if ci != cj else d[1])
            side = 512 - (d[1] if ci != cj else d[0])
            if strip >= 12 and side > 0:
                need.append((i, j))
                linked += (i, j) in links or (j, i) in links
    assert len(need) >= 10 and linked >= 0.95 * len(need), (linked, len(need))
    # the largest group of tiles joined by such overlaps
    label = list(range(len(colrow)))

    def root(i: int) -> int:
        while label[i] != i:
            i = label[i]
        return i

    for i, j in need:
        label[root(i)] = root(j)
    roots = np.array([root(i) for i in range(len(colrow))])
    group = roots == np.bincount(roots).argmax()
    assert group.sum() >= 6
    d = (ours - truth)[group]
    err = np.hypot(*(d - d.mean(axis=0)).T)
    assert np.sqrt(np.mean(err**2)) <= 0.1, err


@pytest.fixture(scope="module")
def floor_log(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("prior")
    _cli("simulate", "floor", root / "log", "--area", "2x2", "--seed", "1", "--quiet")
    return root / "log"


@pytest.mark.parametrize("variant", ["flipped", "loose"])
def test_a_wrong_prior_loses_to_consistent_links(floor_log, tmp_path, variant):
    """One lane's prior heading flipped by pi (gimbal vs body yaw), or positions 5 % too long
    with the heading declared loose (0.2 rad): the links win, the poses land within 0.2 px
    RMS of the truth and nothing is ghosted (max 0.5 px)."""
    from pipeline.simulate.prior_errors import rewrite_prior

    log = tmp_path / "log"
    rewrite_prior(floor_log, log, variant, lane=1)
    args = []
    if variant == "loose":
        (tmp_path / "loose.toml").write_text("[optimize]\nodometry_heading_sigma_floor_rad = 0.2\n")
        args = ["--config", tmp_path / "loose.toml"]
    _cli("build", log, "-w", tmp_path / "w", "--until", "optimize", "--quiet", "--report", tmp_path / "r.json", *args)
    rep = json.loads((tmp_path / "r.json").read_text())
    gt = rep["ground_truth"]
    assert gt["pose_rms_px"] <= 0.2 and gt["pose_max_px"] <= 0.5, gt
    if variant == "flipped":
        assert rep["registration"]["prior"]["frames_corrected"] > 0
