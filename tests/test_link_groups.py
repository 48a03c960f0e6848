"""Overlaps no link verifies (pipeline/link_groups.py) and their publish gate."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.config import load_config
from pipeline.errors import JobFailed
from pipeline.link_groups import unverified_overlaps
from pipeline.links import components
from pipeline.stages.publish import check_gates


def _strips(n: int, lines: int, step: float, spacing: float) -> np.ndarray:
    """Frames along ``lines`` parallel lines (x along a line, y across), 1 x 1 m footprints."""
    return np.array([[k * step, ln * spacing, 0.0] for ln in range(lines) for k in range(n)])


def test_frames_of_one_group_never_count():
    poses = _strips(5, 2, 0.5, 0.6)
    sizes = np.ones((10, 2))
    groups = np.zeros(10, int)
    mask, pairs = unverified_overlaps(poses, sizes, groups, np.ones(10, bool), 0.2)
    assert not mask.any() and pairs == 0


def test_two_groups_overlapping_across_their_lines_count():
    """Two flight lines 0.6 m apart (40 % side overlap), each line linked along itself only:
    every frame overlaps a frame of the other line that nothing links it to."""
    poses = _strips(5, 2, 0.5, 0.6)
    sizes = np.ones((10, 2))
    a = [0, 1, 2, 3, 5, 6, 7, 8]
    b = [1, 2, 3, 4, 6, 7, 8, 9]
    groups = components(10, a, b)
    mask, pairs = unverified_overlaps(poses, sizes, groups, np.ones(10, bool), 0.2)
    assert mask.all() and pairs >= 5
    # one link across the lines makes them one group: nothing left unverified
    groups = components(10, a + [2], b + [7])
    assert not unverified_overlaps(poses, sizes, groups, np.ones(10, bool), 0.2)[0].any()
    # lines 0.9 m apart overlap by 10 % of a frame: below a 20 % threshold
    far = _strips(5, 2, 0.5, 0.9)
    assert not unverified_overlaps(far, sizes, components(10, a, b), np.ones(10, bool), 0.2)[0].any()
    assert unverified_overlaps(far, sizes, components(10, a, b), np.ones(10, bool), 0.05)[0].all()


def test_rotation_and_candidates_are_respected():
    """A frame turned 90 degrees still overlaps by its true (rotated) footprint; frames that
    are not candidates (blank, dropped) neither count nor make others count."""
    poses = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, np.pi / 2]])
    sizes = np.array([[2.0, 0.5], [2.0, 0.5]])  # 1 m^2 each, long and thin
    groups, every = np.array([0, 1]), np.ones(2, bool)
    # turned: a 0.25 x 0.5 m corner, 12.5 % of a footprint (unturned it would be 50 %)
    assert unverified_overlaps(poses, sizes, groups, every, 0.1)[0].all()
    assert not unverified_overlaps(poses, sizes, groups, every, 0.2)[0].any()
    poses[1, 2] = 0.0
    assert unverified_overlaps(poses, sizes, groups, every, 0.45)[0].all()
    # a frame that is not a candidate neither counts nor makes the other count
    assert not unverified_overlaps(poses, sizes, groups, np.array([True, False]), 0.1)[0].any()
    poses[1, 1] = 0.6  # 0.6 m apart across their thin side: no overlap
    assert not unverified_overlaps(poses, sizes, groups, every, 0.01)[0].any()


def test_the_publish_gate_refuses_a_map_mostly_placed_against_itself_by_the_prior():
    pub = load_config()["publish"]
    report = {"links": {"frames_registrable": 100, "unverified_overlap_frames": 66,
                        "unverified_overlap": [f"f{i}" for i in range(66)]}}
    check_gates(report, pub)  # 66 %: under the default 75 %
    report["links"]["unverified_overlap_frames"] = 93
    with pytest.raises(JobFailed) as e:
        check_gates(report, pub)
    msg = str(e.value)
    assert "\n" not in msg and "max_unverified_overlap_fraction" in msg and "93.0%" in msg and "f0" in msg


def test_a_frame_without_links_is_told_apart_from_a_strip():
    """One frame of a linked line without any link of its own: it and the neighbours it
    overlaps count as unverified, and it alone is a lone frame (the warning names it so that
    one unlinked frame does not read as a ghosted strip)."""
    from pipeline.link_groups import lone_frames

    poses = _strips(7, 1, 0.5, 0.6)
    sizes = np.ones((7, 2))
    a, b = [0, 1, 2, 4, 5], [1, 2, 4, 5, 6]  # frame 3 keeps no link (2 -> 4 bridges it)
    groups = components(7, a, b)
    mask, pairs = unverified_overlaps(poses, sizes, groups, np.ones(7, bool), 0.2)
    assert mask[[2, 3, 4]].all() and pairs >= 2
    assert lone_frames(np.flatnonzero(mask), groups).tolist() == [3]
    # two lines, each linked along itself: no lone frame
    poses = _strips(5, 2, 0.5, 0.6)
    groups = components(10, [0, 1, 2, 3, 5, 6, 7, 8], [1, 2, 3, 4, 6, 7, 8, 9])
    mask, _ = unverified_overlaps(poses, np.ones((10, 2)), groups, np.ones(10, bool), 0.2)
    assert mask.all() and lone_frames(np.flatnonzero(mask), groups).size == 0
    assert lone_frames(np.zeros(0, int), groups).size == 0
