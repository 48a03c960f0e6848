"""The trajectory plot (pipeline/plots.py): map links are no lines from the last frame, and the
legend's link counts are the report's (pipeline/link_counts.py, one source for both)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import pipeline.plots as plots
from pipeline.anchor import MAP_FRAME
from pipeline.cli import cli
from pipeline.link_counts import link_counts
from pipeline.links import Link

AREA = "1.5x1.5"


def _link(a: int, b: int, status: str = "accepted") -> Link:
    return Link(a, b, np.zeros(3), np.eye(3) * 1e-6, 0.9, 0.5, 0.5, 100, "correlation", status,
                "" if status == "accepted" else "low NCC")


def _synthetic():
    """10 frames on a line; pair links among frames 0..8 (none touches the last frame, 9),
    map links on every other frame; registration rejected some, the optimizer two more."""
    opt = np.column_stack([np.arange(10.0), np.zeros(10)])
    pairs = [_link(k, k + 1) for k in range(8)] + [_link(0, 5, "rejected"), _link(2, 7, "rejected")]
    maps = [_link(MAP_FRAME, b) for b in (0, 2, 4, 6, 8)] + [_link(MAP_FRAME, 3, "rejected")]
    links = pairs + maps
    registered = [lk.status == "accepted" for lk in links]
    links[1].status = "rejected"  # a pair outlier
    links[-2].status = "rejected"  # a map outlier (frame 8)
    return opt, links, registered


def test_link_counts_split_pairs_from_map_links_and_add_up():
    _, links, registered = _synthetic()
    c = link_counts(links, registered)
    assert c == {"candidates": 10, "accepted": 7, "rejected": 3, "rejected_registration": 2,
                 "rejected_outliers": 1, "map_candidates": 6, "map_accepted": 4,
                 "map_rejected_registration": 1, "map_rejected_outliers": 1}
    with pytest.raises(ValueError, match="flags"):
        link_counts(links, registered[:-1])


def test_no_segment_from_the_last_frame_and_the_legend_shows_the_reports_counts(tmp_path, monkeypatch):
    opt, links, registered = _synthetic()
    counts = link_counts(links, registered)
    figs = []
    monkeypatch.setattr(plots, "_save", lambda fig, path: figs.append(fig))
    drawn = plots.plot_trajectories(tmp_path / "t.png", opt, opt, None, links, counts=counts)
    (fig,) = figs
    (ax,) = fig.axes
    segs = []  # the links' lines: one polyline per kind, segments broken by NaN
    for line in ax.lines:
        xy = np.asarray(line.get_xydata(), float)
        if np.isnan(xy).any():
            segs += [s for s in np.split(xy, np.flatnonzero(np.isnan(xy[:, 0]))) if len(s[~np.isnan(s[:, 0])])]
    segs = [s[~np.isnan(s[:, 0])] for s in segs]
    assert all(len(s) == 2 for s in segs)
    assert len(segs) == counts["candidates"] == len(drawn.accepted) + len(drawn.rejected)
    last = opt[-1]
    assert not any(np.allclose(p, last) for s in segs for p in s)  # no red fan from frame 9
    np.testing.assert_allclose(drawn.anchored, opt[[0, 2, 4, 6]])
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert "accepted links (7)" in legend
    assert "rejected links (3: 2 by registration, 1 as outliers)" in legend
    assert "registered to the map (4 of 6 map links)" in legend
    # without the report's counts, the links' own statuses (same numbers, no split)
    bare = plots.trajectory_links(opt, links)
    assert bare.labels["rejected"] == "rejected links (3)" and bare.labels["anchored"].startswith("registered to the map (4 of 6")


def test_the_residuals_legend_splits_map_links_and_counts_as_the_report(tmp_path, monkeypatch):
    opt, links, registered = _synthetic()
    for k, lk in enumerate(links):  # residuals after optimization; registration's rejects have none
        lk.extra["residual_px"] = 0.01 * (k + 1) if registered[k] else float("nan")
    counts = link_counts(links, registered)
    figs = []
    monkeypatch.setattr(plots, "_save", lambda fig, path: figs.append(fig))
    plots.plot_link_residuals(tmp_path / "r.png", links)
    legend = [t.get_text() for t in figs[0].axes[0].get_legend().get_texts()]
    assert f"accepted links ({counts['accepted']})" in legend
    assert f"accepted map links ({counts['map_accepted']})" in legend
    assert f"rejected as outliers ({counts['rejected_outliers'] + counts['map_rejected_outliers']})" in legend


def _invoke(*args):
    return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)


def test_a_two_day_build_plots_the_counts_of_its_report(tmp_path, monkeypatch):
    seen = []
    real = plots.plot_trajectories

    def record(*a, **k):
        seen.append(real(*a, **k))
        return seen[-1]

    monkeypatch.setattr(plots, "plot_trajectories", record)
    day1, day2 = tmp_path / "day1", tmp_path / "day2"
    assert _invoke("simulate", "floor", day1, "--area", AREA, "--seed", "1", "--quiet").exit_code == 0
    r = _invoke("build", day1, "--map", tmp_path / "map", "-w", tmp_path / "w1", "--report", tmp_path / "r1.json",
                "--quiet")
    assert r.exit_code == 0, r.output
    r = _invoke("simulate", "floor", day2, "--world", day1, "--changes", "2", "--seed", "12", "--quiet")
    assert r.exit_code == 0, r.output
    r = _invoke("build", day2, "--map", tmp_path / "map", "-w", tmp_path / "w2", "--report", tmp_path / "r2.json",
                "--quiet")
    assert r.exit_code == 0, r.output
    rep = json.loads((tmp_path / "r2.json").read_text())
    L, drawn = rep["links"], seen[-1]
    assert L["map_candidates"] > 0  # day 2 was registered to day 1's map
    assert L["rejected"] == L["rejected_registration"] + L["rejected_outliers"]
    assert L["rejected_registration"] == rep["registration"]["rejected"]
    assert len(drawn.accepted) == L["accepted"] and len(drawn.rejected) == L["rejected"]
    assert len(drawn.anchored) == L["map_accepted"]
    assert drawn.labels["accepted"] == f"accepted links ({L['accepted']})"
    assert drawn.labels["rejected"] == (f"rejected links ({L['rejected']}: {L['rejected_registration']} by "
                                        f"registration, {L['rejected_outliers']} as outliers)")
    assert drawn.labels["anchored"] == f"registered to the map ({L['map_accepted']} of {L['map_candidates']} map links)"
    assert (tmp_path / "w2" / "optimize" / "trajectory.png").stat().st_size > 5000
