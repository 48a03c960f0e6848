"""`mosaicmap import-tiles DIR OUT --grid ...` (tile grids without a TileConfiguration),
TileConfiguration dialects, ``--truth``, and the real 9 x 7 brain-section grid."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest
from click.testing import CliRunner

from pipeline.cli import cli
from pipeline.drivelog import read_drive_log, read_pose_csv
from pipeline.errors import BadInput
from pipeline.importers.tiles import GRID_CORNERS, GRID_ORDERS, grid_cells, read_tile_configuration, tile_positions_from_poses

REAL = Path(__file__).resolve().parents[2] / "shared" / "data" / "real"
TILE_W, TILE_H = 20, 16
STEP_X, STEP_Y = 17, 13

# The acquisition index (1-based) of each cell of a 4-column x 3-row grid, rows top to
# bottom, columns left to right: what Fiji's Grid/Collection types and orders mean.
PICTURES = {
    ("row-by-row", "top-left"): [[1, 2, 3, 4], [5, 6, 7, 8], [9, 10, 11, 12]],         # Right & Down
    ("row-by-row", "top-right"): [[4, 3, 2, 1], [8, 7, 6, 5], [12, 11, 10, 9]],        # Left & Down
    ("row-by-row", "bottom-left"): [[9, 10, 11, 12], [5, 6, 7, 8], [1, 2, 3, 4]],      # Right & Up
    ("row-by-row", "bottom-right"): [[12, 11, 10, 9], [8, 7, 6, 5], [4, 3, 2, 1]],     # Left & Up
    ("snake-rows", "top-left"): [[1, 2, 3, 4], [8, 7, 6, 5], [9, 10, 11, 12]],
    ("snake-rows", "top-right"): [[4, 3, 2, 1], [5, 6, 7, 8], [12, 11, 10, 9]],
    ("snake-rows", "bottom-left"): [[9, 10, 11, 12], [8, 7, 6, 5], [1, 2, 3, 4]],
    ("snake-rows", "bottom-right"): [[12, 11, 10, 9], [5, 6, 7, 8], [4, 3, 2, 1]],
    ("column-by-column", "top-left"): [[1, 4, 7, 10], [2, 5, 8, 11], [3, 6, 9, 12]],   # Down & Right
    ("column-by-column", "top-right"): [[10, 7, 4, 1], [11, 8, 5, 2], [12, 9, 6, 3]],  # Down & Left
    ("column-by-column", "bottom-left"): [[3, 6, 9, 12], [2, 5, 8, 11], [1, 4, 7, 10]],  # Up & Right
    ("column-by-column", "bottom-right"): [[12, 9, 6, 3], [11, 8, 5, 2], [10, 7, 4, 1]],  # Up & Left
    ("snake-columns", "top-left"): [[1, 6, 7, 12], [2, 5, 8, 11], [3, 4, 9, 10]],
    ("snake-columns", "top-right"): [[12, 7, 6, 1], [11, 8, 5, 2], [10, 9, 4, 3]],
    ("snake-columns", "bottom-left"): [[3, 4, 9, 10], [2, 5, 8, 11], [1, 6, 7, 12]],
    ("snake-columns", "bottom-right"): [[10, 9, 4, 3], [11, 8, 5, 2], [12, 7, 6, 1]],
}


def run(*args) -> object:
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def one_error_line(res) -> str:
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1, res.output
    return lines[0]


def expected_positions(picture: list[list[int]], step=(STEP_X, STEP_Y)) -> np.ndarray:
    """Top-left corners (pixels) of the tiles in acquisition order from a picture of indices."""
    pic = np.array(picture)
    out = np.zeros((pic.size, 2))
    for r in range(pic.shape[0]):
        for c in range(pic.shape[1]):
            out[pic[r, c] - 1] = (c * step[0], r * step[1])
    return out


def make_tile_dir(d: Path, n: int, *, name: str = "t{:02d}.png", start: int = 1) -> Path:
    d.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(n)
    for i in range(start, start + n):
        assert oiio.ImageBuf(rng.integers(0, 256, (TILE_H, TILE_W), dtype=np.uint8)).write(str(d / name.format(i)))
    return d


@pytest.mark.parametrize("order, first", list(PICTURES))
def test_grid_cells(order, first):
    cells = grid_cells(4, 3, order, first)
    pic = np.zeros((3, 4), int)
    for k, (c, r) in enumerate(cells, start=1):
        pic[r, c] = k
    np.testing.assert_array_equal(pic, PICTURES[(order, first)])


def test_pictures_cover_every_combination():
    assert set(PICTURES) == {(o, f) for o in GRID_ORDERS for f in GRID_CORNERS}


@pytest.mark.parametrize("order, first", list(PICTURES))
def test_import_grid_every_order_and_corner(tmp_path, order, first):
    src = make_tile_dir(tmp_path / "tiles", 12)
    out = tmp_path / "log"
    m = 0.001
    res = run("import-tiles", src, out, "--pixel-size", m, "--grid", "4x3", "--order", order, "--first", first,
              "--step", f"{STEP_X},{STEP_Y}", "--pattern", "t{i:02d}.png", "--report", tmp_path / "r.json", "-q")
    assert res.exit_code == 0, res.output
    lg = read_drive_log(out)
    assert lg.frame_images == [f"images/t{i:02d}.png" for i in range(1, 13)]  # acquisition order
    np.testing.assert_array_equal(lg.frame_t, np.arange(12))
    xy = tile_positions_from_poses(lg.odometry, (TILE_H, TILE_W), m)
    np.testing.assert_allclose(xy, expected_positions(PICTURES[(order, first)]), atol=1e-9)
    assert np.all(lg.odometry[:, 3] == 0)
    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["grid"] == {"columns": 4, "rows": 3, "order": order, "first": first,
                           "step_px": [STEP_X, STEP_Y], "files": "--pattern t{i:02d}.png from 1"}
    assert rep["tile_configuration"] is None and rep["frames"] == 12
    assert rep["extent_px"] == [3 * STEP_X + TILE_W, 2 * STEP_Y + TILE_H]
    assert lg.meta["source"]["kind"] == "tile_grid" and lg.meta["source"]["grid"] == "4x3"


def test_import_grid_overlap_glob_and_fiji_pattern(tmp_path):
    # unpadded names: the glob sorts digit runs as numbers (s2 before s10)
    src = make_tile_dir(tmp_path / "a", 6, name="s{}.png")
    (src / "notes.txt").write_text("not a tile")
    out = tmp_path / "log"
    res = run("import-tiles", src, out, "--pixel-size", 0.001, "--grid", "3x2", "--overlap", "0.1,0.25", "-q")
    assert res.exit_code == 0, res.output  # default glob: the image files
    lg = read_drive_log(out)
    assert lg.frame_images == [f"images/s{i}.png" for i in range(1, 7)]
    step = (TILE_W * 0.9, TILE_H * 0.75)
    np.testing.assert_allclose(tile_positions_from_poses(lg.odometry, (TILE_H, TILE_W), 0.001),
                               expected_positions([[1, 2, 3], [4, 5, 6]], step), atol=1e-9)
    # Fiji's {iii} with indices from 0; other files of the folder are not tiles
    src = make_tile_dir(tmp_path / "b", 4, name="tile_{:03d}_x.png", start=0)
    make_tile_dir(tmp_path / "b", 1, name="other{}.png")
    res = run("import-tiles", src, tmp_path / "log2", "--pixel-size", 0.001, "--grid", "2x2", "--order",
              "snake-columns", "--first", "bottom-right", "--step", 10, "--pattern", "tile_{iii}_x.png",
              "--first-index", 0, "-q")
    assert res.exit_code == 0, res.output
    lg = read_drive_log(tmp_path / "log2")
    assert lg.frame_images == [f"images/tile_{i:03d}_x.png" for i in range(4)]
    np.testing.assert_allclose(tile_positions_from_poses(lg.odometry, (TILE_H, TILE_W), 0.001),
                               [[10, 10], [10, 0], [0, 0], [0, 10]], atol=1e-9)
    res = run("import-tiles", src, tmp_path / "log3", "--pixel-size", 0.001, "--grid", "1x5", "--step", 10,
              "--glob", "*.png", "-q")
    assert res.exit_code == 0, res.output  # 4 tiles and other1.png: a 1-column grid
    lg = read_drive_log(tmp_path / "log3")
    assert lg.frame_images[0] == "images/other1.png"
    np.testing.assert_allclose(lg.odometry[:, 1], 0.001 * (TILE_W - 1) / 2)


@pytest.mark.parametrize("files, args, expect", [
    (11, ["--pattern", "t{i:02d}.png"], "11 of the grid's 12 tiles found"),
    (11, ["--pattern", "t{i:02d}.png"], "first missing: 't12.png'"),
    (13, ["--pattern", "t{i:02d}.png"], "13 files match, the grid has 12 cells; more files than grid cells (e.g. 't13.png')"),
    (11, [], "11 files, the grid has 12 cells (fewer files than grid cells"),
    (13, ["--glob", "t*.png"], "--glob 't*.png': 13 files, the grid has 12 cells (more files than grid cells"),
    (12, ["--glob", "*.tif"], "no files match, the grid has 12 cells"),
])
def test_import_grid_file_count_mismatch(tmp_path, files, args, expect):
    src = make_tile_dir(tmp_path / "tiles", files)
    out = tmp_path / "log"
    res = run("import-tiles", src, out, "--pixel-size", 0.001, "--grid", "4x3", "--step", 10, *args)
    assert res.exit_code == 2, res.output
    line = one_error_line(res)
    assert line.startswith(f"mosaicmap: error: {src}: ") and expect in line, line
    assert not out.exists()


@pytest.mark.parametrize("args, where, expect", [
    (["{dir}"], "{dir}", "is a folder: give its TileConfiguration file, or --grid"),
    (["{dir}/t01.png", "--grid", "4x3", "--step", "10"], "{dir}/t01.png", "with --grid, give the folder"),
    (["{dir}", "--grid", "4x3"], "--grid", "either --step PX[,PY] or --overlap"),
    (["{dir}", "--grid", "4x3", "--step", "10", "--overlap", "0.1"], "--grid", "either --step"),
    (["{dir}", "--grid", "4by3", "--step", "10"], "--grid", "expected COLUMNSxROWS"),
    (["{dir}", "--grid", "4x0", "--step", "10"], "--grid", "expected COLUMNSxROWS"),
    (["{dir}", "--grid", "4x3", "--overlap", "10"], "--overlap", "a fraction in [0, 1)"),
    (["{dir}", "--grid", "4x3", "--step", "10,-2"], "--step", "must be positive"),
    (["{dir}", "--grid", "4x3", "--step", "ten"], "--step", "expected a number"),
    (["{dir}", "--grid", "4x3", "--step", "10", "--pattern", "t.png"], "--pattern", "exactly one tile index field"),
    (["{dir}", "--grid", "4x3", "--step", "10", "--pattern", "t{i}.png", "--glob", "*"], "--pattern", "not both"),
    (["{dir}/TileConfiguration.txt", "--order", "snake-rows"], "--order", "only with --grid"),
    (["{dir}/TileConfiguration.txt", "--step", "10"], "--step", "only with --grid"),
])
def test_import_grid_usage_errors(tmp_path, args, where, expect):
    src = make_tile_dir(tmp_path / "tiles", 12)
    (src / "TileConfiguration.txt").write_text("t01.png; ; (0, 0)\nt02.png; ; (10, 0)\n")
    args = [a.replace("{dir}", str(src)) for a in args]
    out = tmp_path / "log"
    res = run("import-tiles", args[0], out, "--pixel-size", 0.001, *args[1:])
    assert res.exit_code == 2, res.output
    line = one_error_line(res)
    assert line.startswith(f"mosaicmap: error: {where.replace('{dir}', str(src))}: ") and expect in line, line
    assert not out.exists()


# --- TileConfiguration dialects and --truth ----------------------------------------------------


def test_tile_configuration_without_dim_line(tmp_path):
    src = make_tile_dir(tmp_path / "tiles", 3)
    cfg = src / "TileConfiguration.txt"
    cfg.write_text("# no dim line: 2-D\nt01.png; ; (0.0, 0.0)\nt02.png;;(17,0)\n\nt03.png; ; (0.0, 13.5)\n")
    assert read_tile_configuration(cfg) == [("t01.png", 0.0, 0.0), ("t02.png", 17.0, 0.0), ("t03.png", 0.0, 13.5)]
    res = run("import-tiles", cfg, tmp_path / "log", "--pixel-size", 0.001, "-q")
    assert res.exit_code == 0, res.output
    np.testing.assert_allclose(tile_positions_from_poses(read_drive_log(tmp_path / "log").odometry, (TILE_H, TILE_W), 0.001),
                               [[0, 0], [17, 0], [0, 13.5]], atol=1e-9)
    # a dim line after the tiles is fine when it says 2; any other dim, or 3-D positions, is refused
    cfg.write_text("t01.png; ; (0.0, 0.0)\nt02.png; ; (17, 0)\ndim = 2\n")
    assert len(read_tile_configuration(cfg)) == 2
    cfg.write_text("dim = 3\nt01.png; ; (0.0, 0.0, 0.0)\n")
    with pytest.raises(BadInput, match=r"TileConfiguration.txt:1: dim = 3"):
        read_tile_configuration(cfg)
    cfg.write_text("t01.png; ; (0.0, 0.0, 0.0)\nt02.png; ; (17, 0, 0)\n")
    res = run("import-tiles", cfg, tmp_path / "log2", "--pixel-size", 0.001)
    assert res.exit_code == 2
    assert f"{cfg}:1: 3-D position" in one_error_line(res)


def test_import_tiles_truth(tmp_path):
    src = make_tile_dir(tmp_path / "tiles", 6)
    truth_pos = {f"t{i:02d}.png": (c * STEP_X + 0.3 * i, r * STEP_Y - 0.2 * i)
                 for i, (c, r) in enumerate(grid_cells(3, 2, "snake-rows", "top-left"), start=1)}
    truth = tmp_path / "sim" / "TileConfiguration.truth.txt"  # another folder: tiles matched by file name
    truth.parent.mkdir()
    truth.write_text("dim = 2\n" + "".join(f"{n}; ; ({x!r}, {y!r})\n" for n, (x, y) in reversed(truth_pos.items())))
    out = tmp_path / "log"
    m = 0.002
    res = run("import-tiles", src, out, "--pixel-size", m, "--grid", "3x2", "--order", "snake-rows", "--step",
              f"{STEP_X},{STEP_Y}", "--truth", truth, "--report", tmp_path / "r.json", "-q")
    assert res.exit_code == 0, res.output
    assert "ground truth (RMS offset" in res.output
    lg = read_drive_log(out)
    gt = read_pose_csv(out / "ground_truth.csv")
    np.testing.assert_array_equal(gt[:, 0], lg.frame_t)  # one row per frame, the odometry's convention
    np.testing.assert_allclose(tile_positions_from_poses(gt, (TILE_H, TILE_W), m), list(truth_pos.values()), atol=1e-9)
    assert np.all(gt[:, 3] == 0)
    assert out / "ground_truth.csv" not in lg.files()  # never an input of the build
    rep = json.loads((tmp_path / "r.json").read_text())
    d = np.array(list(truth_pos.values())) - expected_positions([[1, 2, 3], [6, 5, 4]])  # 3 x 2 snake from top left
    assert rep["ground_truth"] == "ground_truth.csv"
    assert rep["truth_rms_offset_px"] == pytest.approx(float(np.sqrt(np.mean(np.sum(d**2, axis=1)))))
    # the same with a TileConfiguration as input
    cfg = src / "TileConfiguration.txt"
    cfg.write_text("".join(f"t{i:02d}.png; ; ({10 * i}, 0)\n" for i in range(1, 7)))
    res = run("import-tiles", cfg, tmp_path / "log2", "--pixel-size", m, "--truth", truth, "-q")
    assert res.exit_code == 0, res.output
    gt2 = read_pose_csv(tmp_path / "log2" / "ground_truth.csv")
    np.testing.assert_allclose(gt2, gt, atol=1e-12)
    # a truth without a tile, or with another tile, is bad input
    truth.write_text("".join(f"{n}; ; ({x!r}, {y!r})\n" for n, (x, y) in list(truth_pos.items())[:5]))
    res = run("import-tiles", cfg, tmp_path / "log3", "--pixel-size", m, "--truth", truth)
    assert res.exit_code == 2
    assert f"{truth}: has no position for tile 't06.png' (1 of 6 tiles missing)" in one_error_line(res)
    truth.write_text("".join(f"{n}; ; ({x!r}, {y!r})\n" for n, (x, y) in truth_pos.items()) + "t99.png; ; (0, 0)\n")
    res = run("import-tiles", cfg, tmp_path / "log3", "--pixel-size", m, "--truth", truth)
    assert res.exit_code == 2 and "lists tile 't99.png'" in one_error_line(res)
    assert not (tmp_path / "log3").exists()


# --- the real brain-section grid (../shared/data/real/wsi_brain_16bit_9x7) -------------------


@pytest.mark.realdata
def test_real_brain_grid_matches_its_tile_configuration(tmp_path):
    d = REAL / "wsi_brain_16bit_9x7"
    if not d.exists():
        pytest.skip(f"real data {d} absent (../shared is not checked out beside the repository)")
    out = tmp_path / "brain"
    m = 0.001
    res = run("import-tiles", d, out, "--pixel-size", m, "--grid", "9x7", "--order", "snake-rows",
              "--first", "top-right", "--step", 460, "--glob", "C3-BrainSection*.tif", "-q")
    assert res.exit_code == 0, res.output
    lg = read_drive_log(out)
    assert lg.frame_images == [f"images/C3-BrainSection{i:04d}.tif" for i in range(1, 64)]
    xy = tile_positions_from_poses(lg.odometry, (512, 512), m)
    pos = {Path(n).name: p for n, p in zip(lg.frame_images, xy)}
    ref = read_tile_configuration(d / "TileConfiguration.txt")
    assert len(ref) == 54
    for name, x, y in ref:  # exactly the nominal positions of its TileConfiguration.txt
        assert pos[name].tolist() == pytest.approx([x, y], abs=1e-9), name
    # the 7th row, which the file omits: 0055 at the right, 0063 at the left (SOURCE.md)
    assert pos["C3-BrainSection0055.tif"].tolist() == pytest.approx([3680, 2760], abs=1e-9)
    assert pos["C3-BrainSection0063.tif"].tolist() == pytest.approx([0, 2760], abs=1e-9)
    # the same with a pattern and the overlap instead of the step (512 x (1 - 0.1015625) = 460)
    res = run("import-tiles", d, tmp_path / "brain2", "--pixel-size", m, "--grid", "9x7", "--order", "snake-rows",
              "--first", "top-right", "--overlap", 52 / 512, "--pattern", "C3-BrainSection{i:04d}.tif", "-q")
    assert res.exit_code == 0, res.output
    lg2 = read_drive_log(tmp_path / "brain2")
    assert lg2.frame_images == lg.frame_images
    np.testing.assert_allclose(lg2.odometry, lg.odometry, atol=1e-12)
