"""The tracking session (tracker.session) and relative mode (tracker.relative) on frames cut
from a known map, and `mosaicmap track` on a simulated map and a held-out log."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from mapstore.grid import MapGrid, se2_between, se2_compose
from pipeline.cli import cli
from pipeline.testing.synthmap import periodic_texture
from tracker.floor import FloorTracker
from tracker.relative import RelativeTracker, compose_covariance, frame_grid
from tracker.reloc import Relocalizer, build_index
from tracker.session import Session, SessionParams, summarize
from tracker.tiles import ArrayTiles
from conftest import invoke

PX = 0.0025
FRAME = (240, 320)


@pytest.fixture(scope="module")
def world():
    big = np.clip(np.rint(periodic_texture(21, 2048)[:1024]), 1, 255).astype(np.uint8)  # 5.12 x 2.56 m
    grid = MapGrid(0.0, (big.shape[0] - 1) * PX, PX, big.shape[1], big.shape[0])
    return big, grid


def frame_at(m, grid, pose, rng, noise=8.0):
    a = grid.frame_to_grid_affine(pose, FRAME, PX)
    f = cv2.warpAffine(m, a, FRAME[::-1], flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP).astype(np.float32)
    return np.clip(f + rng.normal(0, noise, f.shape), 0, 255).astype(np.uint8)


def drive(n: int, start, step=(0.05, 0.0, 0.004)) -> np.ndarray:
    """Ground-truth poses of a gently curving drive (world frame)."""
    out = [np.asarray(start, float)]
    for _ in range(n - 1):
        out.append(se2_compose(out[-1], np.asarray(step, float)))
    return np.array(out)


def odometry_of(truth: np.ndarray, rng, drift=0.01) -> np.ndarray:
    """Odometry motions with errors of ``drift`` x distance (vehicle frame)."""
    d = [se2_between(truth[k - 1], truth[k]) for k in range(1, len(truth))]
    return np.array([m + rng.normal(0, drift * np.hypot(m[0], m[1]), 3) * [1, 1, 0.5] for m in d])


def simulated_drive(world, n: int, seed: int, start=(1.2, 1.3, -0.4)):
    """A drive of ``n`` frames over ``world``: (truth poses, frames, odometry motions, tracker)."""
    m, grid = world
    rng = np.random.default_rng(seed)
    truth = drive(n, start)
    frames = [frame_at(m, grid, p, rng) for p in truth]
    return truth, frames, odometry_of(truth, rng), FloorTracker(ArrayTiles(m), grid, PX)


def run(session: Session, frames, motions, valid=None):
    steps = [session.step(frames[0], valid, None)]
    for k in range(1, len(frames)):
        steps.append(session.step(frames[k], valid, motions[k - 1]))
    return steps


def test_frame_grid_maps_frame_pixels_onto_themselves():
    g = frame_grid(FRAME, PX)
    a = g.frame_to_grid_affine(np.zeros(3), FRAME, PX)
    assert np.allclose(a, [[1, 0, 0], [0, 1, 0]])


def test_compose_covariance_matches_sampling():
    rng = np.random.default_rng(3)
    a, d = np.array([1.0, 2.0, 0.7]), np.array([0.3, -0.1, 0.05])
    ca, cd = np.diag([1e-4, 4e-4, 1e-3]), np.diag([2e-4, 1e-4, 5e-4])
    sa = a + rng.multivariate_normal(np.zeros(3), ca, 20000)
    sd = d + rng.multivariate_normal(np.zeros(3), cd, 20000)
    emp = np.cov(se2_compose(sa, sd).T)
    assert np.allclose(compose_covariance(a, ca, d, cd), emp, rtol=0.1, atol=2e-5)


def test_relative_step_measures_the_motion(world):
    m, grid = world
    rng = np.random.default_rng(4)
    rel = RelativeTracker(PX)
    errs = []
    for _ in range(10):
        p0 = np.array([rng.uniform(1, 4), rng.uniform(0.6, 2.0), rng.uniform(-3, 3)])
        motion = np.array([rng.uniform(0.03, 0.1), rng.uniform(-0.02, 0.02), rng.uniform(-0.03, 0.03)])
        f0, f1 = frame_at(m, grid, p0, rng), frame_at(m, grid, se2_compose(p0, motion), rng)
        fix = rel.step(f0, None, f1, None, motion + [0.004, -0.003, 0.004], np.array([0.01, 0.01, 0.01]))
        assert fix.ok, fix
        errs.append(np.hypot(*(fix.pose[:2] - motion[:2])) / PX)
    assert max(errs) < 0.2, errs


def test_session_tracks_a_drive_within_a_fraction_of_a_pixel(world):
    m, grid = world
    rng = np.random.default_rng(5)
    truth = drive(60, (0.8, 1.0, 0.1))
    frames = [frame_at(m, grid, p, rng) for p in truth]
    motions = odometry_of(truth, rng)
    ses = Session(FloorTracker(ArrayTiles(m), grid, PX))
    ses.start(truth[0] + [0.01, -0.01, 0.01])
    steps = run(ses, frames, motions)
    rep = summarize(steps, truth, PX)
    assert rep["ok_rate"] == 1.0 and rep["wrong_ok"] == 0
    assert rep["error_rms_px"] < 0.1 and rep["error_max_ok_px"] < 0.3
    assert rep["fixes_per_s"] > 0 and rep["latency_ms"]["p99"] >= rep["latency_ms"]["p50"]
    assert rep["modes"]["fix"] == 60 and rep["relocalizations"] == 0


def test_kidnapped_start_is_detected_and_relocalized(world):
    m, grid = world
    truth, frames, motions, tr = simulated_drive(world, 30, 6)
    reloc = Relocalizer(build_index(ArrayTiles(m), grid), tr)
    ses = Session(tr, reloc, SessionParams(lost_after=3))
    ses.start(truth[0] + [1.5, 0.4, 0.3])  # confident and 1.5 m off
    steps = run(ses, frames, motions)
    rep = summarize(steps, truth, PX)
    assert rep["wrong_ok"] == 0, [(s.index, s.status, s.mode) for s in steps]
    assert rep["relocalizations"] >= 1, [(s.index, s.status, s.mode, s.fix and s.fix.reasons) for s in steps]
    first = next(s.index for s in steps if s.mode == "reloc")
    assert first <= 5  # lost after 3 failed fixes, relocalized at once
    assert all(s.ok for s in steps[first:]), [(s.index, s.status) for s in steps[first:]]
    # no prior at all: relocalize on the first frame
    ses.start(None)
    steps = run(ses, frames[:5], motions[:4])
    assert steps[0].mode == "reloc" and summarize(steps, truth[:5], PX)["wrong_ok"] == 0


def test_low_texture_stretch_ends_lost_then_recovers(world):
    m, grid = world
    rng = np.random.default_rng(7)
    truth = drive(70, (0.7, 1.2, 0.0), step=(0.06, 0.0, 0.0))
    frames = [frame_at(m, grid, p, rng) for p in truth]
    for k in range(10, 50):  # 2.4 m of bare floor (or a covered lens)
        frames[k] = np.clip(128 + rng.normal(0, 2, FRAME), 0, 255).astype(np.uint8)
    motions = odometry_of(truth, rng, drift=0.02)
    tr = FloorTracker(ArrayTiles(m), grid, PX)
    ses = Session(tr, Relocalizer(build_index(ArrayTiles(m), grid), tr), SessionParams(lost_sigma_m=0.03))
    ses.start(truth[0])
    steps = run(ses, frames, motions)
    status = [s.status for s in steps]
    assert set(status[10:30]) <= {"low_texture", "lost"} and "lost" in status[10:50]
    # found again on the first textured frame: at the dead-reckoned pose or by relocalization
    assert steps[50].mode in ("fix", "reloc") and all(s.ok for s in steps[50:]), status[48:]
    rep = summarize(steps, truth, PX)
    assert rep["wrong_ok"] == 0 and rep["relocalizations"] <= 1


def test_off_the_map_the_session_goes_relative(world):
    m, grid = world
    rng = np.random.default_rng(8)
    half = m.copy()
    half[:, 1100:] = 0  # the map stops at x = 2.75 m
    truth = drive(50, (1.6, 1.3, 0.0), step=(0.05, 0.0, 0.0))  # to x = 4.05 m and back onto nothing
    frames = [frame_at(m, grid, p, rng) for p in truth]
    motions = odometry_of(truth, rng, drift=0.02)
    ses = Session(FloorTracker(ArrayTiles(half), grid, PX))
    ses.start(truth[0])
    steps = run(ses, frames, motions)
    rel = [s for s in steps if s.mode == "relative"]
    assert len(rel) >= 15 and all(s.status == "off_map" for s in rel)
    rep = summarize(steps, truth, PX)
    assert rep["wrong_ok"] == 0 and rep["relative"]["frames"] == len(rel)
    # frame-to-frame motion drifts far less than the 2 % odometry
    assert rep["relative"]["error_growth_per_m"] < 0.005, rep["relative"]
    # the reported uncertainty grows along the stretch
    assert rel[-1].sigma[0] > rel[0].sigma[0]


# --- the command ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    root = tmp_path_factory.mktemp("tracksite")
    day1, ops = root / "day1", root / "ops"
    for args in (("simulate", "floor", day1, "--area", "1.5x1.5", "--seed", "5", "--quiet"),
                 ("build", day1, "--map", root / "map", "-w", root / "w1", "--tag", "day1", "--quiet"),
                 ("keys", "new", root / "owner.key"),
                 ("export", root / "map", root / "day1.zip", "--sign", root / "owner.key", "--quiet"),
                 ("simulate", "floor", ops, "--world", day1, "--noise", "10",
                  "--illumination", "0.8", "--seed", "9", "--quiet")):
        r = invoke(*args)
        assert r.exit_code == 0, r.output
    return root


def test_cli_track_replays_a_held_out_log(site, tmp_path):
    rep_path, plot, poses = tmp_path / "t.json", tmp_path / "t.png", tmp_path / "poses.csv"
    r = invoke("track", site / "day1.zip", site / "ops", "--key", site / "owner.key.pub", "--report", rep_path,
               "--plot", plot, "--poses", poses,
               "--quiet")
    assert r.exit_code == 0, r.output
    rep = json.loads(rep_path.read_text())
    for key in ("fixes", "ok_rate", "error_rms_px", "error_max_ok_px", "wrong_ok", "fixes_per_s", "relocalizations"):
        assert key in rep
    assert rep["latency_ms"]["p50"] > 0 and rep["latency_ms"]["p99"] >= rep["latency_ms"]["p50"]
    assert rep["wrong_ok"] == 0 and rep["ok_rate"] > 0.9 and rep["error_rms_px"] < 0.2
    assert cv2.imread(str(plot)).shape[2] == 3
    lines = poses.read_text().splitlines()
    assert lines[0].startswith("t,x,y,theta,status,mode") and len(lines) == rep["fixes"] + 1
    assert "wrong ok" in r.output and "fixes/s" in r.output
    # the speed figures of the replay (pipeline.track_replay): the same as bench_tracker_speed.py prints
    sp = rep["speed"]
    assert sp["fixes"] == rep["fixes"] and sp["cpu"]["fixes_per_s"] > 0 and sp["wall"]["fixes_per_s"] > 0
    assert sp["wall"]["latency_ms"]["max"] >= sp["wall"]["latency_ms"]["p99"] >= sp["wall"]["latency_ms"]["p50"] > 0
    assert sp["step"]["frames"] == rep["fixes"] and sp["search_radius_px"] >= 3 and len(sp["prior_sigma_median"]) == 3
    assert rep["tile_cache"]["misses"] == 0 and rep["tile_cache"]["reads_ahead"] > 0  # no fix waited for a tile
    assert "frames decoded before timing" in r.output and "CPU" in r.output
    # kidnapped: no prior at all, a part of the log
    r = invoke("track", site / "day1.zip", site / "ops", "--key", site / "owner.key.pub", "--start", "none",
               "--frames", "0:20", "--report", rep_path,
               "--quiet")
    assert r.exit_code == 0, r.output
    rep = json.loads(rep_path.read_text())
    assert rep["fixes"] == 20 and rep["relocalizations"] >= 1 and rep["wrong_ok"] == 0


def test_cli_track_bad_input(site, tmp_path):
    junk = tmp_path / "junk.zip"
    junk.write_bytes(b"not a bundle at all")
    key = ("--key", site / "owner.key.pub")
    cases = [(("track", junk, site / "ops", *key), "junk.zip"),
             (("track", tmp_path / "none.zip", site / "ops", *key), "none.zip"),
             (("track", site / "day1.zip", site / "ops", "--start", "1,2", *key), "--start"),
             (("track", site / "day1.zip", site / "ops", "--frames", "5:2", *key), "--frames"),
             (("track", site / "day1.zip", tmp_path, *key), "drive.toml")]
    for args, what in cases:
        r = CliRunner().invoke(cli, [str(a) for a in args])
        assert r.exit_code == 2, (args, r.output)
        assert what in r.output and len(r.output.strip().splitlines()) == 1, r.output


def test_session_core_transitions_shared_by_both_sessions():
    """The skeleton both sessions run on (tracker.session_core): dead reckoning grows the
    1-sigma with the distance, the lock is lost by uncertainty or by lost_after rejections,
    the relocalizer is asked every reloc_every-th lost frame, an accepted fix resets."""
    import numpy as np

    from tracker.orp_session import ORPSession, ORPSessionParams
    from tracker.session import Session, SessionParams
    from tracker.session_core import CoreParams, SessionCore

    assert issubclass(Session, SessionCore) and issubclass(ORPSession, SessionCore)
    assert issubclass(SessionParams, CoreParams) and issubclass(ORPSessionParams, CoreParams)
    assert ORPSessionParams().lost_sigma_m == 0.2 and SessionParams().lost_sigma_m == 0.04

    core = SessionCore()
    core.p = CoreParams(lost_sigma_m=0.05, lost_after=2, reloc_every=3)
    core.start(np.array([1.0, 2.0, 0.0]))
    assert not core.s.lost and np.allclose(core.sigma, [0.02, 0.02, 0.02])
    core._predict(np.array([1.0, 0.0, 0.0]))
    assert np.allclose(core.s.pose, [2.0, 2.0, 0.0]) and np.allclose(core.sigma, [0.04, 0.04, 0.04])
    core._lose_if_uncertain()
    assert not core.s.lost
    core._predict(np.array([1.0, 0.0, 0.0]))
    core._lose_if_uncertain()
    assert core.s.lost and core.s.since_reloc == 0
    assert [core._reloc_due(True) for _ in range(7)] == [True, False, False, True, False, False, True]
    assert not core._reloc_due(False)
    core._locked(np.array([0.0, 0.0, 0.1]), np.array([0.001, 0.001, 0.002]))
    assert not core.s.lost and core.s.fails == 0
    core._rejected()
    assert not core.s.lost
    core._rejected()
    assert core.s.lost


def test_feature_index_near_is_the_disc_around_the_point():
    from tracker.reloc import FeatureIndex

    rng = np.random.default_rng(3)
    xy = rng.uniform([-2.0, 5.0], [18.0, 9.0], (20000, 2))
    fi = FeatureIndex(xy, np.zeros((len(xy), 32), np.uint8), np.zeros(len(xy), np.float32))
    for x, y, r in [(3.0, 7.0, 1.2), (-2.0, 5.0, 0.7), (17.9, 8.9, 2.5), (40.0, 7.0, 3.0), (8.0, 7.0, 50.0), (5.0, 6.0, 0.0)]:
        want = np.flatnonzero(((xy - (x, y)) ** 2).sum(axis=1) <= r * r)
        np.testing.assert_array_equal(fi.near(x, y, r), want)


def test_relocalizer_near_a_pose_matches_only_the_features_there(world):
    m, grid = world
    rng = np.random.default_rng(8)
    truth = np.array([2.1, 1.4, 0.7])
    frame = frame_at(m, grid, truth, rng)
    tr = FloorTracker(ArrayTiles(m), grid, PX)
    reloc = Relocalizer(build_index(ArrayTiles(m), grid), tr)
    here = reloc.locate(frame, near=(truth[0] + 0.2, truth[1] - 0.1, 0.6))
    assert here.ok and np.hypot(*(here.pose[:2] - truth[:2])) < 2 * PX
    elsewhere = reloc.proposals(frame, near=(4.5, 0.5, 0.4))  # no feature of the frame's floor in this disc
    assert all(np.hypot(*(p[:2] - truth[:2])) > 0.1 for p, _ in elsewhere)
    assert len(reloc.index.near(4.5, 0.5, 0.4)) < len(reloc.index) // 10


def test_lost_session_searches_near_its_pose_then_now_and_then_the_whole_index(world):
    truth, frames, motions, tr = simulated_drive(world, 16, 9)

    class Recorder:  # a relocalizer that never finds the pose, recording where it searched
        def __init__(self):
            self.near, self.last_seconds = [], 0.0

        def locate(self, frame, valid=None, near=None):
            self.near.append(near)
            return tr.fix(frame, np.array([0.1, 0.1, 0.0]), np.full(3, 1e-3), valid)  # off the drive: not ok

    rec = Recorder()
    ses = Session(tr, rec, SessionParams(lost_after=3, reloc_global_every=5))
    ses.start(truth[0] + [1.5, 0.4, 0.3])  # confident and 1.5 m off: lost after 3 frames, never found
    steps = run(ses, frames, motions)
    assert sum(s.lost for s in steps) >= 12
    whole = [k for k, n in enumerate(rec.near) if n is None]
    assert whole == [1, 6, 11], rec.near  # the 2nd attempt of the streak, then every 5th
    for k, n in enumerate(rec.near):
        if n is not None:  # around the dead-reckoned pose, 1 m + 3 sigma
            pose = steps[3 + k].pose
            assert n[2] >= 1.0 and np.hypot(n[0] - pose[0], n[1] - pose[1]) < 0.5
    rec.near.clear()
    ses = Session(tr, rec, SessionParams(lost_after=3, reloc_global_every=1))  # every attempt: the whole index
    ses.start(truth[0] + [1.5, 0.4, 0.3])
    run(ses, frames[:8], motions[:7])
    assert rec.near and all(n is None for n in rec.near)
