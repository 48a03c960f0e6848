"""The tile-grid simulator (`mosaicmap simulate tiles`): sub-pixel truth, layout, options, CLI."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from pipeline.cli import cli
from pipeline.importers.tiles import read_tile_configuration
from pipeline.simulate.tiles import LANCZOS_A, cut_tile, grid_layout, shift_kernel

SMALL = ["--grid", "3x2", "--tile", "96", "--overlap", "0.25", "--stage-error", "3", "--quiet"]


def run(args: list[str]):
    return CliRunner().invoke(cli, ["simulate", "tiles", *args])


def simulate(out: Path, *args: str) -> Path:
    r = run([str(out), *SMALL, *args])
    assert r.exit_code == 0, r.output
    return out


def tiles(d: Path) -> list[np.ndarray]:
    files = [n for n, _, _ in read_tile_configuration(d / "TileConfiguration.txt")]
    return [cv2.imread(str(d / f), cv2.IMREAD_UNCHANGED) for f in files]


def equivalent_shift(diff: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Least-squares (dx, dy) such that diff ~ grad(ref) . (dx, dy): the shift a difference implies."""
    gy, gx = np.gradient(ref.astype(np.float64))
    A = np.stack([gx.ravel(), gy.ravel()], axis=1)
    return np.linalg.lstsq(A, diff.astype(np.float64).ravel(), rcond=None)[0]


# --- sub-pixel cutting ------------------------------------------------------------------------


def test_shift_kernel_is_a_unit_impulse_at_whole_pixels_and_sums_to_one():
    k = shift_kernel(0.0)
    assert len(k) == 2 * LANCZOS_A and k[LANCZOS_A - 1] == pytest.approx(1.0) and np.abs(k).sum() == pytest.approx(1.0)
    assert shift_kernel(0.37).sum() == pytest.approx(1.0)


def test_cut_tile_matches_an_exact_fourier_shift():
    """On a periodic texture band-limited like the floor's (Gaussian sigma 0.7 px) the cut at a
    sub-pixel position equals the exact Fourier shift to far below 0.01 px."""
    rng = np.random.default_rng(3)
    n = 128
    f = np.fft.fftfreq(n)
    fx, fy = np.meshgrid(f, f)
    spec = np.fft.fft2(rng.standard_normal((n, n))) * np.exp(-2 * np.pi**2 * 0.7**2 * (fx**2 + fy**2))
    tex = np.real(np.fft.ifft2(spec))
    tex = (tex / tex.std() * 32.0).astype(np.float32)
    pad = LANCZOS_A + 2
    padded = np.pad(tex, pad, mode="wrap")
    worst = 0.0
    for _ in range(8):
        dx, dy = rng.uniform(-3, 3, 2)
        exact = np.real(np.fft.ifft2(spec * np.exp(2j * np.pi * (fx * dx + fy * dy)))) / np.real(
            np.fft.ifft2(spec)).std() * 32.0
        # tile pixel (u, v) <- texture (u + dx, v + dy); the tile spans the whole period
        cut = cut_tile(padded, pad + dx, pad + dy, (n - 8, n - 8))
        ref = exact[: n - 8, : n - 8]
        worst = max(worst, float(np.abs(equivalent_shift(cut - ref, ref)).max()))
    assert worst < 1e-3


# --- the simulated grid -----------------------------------------------------------------------


def test_grid_files_positions_and_determinism(tmp_path):
    a = simulate(tmp_path / "a", "--seed", "4")
    b = simulate(tmp_path / "b", "--seed", "4")
    c = simulate(tmp_path / "c", "--seed", "5")
    names = sorted(p.name for p in a.iterdir())
    assert names == ["TileConfiguration.truth.txt", "TileConfiguration.txt", "grid.json"] + [
        f"tile_{i:03d}.tif" for i in range(6)]
    for n in names:
        assert (a / n).read_bytes() == (b / n).read_bytes(), n
    assert (a / "tile_000.tif").read_bytes() != (c / "tile_000.tif").read_bytes()

    meta = json.loads((a / "grid.json").read_text())
    assert meta["step_px"] == [72, 72] and meta["overlap_px"] == [24, 24] and meta["cols"] == 3
    nominal = read_tile_configuration(a / "TileConfiguration.txt")
    truth = read_tile_configuration(a / "TileConfiguration.truth.txt")
    assert [t[0] for t in nominal] == [t[0] for t in truth] == [f"tile_{i:03d}.tif" for i in range(6)]
    assert [(x, y) for _, x, y in nominal] == [(c * 72.0, r * 72.0) for r in range(2) for c in range(3)]
    err = np.array([(tx - nx, ty - ny) for (_, nx, ny), (_, tx, ty) in zip(nominal, truth)])
    assert np.abs(err).max() <= 3.0 and np.abs(err).max() > 0.5 and np.any(err % 1 != 0)
    for t, (_, tx, ty) in zip(meta["tiles"], truth):
        assert t["truth"] == pytest.approx([tx, ty], abs=1e-4)
    imgs = tiles(a)
    assert all(im.dtype == np.uint8 and im.shape == (96, 96) for im in imgs)


def test_truth_is_exact_in_the_overlap_of_neighbours(tmp_path):
    """Without noise and gain, tile b's overlap is tile a resampled at the true offset: the
    residual shift is far below 0.01 px (and a 0.05 px error in the offset is seen)."""
    size = 128
    d = simulate(tmp_path / "g", "--tile", str(size), "--overlap", "0.5", "--noise", "0", "--gain", "0",
                 "--bits", "16", "--stage-error", "6")
    truth = np.array([(x, y) for _, x, y in read_tile_configuration(d / "TileConfiguration.truth.txt")])
    imgs = [im.astype(np.float32) / 257.0 for im in tiles(d)]

    def span(off: float) -> tuple[int, int]:
        """Tile b pixels u whose tile a position u + off keeps the kernel's support inside tile a."""
        start = max(0, int(np.ceil(LANCZOS_A - off)))
        end = min(size, int(np.floor(size - LANCZOS_A - 1 - off)) + 1)
        return start, end - start

    for a, b in ((0, 1), (1, 2), (0, 3), (2, 5)):
        off = truth[b] - truth[a]  # tile b pixel (u, v) shows tile a pixel (u, v) + off
        (u0, w), (v0, h) = span(off[0]), span(off[1])
        assert w >= 20 and h >= 20
        ref = imgs[b][v0 : v0 + h, u0 : u0 + w]
        for error in (0.0, 0.05):
            res = cut_tile(imgs[a], u0 + off[0] + error, v0 + off[1], (h, w))
            s = equivalent_shift(ref - res, res)
            if error == 0.0:
                assert np.abs(s).max() < 0.01, (a, b, s)
            else:
                assert s[0] == pytest.approx(-0.05, abs=0.01), (a, b, s)


def test_snake_order_16_bit_range_blank_tiles_and_hot_pixels(tmp_path):
    d = simulate(tmp_path / "g", "--order", "snake", "--bits", "16", "--value-range", "700,2011",
                 "--blank-tiles", "1", "--blank-count", "1", "--hot-pixels", "3", "--noise", "2")
    assert grid_layout(3, 2, "snake") == [(0, 0), (1, 0), (2, 0), (2, 1), (1, 1), (0, 1)]
    meta = json.loads((d / "grid.json").read_text())
    assert [(t["col"], t["row"]) for t in meta["tiles"]] == grid_layout(3, 2, "snake")
    nominal = read_tile_configuration(d / "TileConfiguration.txt")
    assert [(x, y) for _, x, y in nominal][3:] == [(144.0, 72.0), (72.0, 72.0), (0.0, 72.0)]
    assert 1 in meta["blank_tiles"] and len(meta["blank_tiles"]) == 2
    hot = [tuple(p) for p in meta["hot_pixel_xy"]]
    assert len(hot) == 3
    for i, im in enumerate(tiles(d)):
        assert im.dtype == np.uint16
        for x, y in hot:
            assert im[y, x] == 65535
        body = np.delete(im.ravel(), [y * 96 + x for x, y in hot])
        assert body.min() >= 700 and body.max() <= 2011
        if i in meta["blank_tiles"]:
            # flat background (16 grey levels x gain) plus noise of 2 grey levels (5.14 counts each)
            assert body.std() == pytest.approx(2 * 1311 / 255, rel=0.15)
        else:
            assert body.std() > 40


def test_import_tiles_takes_the_simulated_grid(tmp_path):
    d = simulate(tmp_path / "g")
    r = CliRunner().invoke(cli, ["import-tiles", str(d / "TileConfiguration.txt"), str(tmp_path / "log"),
                                 "--pixel-size", "0.001", "--quiet"])
    assert r.exit_code == 0, r.output
    assert len((tmp_path / "log" / "frames.csv").read_text().strip().splitlines()) == 7


@pytest.mark.parametrize("args, needle", [
    (["--grid", "5"], "--grid"),
    (["--grid", "1x1"], "--grid"),
    (["--tile", "8"], "--tile"),
    (["--tile", "big"], "--tile"),
    (["--overlap", "0.95"], "--overlap"),
    (["--stage-error", "-1"], "--stage-error"),
    (["--order", "zigzag"], "--order"),
    (["--bits", "12"], "--bits"),
    (["--value-range", "900,300"], "--value-range"),
    (["--value-range", "a,b"], "--value-range"),
    (["--bits", "8", "--value-range", "0,1000"], "--value-range"),
    (["--blank-tiles", "99"], "--blank-tiles"),
    (["--blank-count", "7"], "--blank-count"),
    (["--hot-pixels", "-2"], "--hot-pixels"),
    (["--noise", "nan"], "--noise"),
    (["--gain", "1.5"], "--gain"),
    (["--seed", "-1"], "--seed"),
    (["--grid", "400x400", "--tile", "1024"], "MPix"),
])
def test_bad_options_are_usage_errors_without_traceback(tmp_path, args, needle):
    r = run([str(tmp_path / "out"), *SMALL, *args])
    assert r.exit_code == 2, r.output
    assert "Traceback" not in r.output and needle in r.output
    assert not (tmp_path / "out").exists()


def test_refuses_a_non_empty_output_folder(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    r = run([str(out), *SMALL])
    assert r.exit_code == 2 and "not an empty directory" in r.output
    assert (out / "keep.txt").read_text() == "mine"


def test_config_table_sets_the_defaults(tmp_path):
    cfg = tmp_path / "c.toml"
    cfg.write_text("[simulate.tiles]\ngrid = [2, 2]\ntile_size = [64, 48]\nbits = 16\nvalue_range = [700, 2011]\n")
    r = run([str(tmp_path / "g"), "--config", str(cfg), "--quiet"])
    assert r.exit_code == 0, r.output
    imgs = tiles(tmp_path / "g")
    assert len(imgs) == 4 and all(im.shape == (48, 64) and im.dtype == np.uint16 for im in imgs)
    cfg.write_text("[simulate.tiles]\ngrid = [0, 2]\n")
    r = run([str(tmp_path / "h"), "--config", str(cfg), "--quiet"])
    assert r.exit_code == 2 and "[simulate.tiles] grid: 0 is out of range" in r.output and "Traceback" not in r.output
