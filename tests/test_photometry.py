"""Photometry from the data: per-log normalization, clipping gates, noise, hot pixels, the
registrable flag (pipeline/images.py, pipeline/quality.py, pipeline/stages/ingest.py)."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import REPO, smooth_texture, write_small_log
from pipeline.stages.build import run_build
from pipeline.config import load_config
from pipeline.drivelog import CameraSpec, write_drive_log
from pipeline.errors import BadInput
from pipeline.framestore import FrameStore
from pipeline.images import IntensityMap, check_photometry_config, estimate_intensity_map, read_grey_coded, write_image
from pipeline.quality import (
    ExposureLevels,
    FrameAssessor,
    block_isotropy,
    exposure_levels,
    isotropy_from_gradients,
    noise_sigma,
    remove_hot_pixels,
    smoothed_gradients,
)

STEP16 = 255.0 / 65535.0  # one 16-bit code in grey levels


def _cfg() -> dict:
    return load_config()


def _write_log(path: Path, frames: list[np.ndarray], *, dtype=np.uint16) -> Path:
    """A drive log of already-rectified frames given as integer codes of ``dtype``."""
    (path / "images").mkdir(parents=True)
    names = []
    for i, f in enumerate(frames):
        names.append(f"images/{i:06d}.png")
        write_image(path / names[-1], np.clip(np.rint(f), 0, np.iinfo(dtype).max).astype(dtype))
    frame_t = 0.1 + 0.1 * np.arange(len(frames))
    t = np.arange(0.0, frame_t[-1] + 0.1001, 0.05)
    odo = np.stack([t, 0.5 * t, 0.1 * t, 0.0 * t], axis=1)
    write_drive_log(path, CameraSpec(pixel_size_m=0.0025), frame_t, names, odo, log_id=path.name)
    return path


# --- normalization -------------------------------------------------------------------------


def test_intensity_map_stretches_a_dim_log_to_the_working_range():
    p = _cfg()["ingest"]["photometry"]
    rng = np.random.default_rng(0)
    counts = rng.uniform(1000, 2310, 200_000)  # 16-bit data using 1/50 of the range
    imap, info = estimate_intensity_map(counts * STEP16, p, STEP16)
    assert info["applied"] and info["normalize"] == "auto"
    assert info["used_fraction"] == pytest.approx(1310 / 65535, rel=0.01)
    assert info["low_counts"] == pytest.approx(1000, abs=3) and info["high_counts"] == pytest.approx(2310, abs=3)
    # the used range maps to [0, 255] grey levels
    out = imap.apply(np.array([info["low_level"], info["high_level"]], np.float32))
    assert out == pytest.approx([0.0, 255.0], abs=1e-3)
    assert imap.gain == pytest.approx(255.0 / (1310 * STEP16), rel=0.01)
    assert info["gain"] == imap.gain and info["offset"] == imap.offset


def test_intensity_map_leaves_full_range_8bit_logs_unchanged():
    p = _cfg()["ingest"]["photometry"]
    rng = np.random.default_rng(1)
    grey = np.clip(rng.normal(120, 40, 100_000), 0, 255)  # a full-range 8-bit log
    imap, info = estimate_intensity_map(grey, p, 1.0)
    assert not info["applied"] and imap.identity
    img = rng.uniform(0, 255, (8, 8)).astype(np.float32)
    assert imap.apply(img) is img  # bit for bit: not even a copy
    # "always" stretches it too, "none" never touches even a dim log
    imap2, info2 = estimate_intensity_map(grey, {**p, "normalize": "always"}, 1.0)
    assert info2["applied"] and imap2.gain > 1.0
    imap3, info3 = estimate_intensity_map(np.full(100, 3.0) + np.arange(100) * 0.01, {**p, "normalize": "none"}, STEP16)
    assert imap3.identity and not info3["applied"] and info3["used_fraction"] < 0.01
    # a uniform log has no range to stretch
    imap4, info4 = estimate_intensity_map(np.full(1000, 3.0), p, STEP16)
    assert imap4.identity and "note" in info4


def test_intensity_map_clips_to_the_store_range_and_zeroes_invalid_pixels():
    imap = IntensityMap(gain=10.0, offset=-20.0)
    img = np.array([[1.0, 2.0], [30.0, 200.0]], np.float32)
    valid = np.array([[True, True], [True, False]])
    out = imap.apply(img, valid)
    assert out.tolist() == [[0.0, 0.0], [pytest.approx(255.99609375), 0.0]]


@pytest.mark.parametrize("key,value", [("normalize", "sometimes"), ("target_levels", [200.0, 100.0]),
                                       ("low_percentile", 99.95), ("auto_max_used_fraction", 0.0)])
def test_photometry_config_is_checked(key, value):
    p = _cfg()["ingest"]["photometry"]
    with pytest.raises(BadInput, match=r"config\[ingest\.photometry\."):
        check_photometry_config({**p, key: value})


def test_read_grey_coded_reports_the_code_step(tmp_path: Path):
    write_image(tmp_path / "a.png", np.full((4, 4), 3, np.uint8))
    write_image(tmp_path / "b.png", np.full((4, 4), 1000, np.uint16))
    a, sa = read_grey_coded(tmp_path / "a.png")
    b, sb = read_grey_coded(tmp_path / "b.png")
    assert sa == 1.0 and a[0, 0] == pytest.approx(3.0)
    assert sb == pytest.approx(STEP16) and b[0, 0] / sb == pytest.approx(1000, abs=1e-3)


# --- clipping gates ------------------------------------------------------------------------


def test_dim_unclipped_16bit_frame_is_not_underexposed():
    q = _cfg()["ingest"]["quality"]
    rng = np.random.default_rng(2)
    raw = (700 + 300 * rng.random((64, 64))) * STEP16  # 700..1000 counts: 1-1.5 % of full scale
    levels = exposure_levels(raw.ravel(), STEP16, q)
    assert (levels.dark, levels.saturated) == (0.0, 255.0)
    assert (levels.dark_source, levels.saturated_source) == ("bottom code", "top code")
    fig = FrameAssessor(np.ones((64, 64), bool), q, levels=levels).clean(raw.astype(np.float32))
    assert fig.dark_fraction == 0.0 and fig.saturated_fraction == 0.0


def test_8bit_clip_levels_match_the_old_fractions():
    """2 codes of margin: codes 0-2 dark and 253-255 saturated, as the 1 % / 99 % of full scale were."""
    lv = ExposureLevels(code_step=1.0, margin_codes=2.0)
    raw = np.arange(256, dtype=np.float32)
    sat, dark = lv.fractions(raw)
    assert sat * 256 == 3 and dark * 256 == 3


def test_12bit_data_in_16bit_files_saturate_at_their_pile_up():
    q = _cfg()["ingest"]["quality"]
    rng = np.random.default_rng(3)
    counts = np.minimum(rng.normal(2500, 900, 100_000), 4095).round()  # clips at 4095 (~4 % of pixels)
    levels = exposure_levels(counts * STEP16, STEP16, q)
    assert levels.saturated_source == "pile-up" and levels.saturated / STEP16 == pytest.approx(4095)
    assert levels.dark_source == "bottom code"
    sat, _ = levels.fractions((counts * STEP16).astype(np.float32))
    assert sat == pytest.approx(np.mean(counts >= 4093), abs=1e-6) and 0.02 < sat < 0.08
    # a black clip above code 0 (e.g. video-range data) is a dark pile-up
    low = np.maximum(rng.normal(40, 30, 100_000), 16).round()
    lv = exposure_levels(low, 1.0, q)
    assert lv.dark_source == "pile-up" and lv.dark == 16.0
    # a uniform scene has no clip level of its own
    assert exposure_levels(np.full(1000, 100.0), 1.0, q).saturated_source == "top code"


def test_12bit_log_rejects_the_frame_clipping_at_its_own_top(tmp_path: Path):
    rng = np.random.default_rng(4)
    frames = [np.clip(2000 + 600 * (smooth_texture(rng, (96, 128)) - 128) / 30, 0, 4095).round() for _ in range(6)]
    frames[3] = np.minimum(frames[3] * 2.0, 4095)  # a third of its pixels clip at 4095, 16x below 65535
    rep = run_build([_write_log(tmp_path / "log", frames)], tmp_path / "w", _cfg(), until="ingest", quiet=True)
    ing = rep["ingest"]
    (rej,) = ing["rejected"]
    assert rej["frame"] == 3 and rej["reason"].startswith("overexposed") and "4095, the pile-up" in rej["reason"]
    assert ing["logs"][0]["exposure"]["saturated_source"] == "pile-up"


# --- noise ---------------------------------------------------------------------------------


def test_noise_sigma_of_white_noise_and_of_a_noisy_texture():
    rng = np.random.default_rng(5)
    noise = rng.normal(0, 3.0, (256, 256)).astype(np.float32)
    assert noise_sigma(noise + 100) == pytest.approx(3.0, rel=0.05)
    tex = smooth_texture(rng, (256, 256))
    assert noise_sigma(tex + noise) == pytest.approx(3.0, rel=0.2)  # fine texture leaks in a little
    mask = np.zeros((256, 256), bool)
    mask[50:200, 60:220] = True
    img = tex + noise
    img[~mask] = 0.0  # outside the mask: nothing counts
    assert noise_sigma(img, mask) == pytest.approx(3.0, rel=0.2)
    assert noise_sigma(np.full((64, 64), 7.0, np.float32)) == 0.0


def test_texture_threshold_follows_the_noise():
    """Pure noise is not texture however strong it is; the floor holds for quiet frames."""
    q = _cfg()["ingest"]["quality"]
    rng = np.random.default_rng(6)
    valid = np.ones((160, 160), bool)
    a = FrameAssessor(valid, q)
    for sigma in (2.0, 10.0, 25.0):
        img = (128 + rng.normal(0, sigma, valid.shape)).astype(np.float32)
        fq = a(img, img)
        assert fq.noise_sigma == pytest.approx(sigma, rel=0.05)
        assert fq.textured_fraction == 0.0 and fq.prior_reason.startswith("low texture"), (sigma, fq)
    assert a.texture_threshold(2.0) == q["min_local_texture"]
    assert a.texture_threshold(20.0) == pytest.approx(q["noise_texture_factor"] * 400)
    # a textured frame under the same strong noise stays textured
    img = (smooth_texture(rng, valid.shape, std=40) + rng.normal(0, 10, valid.shape)).astype(np.float32)
    fq = a(img, img)
    assert fq.registrable and fq.textured_fraction > 0.9


# --- hot pixels ----------------------------------------------------------------------------


def test_hot_pixels_are_replaced_and_real_structure_is_not():
    rng = np.random.default_rng(7)
    base = (smooth_texture(rng, (128, 128), mean=4.0, std=0.5) + rng.normal(0, 0.05, (128, 128))).astype(np.float32)
    img = base.copy()
    img[10, 10] = 255.0  # a 16-bit 65535 in a frame near 1000 counts
    img[40, 40] = img[40, 41] = 200.0  # an adjacent pair
    img[90, 20] = 0.0  # a dead pixel
    # real signal: a bright 3x3 speck, a 1-pixel line, an edge corner
    img[60:63, 60:63] += 50.0
    img[100, 30:60] += 40.0
    img[110:, 110:] += 60.0
    sigma = noise_sigma(img)
    out, n = remove_hot_pixels(img, 20.0, max(sigma, STEP16))
    assert n == 4
    for y, x in ((10, 10), (40, 40), (40, 41), (90, 20)):
        assert abs(out[y, x] - base[y, x]) < 1.0
    changed = np.argwhere(out != img)
    assert sorted(map(tuple, changed)) == [(10, 10), (40, 40), (40, 41), (90, 20)]
    same, n0 = remove_hot_pixels(base, 20.0, max(noise_sigma(base), STEP16))
    assert n0 == 0 and same is base


def test_hot_pixels_neither_texture_nor_statistics(tmp_path: Path):
    """A dim 16-bit log with hot pixels at 65535 ingests like the same log without them."""
    rng = np.random.default_rng(8)
    clean = [1000 + (smooth_texture(rng, (96, 128)) - 128) * 10 + rng.normal(0, 5, (96, 128)) for _ in range(6)]
    clean[4] = np.full((96, 128), 1200.0) + rng.normal(0, 3, (96, 128))  # no texture
    hot = [f.copy() for f in clean]
    for f in hot:
        ys, xs = rng.integers(20, 76, 25), rng.integers(20, 108, 25)
        f[ys, xs] = 65535
    ra = run_build([_write_log(tmp_path / "a", clean)], tmp_path / "wa", _cfg(), until="ingest", quiet=True)
    rb = run_build([_write_log(tmp_path / "b", hot)], tmp_path / "wb", _cfg(), until="ingest", quiet=True)
    pa, pb = ra["ingest"]["logs"][0]["photometry"], rb["ingest"]["logs"][0]["photometry"]
    # 25 hot pixels per frame are 0.2 % of it: left in, the 99.9th percentile would be 65535
    assert pb["gain"] == pytest.approx(pa["gain"], rel=0.01) and pb["applied"]
    flagged = [[p["frame"] for p in r["ingest"]["placed_by_prior"]] for r in (ra, rb)]
    assert flagged == [[4], [4]]
    lb = FrameStore(tmp_path / "wb" / "ingest" / "frames.zarr").logs[0]
    la = FrameStore(tmp_path / "wa" / "ingest" / "frames.zarr").logs[0]
    cols = lb.quality_columns
    assert (lb.quality[:, cols.index("hot_pixels")] >= 20).all()  # (a few may land on each other)
    assert (la.quality[:, cols.index("hot_pixels")] == 0).all()
    t = cols.index("textured_fraction")
    assert np.abs(lb.quality[:, t] - la.quality[:, t]).max() < 0.01
    assert rb["ingest"]["logs"][0]["hot_pixels"] >= 6 * 20
    assert np.median(np.abs(lb.image(0) - la.image(0))[lb.valid]) < 0.01


# --- isotropy ------------------------------------------------------------------------------


def test_block_isotropy_keeps_blur_and_forgives_one_strong_edge():
    rng = np.random.default_rng(9)
    tex = smooth_texture(rng, (256, 256), std=10)
    w = np.ones(tex.shape, np.float32)
    for k, lo, hi in ((1, 0.85, 1.0), (5, 0.5, 0.65), (9, 0.28, 0.42)):
        gx, gy = smoothed_gradients(cv2.blur(tex, (k, 1)), 1.0)
        frame = isotropy_from_gradients(gx, gy, w)
        blocks = block_isotropy(gx, gy, w, w, 32)
        assert lo < frame < hi and abs(blocks - frame) < 0.05, (k, frame, blocks)
    edge = tex.copy()
    edge[:, 128:] += 150.0  # a tissue border: one strong straight edge
    gx, gy = smoothed_gradients(edge, 1.0)
    assert isotropy_from_gradients(gx, gy, w) < 0.4 < block_isotropy(gx, gy, w, w, 32)


# --- the registrable flag, warnings, all rejected --------------------------------------------


def test_registrable_accessor_without_the_column(tmp_path: Path):
    """Stores written before the column existed read as all registrable."""
    log_dir = write_small_log(tmp_path / "log")
    run_build([log_dir], tmp_path / "w", _cfg(), until="ingest", quiet=True)
    import zarr

    g = zarr.open_group(str(tmp_path / "w" / "ingest" / "frames.zarr" / "log000"), mode="r+")
    q = g["quality"][...]
    cols = list(g["quality"].attrs["columns"])
    del g["quality"]
    a = g.create_array("quality", data=q[:, :6])
    a.attrs["columns"] = cols[:6]
    lf = FrameStore(tmp_path / "w" / "ingest" / "frames.zarr").logs[0]
    assert lf.registrable.dtype == bool and lf.registrable.all() and lf.registrable.shape == (8,)


def test_most_of_a_log_flagged_warns_naming_the_knob(tmp_path: Path, caplog):
    rng = np.random.default_rng(10)
    frames = [np.clip(smooth_texture(rng, (64, 96)), 0, 255) for _ in range(2)]
    frames += [np.full((64, 96), 100.0) + rng.normal(0, 1, (64, 96)) for _ in range(4)]
    log_dir = _write_log(tmp_path / "log", [np.clip(f, 0, 255).round() for f in frames], dtype=np.uint8)
    with caplog.at_level(logging.WARNING, logger="pipeline.stages.ingest"):
        rep = run_build([log_dir], tmp_path / "w", _cfg(), until="ingest", quiet=True)
    (w,) = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert "4 of 6 frames placed by the prior" in w and "low texture gate" in w and "min_textured_fraction" in w
    assert rep["ingest"]["logs"][0]["warnings"] == [w]
    assert rep["ingest"]["frames_registrable"] == 2 and rep["ingest"]["frames_placed_by_prior"] == 4


def test_nothing_registrable_is_bad_input_without_traceback(tmp_path: Path):
    rng = np.random.default_rng(11)
    frames = [np.full((64, 96), 90.0) + rng.normal(0, 0.5, (64, 96)) for _ in range(5)]
    frames[2] = np.minimum(smooth_texture(rng, (64, 96)) * 3.0, 255)  # overexposed
    log_dir = _write_log(tmp_path / "log", [np.clip(f, 0, 255).round() for f in frames], dtype=np.uint8)
    r = subprocess.run([sys.executable, "-m", "pipeline.cli", "build", str(log_dir), "-w", str(tmp_path / "w"),
                        "--until", "optimize", "--quiet"], cwd=REPO, capture_output=True, text=True)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    (line,) = [ln for ln in r.stderr.splitlines() if ln.startswith("mosaicmap: error:")]
    assert "no registrable frame" in line and "4 of 5 frames placed by the prior" in line
    assert "[ingest.quality] min_textured_fraction" in line
    assert not (tmp_path / "w" / "ingest").exists() and not (tmp_path / "w" / "register").exists()


# --- 16-bit at 1/50 of the range == its 8-bit stretched copy --------------------------------


def test_dim_16bit_log_ingests_like_its_8bit_stretched_copy(tmp_path: Path):
    """Same scene, 16-bit codes 1000..2310 (1/50 of the range) vs 8-bit 0..255.

    Tolerance: 0.65 grey levels = the 8-bit copy's rounding (0.5) + the 16-bit data's
    (0.5 x 255 / 1310 = 0.1) + the store's 1/256 step; the 16-bit log's used range is exactly
    [1000, 2310] (1 % of the scene sits at each end), so its map is exact.
    """
    rng = np.random.default_rng(12)
    tex = [smooth_texture(rng, (96, 128)) for _ in range(8)]
    lo, hi = np.percentile(np.stack(tex), [1, 99])
    scenes = [np.clip((t - lo) / (hi - lo), 0.0, 1.0) for t in tex]
    scenes[5] = 0.5 + 0.002 * (scenes[5] - 0.5)  # no texture: placed by the prior in both
    a = _write_log(tmp_path / "a16", [1000 + np.round(s * 1310) for s in scenes], dtype=np.uint16)
    b = _write_log(tmp_path / "b8", [np.round(s * 255) for s in scenes], dtype=np.uint8)
    cfg = _cfg()
    ra = run_build([a], tmp_path / "wa", cfg, until="ingest", quiet=True)["ingest"]
    rb = run_build([b], tmp_path / "wb", cfg, until="ingest", quiet=True)["ingest"]
    pa, pb = ra["logs"][0]["photometry"], rb["logs"][0]["photometry"]
    assert pa["applied"] and not pb["applied"]
    assert (pa["low_counts"], pa["high_counts"]) == (pytest.approx(1000, abs=0.01), pytest.approx(2310, abs=0.01))
    assert ra["rejected"] == rb["rejected"] == []
    assert [p["frame"] for p in ra["placed_by_prior"]] == [p["frame"] for p in rb["placed_by_prior"]] == [5]
    fa = FrameStore(tmp_path / "wa" / "ingest" / "frames.zarr").logs[0]
    fb = FrameStore(tmp_path / "wb" / "ingest" / "frames.zarr").logs[0]
    assert fa.count == fb.count == 8 and (fa.registrable == fb.registrable).all()
    assert (fa.valid == fb.valid).all()
    for i in range(8):
        d = np.abs(fa.image(i) - fb.image(i))[fa.valid]
        assert d.max() <= 0.65, (i, d.max())  # measured: 0.59 max, 0.25 mean
    json.dumps(ra)


# --- real data: the 16-bit brain tiles ------------------------------------------------------

BRAIN = REPO.parent / "shared" / "data" / "real" / "wsi_brain_16bit_9x7"
# Tiles without tissue (SOURCE.md names 0001, 0037, 0054; the others measured: no pixel of the
# flat-corrected, stretched tile above 60 grey levels after a 3-pixel Gaussian, but 0007's 0.3 %).
BRAIN_BACKGROUND = ["0001", "0002", "0007", "0008", "0009", "0010", "0018", "0027", "0037", "0044", "0047",
                    "0048", "0053", "0054"]
# Tiles at least half tissue.
BRAIN_TISSUE = ["0012", "0013", "0014", "0015", "0016", "0020", "0021", "0022", "0023", "0024", "0025", "0030",
                "0031", "0032", "0033", "0034", "0035", "0039", "0040", "0041", "0042", "0045"]


@pytest.mark.realdata
def test_brain_tiles_ingest_with_the_defaults(tmp_path: Path):
    if not BRAIN.exists():
        pytest.skip(f"real data {BRAIN} absent (../shared not checked out beside the repo)")
    log_dir = tmp_path / "log"
    r = subprocess.run([sys.executable, "-m", "pipeline.cli", "import-tiles", str(BRAIN / "TileConfiguration.txt"),
                        str(log_dir), "--pixel-size", "0.001", "--quiet"], cwd=REPO, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    ing = run_build([log_dir], tmp_path / "w", _cfg(), until="ingest", quiet=True)["ingest"]
    tile = lambda e: Path(e["image"]).stem[-4:]  # noqa: E731
    assert ing["frames_total"] == 54
    # nothing rejected: in particular none under- or overexposed
    assert ing["rejected"] == [], ing["rejected"]
    assert ing["frames_accepted"] == 54
    placed = {tile(e): e["reason"] for e in ing["placed_by_prior"]}
    for t in BRAIN_BACKGROUND:
        assert placed.get(t, "").startswith("low texture"), (t, placed.get(t))
    assert not set(BRAIN_TISSUE) & set(placed), {t: placed[t] for t in set(BRAIN_TISSUE) & set(placed)}
    lg = ing["logs"][0]
    ph = lg["photometry"]
    assert ph["applied"] and 600 < ph["low_counts"] < 1200 and 8000 < ph["high_counts"] < 12000, ph
    assert lg["exposure"]["saturated_source"] == "top code" and lg["exposure"]["dark_source"] == "bottom code"
    assert 0.05 < lg["noise_sigma"] < 2.0  # working grey levels
    lf = FrameStore(tmp_path / "w" / "ingest" / "frames.zarr").logs[0]
    assert int((~lf.registrable).sum()) == len(placed) == ing["frames_placed_by_prior"]
    assert int(lf.registrable.sum()) == ing["frames_registrable"] >= len(BRAIN_TISSUE)


def test_writers_of_the_first_six_columns_store_registrable_frames(tmp_path: Path):
    from pipeline.framestore import LogFramesWriter, create_store

    root = create_store(tmp_path / "frames.zarr", 0.0025)
    w = LogFramesWriter(root, 0, {"log_id": "x"}, np.ones((8, 8), bool))
    for i in range(3):
        w.append(np.full((8, 8), 10.0, np.float32), float(i), np.zeros(3), i, (0.0,) * 6)
    w.close()
    root.attrs["logs"] = [{"log_id": "x"}]
    lf = FrameStore(tmp_path / "frames.zarr").logs[0]
    assert lf.registrable.tolist() == [True] * 3 and lf.quality.shape == (3, 9)
