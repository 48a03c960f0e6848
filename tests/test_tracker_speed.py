"""The tracker's speed machinery: tiles read ahead of the fixes (TileCache.warm,
FloorTracker.prefetch, Session look-ahead), the camera mask's template exclusion kept between
frames, the search radius, and the replay that times `mosaicmap track`
(pipeline.track_replay)."""

from __future__ import annotations

import numpy as np
import pytest

from mapstore.grid import MapGrid
from pipeline.testing.synthmap import periodic_texture
from pipeline.track_replay import ReplayRun, frame_blocks, replay, speed_figures, speed_line
from tracker.floor import FloorTracker, FloorTrackerParams, half_frame, select_templates, template_exclusion
from tracker.session import Session, SessionParams
from tracker.tiles import TileCache
from test_tracker_session import FRAME, PX, drive, frame_at, odometry_of


@pytest.fixture(scope="module")
def world():
    big = np.clip(np.rint(periodic_texture(21, 2048)[:1024]), 1, 255).astype(np.uint8)  # 5.12 x 2.56 m
    grid = MapGrid(0.0, (big.shape[0] - 1) * PX, PX, big.shape[1], big.shape[0])
    return big, grid


def counting_tiles(a: np.ndarray, tile_px: int = 128, capacity: int = 1024):
    reads: list[tuple[int, int]] = []

    def read(tr, tc):
        reads.append((tr, tc))
        return a[tr * tile_px : (tr + 1) * tile_px, tc * tile_px : (tc + 1) * tile_px]

    return TileCache(read, a.shape, tile_px, capacity=capacity, dtype=a.dtype), reads


def test_warm_reads_each_missing_tile_once_and_counts_apart():
    a = np.arange(100 * 90, dtype=np.int32).reshape(100, 90)
    tc, reads = counting_tiles(a, 32, capacity=6)
    assert tc.warm(-10, 40, 50, 200) == 4  # rows 0..39 -> tiles 0-1, cols 50..89 -> tiles 1-2; clipped
    assert sorted(reads) == [(0, 1), (0, 2), (1, 1), (1, 2)] and tc.reads_ahead == 4
    assert tc.hits == 0 and tc.misses == 0
    assert tc.warm(0, 40, 50, 90) == 0 and len(reads) == 4  # all cached: nothing read
    assert np.array_equal(tc.window(0, 40, 50, 90), a[0:40, 50:90]) and len(reads) == 4 and tc.misses == 0
    assert tc.warm(0, 100, 0, 90) == 6  # at most `capacity` tiles read by one call
    assert len(tc._tiles) <= 6
    assert tc.warm(200, 300, 0, 90) == 0  # beyond the raster
    tc.resize(2)
    assert len(tc._tiles) == 2 and tc.capacity == 2
    with pytest.raises(ValueError):
        tc.resize(0)


def test_session_grows_the_tile_cache_to_hold_the_map(world):
    m, grid = world
    tiles, _ = counting_tiles(m, capacity=16)
    Session(FloorTracker(tiles, grid, PX), None, SessionParams(cache_tiles=600))
    assert tiles.capacity == 600
    Session(FloorTracker(tiles, grid, PX), None, SessionParams(cache_tiles=10))  # never shrunk
    assert tiles.capacity == 600


def test_search_radius_is_the_reach_of_the_corner_template(world):
    m, grid = world
    tr = FloorTracker(TileCache(lambda r, c: None, m.shape, 256), grid, PX)
    assert tr.search_radius_px(np.array([0.02, 0.02, 0.01]), FRAME) == 36  # the +-2 cm prior
    assert tr.search_radius_px(np.array([1e-5, 1e-5, 0.0]), FRAME) == tr.p.min_radius_px
    assert tr.search_radius_px(np.array([1.0, 1.0, 0.0]), FRAME) == tr.p.max_radius_px


def test_template_exclusion_is_what_select_templates_derives_and_is_kept(world):
    m, grid = world
    rng = np.random.default_rng(2)
    frame = frame_at(m, grid, np.array([2.0, 1.2, 0.3]), rng)
    p = FloorTrackerParams()
    valid = np.ones(FRAME, bool)
    valid[:, :100] = False
    ex = template_exclusion(valid, p)
    assert ex.shape == (FRAME[0] // 2, FRAME[1] // 2) and ex[:, :50].all() and not ex[:, 60:].any()
    a = select_templates(frame, valid, p)
    b = select_templates(frame, None, p, small=half_frame(frame), exclusion=ex)
    assert all(np.array_equal(x, y) for x, y in zip(a[:2], b[:2])) and a[2] == b[2]
    tr = FloorTracker(TileCache(lambda r, c: None, m.shape, 256), grid, PX)
    e1 = tr._exclusion(valid)
    assert tr._exclusion(valid.copy()) is e1  # the same mask: kept
    valid[:, :100] = True  # changed in place: derived anew
    assert not tr._exclusion(valid).any()


def test_session_reads_tiles_ahead_so_fixes_never_wait_for_one(world):
    m, grid = world
    rng = np.random.default_rng(11)
    truth = drive(30, (1.0, 1.2, 0.1), step=(0.06, 0.0, 0.003))
    frames = [frame_at(m, grid, t, rng) for t in truth]
    motions = odometry_of(truth, rng)
    results = {}
    for look in (0, 128):
        tiles, reads = counting_tiles(m)
        ses = Session(FloorTracker(tiles, grid, PX), None, SessionParams(relative=False, look_ahead_px=look))
        ses.start(truth[0])
        steps = [ses.step(frames[0], None, None)] + [ses.step(f, None, mo) for f, mo in zip(frames[1:], motions)]
        results[look] = (steps, tiles, len(reads))
    steps0, tiles0, n0 = results[0]
    steps1, tiles1, n1 = results[128]
    assert all(st.ok for st in steps1) and [st.pose.tolist() for st in steps0] == [st.pose.tolist() for st in steps1]
    assert tiles0.misses > 0 and tiles1.misses == 0  # every tile a fix used was read ahead of it
    assert sum(st.prefetched for st in steps1) == tiles1.reads_ahead == n1 and steps1[0].prefetched > 0
    assert all(st.prefetched == 0 and st.prefetch_seconds == 0.0 for st in steps0)
    assert all(st.prior_sigma is not None and st.prior_sigma.shape == (3,) for st in steps1)
    assert np.allclose(steps1[0].prior_sigma, [0.02, 0.02, 0.02])  # the start sigma was given to the first fix


def test_frame_blocks_decode_in_order_within_the_budget():
    calls = []

    def load(i):
        calls.append(i)
        return np.full((2, 3), i, np.uint8)

    blocks = list(frame_blocks(load, range(3, 10), frame_bytes=6, block_bytes=18))
    assert [[int(f[0, 0]) for f in fr] for fr, _ in blocks] == [[3, 4, 5], [6, 7, 8], [9]]
    assert sorted(calls) == list(range(3, 10)) and all(s >= 0 for _, s in blocks)


class _FakeStep:
    def __init__(self, k):
        self.fix_seconds = 0.0 if k == 0 else 0.001 * k
        self.fix_cpu_seconds = 0.0005 * k
        self.prior_sigma = None if k == 0 else np.array([0.002, 0.002, 0.003])


class _FakeSession:
    def __init__(self):
        self.seen = []

    def step(self, frame, valid, motion):
        self.seen.append((int(frame[0, 0]), motion))
        return _FakeStep(len(self.seen) - 1)


def test_replay_and_speed_figures():
    ses = _FakeSession()
    frames = [np.full((4, 4), k, np.uint8) for k in range(5)]
    motions = [None] + [np.array([0.1, 0.0, 0.0])] * 4
    ticks = []
    run = replay(ses, [(frames[:2], 0.5), (frames[2:], 0.25)], None, motions, on_step=lambda: ticks.append(1))
    assert [s[0] for s in ses.seen] == [0, 1, 2, 3, 4] and ses.seen[0][1] is None and len(ticks) == 5
    assert run.decode_seconds == 0.75 and run.blocks == 2 and len(run.step_seconds) == 5
    assert np.isnan(run.prior_sigma[0]).all()
    sp = speed_figures(run, search_radius_px=lambda sig: 7)
    # fixes of 1, 2, 3, 4 ms wall (the first frame tried none), 0.5 .. 2 ms CPU
    assert sp["fixes"] == 4 and sp["wall"]["fixes_per_s"] == pytest.approx(4 / 0.010)
    assert sp["cpu"]["fixes_per_s"] == pytest.approx(4 / 0.005)
    lat = sp["wall"]["latency_ms"]
    assert lat["max"] == pytest.approx(4.0) and lat["p50"] == pytest.approx(2.5)
    assert sp["cpu"]["latency_ms"]["p50"] == pytest.approx(1.25) and sp["step"]["frames"] == 5
    assert sp["prior_sigma_median"] == pytest.approx([0.002, 0.002, 0.003]) and sp["search_radius_px"] == 7
    text = speed_line(sp)
    assert "400 fixes/s wall" in text and "CPU 800 fixes/s" in text and "search radius 7 px" in text
    assert speed_line(speed_figures(ReplayRun())) == "speed: no fixes tried"
