"""Plots written next to the reports: trajectories and link residuals (matplotlib, Agg).

matplotlib is imported inside the functions, so importing this module costs nothing.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["TrajectoryLinks", "trajectory_links", "plot_trajectories", "plot_link_residuals", "plot_tracking"]


def _figure(size=(8.0, 8.0)):
    """A figure drawn by the Agg canvas directly: no pyplot (its import and its global
    figure registry cost a tenth of a second per build, and nothing here is interactive)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size)
    FigureCanvasAgg(fig)
    return fig


def _save(fig, path_png) -> None:
    path = Path(path_png)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")


@dataclass
class TrajectoryLinks:
    """What the trajectory plot draws of the links (positions in metres).

    ``accepted`` / ``rejected``: (K, 2, 2) segments between the optimized positions of pair
    links' two frames (segment, end, x/y); ``anchored``: the positions of frames an accepted map link ties to the published
    map (a map link has no second frame: it is a marker, not a line); ``labels``: the legend's
    text of each, its counts those of :func:`pipeline.link_counts.link_counts` (the report's).
    """

    accepted: np.ndarray
    rejected: np.ndarray
    anchored: np.ndarray
    labels: dict[str, str]


def trajectory_links(optimized_xy: np.ndarray, links, counts: dict | None = None) -> TrajectoryLinks:
    """The segments, markers and legend labels :func:`plot_trajectories` draws for ``links``.

    Map links (``a = MAP_FRAME``) are never drawn as segments (``MAP_FRAME`` = -1 is no frame:
    it would index the last one). ``counts``: the report's ``links`` counts; without them,
    the counts are taken from the links' statuses (no registration/outlier split).
    """
    from pipeline.anchor import MAP_FRAME

    opt = np.asarray(optimized_xy, dtype=float)[:, :2]
    pairs = [lk for lk in links if lk.a != MAP_FRAME]
    maps = [lk for lk in links if lk.a == MAP_FRAME]
    ends = np.array([(lk.a, lk.b) for lk in pairs], dtype=np.int64).reshape(-1, 2)
    ok = np.array([lk.status == "accepted" for lk in pairs], dtype=bool)
    acc, rej = opt[ends[ok]], opt[ends[~ok]]
    anchored = np.array([opt[lk.b] for lk in maps if lk.status == "accepted"]).reshape(-1, 2)
    if counts is None:
        counts = {"accepted": len(acc), "rejected": len(rej), "map_candidates": len(maps),
                  "map_accepted": len(anchored)}
    labels = {"accepted": f"accepted links ({counts['accepted']})"}
    split = ""
    if "rejected_registration" in counts:
        split = (f": {counts['rejected_registration']} by registration, "
                 f"{counts['rejected_outliers']} as outliers")
    labels["rejected"] = f"rejected links ({counts['rejected']}{split})"
    if counts.get("map_candidates"):
        labels["anchored"] = (f"registered to the map ({counts['map_accepted']} of "
                              f"{counts['map_candidates']} map links)")
    return TrajectoryLinks(acc, rej, anchored, labels)


def _broken_line(segments: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """x and y of (K, 2, 2) segments as one polyline broken by NaN between segments: a
    single artist (a collection of a few hundred thousand links holds one path object per
    segment: ~300 MB at 185,000 links, the optimize stage's peak on a 40 x 40 m site)."""
    pts = np.full((len(segments), 3, 2), np.nan)
    pts[:, :2] = segments
    return pts[:, :, 0].ravel(), pts[:, :, 1].ravel()


def plot_trajectories(path_png, odometry_xy: np.ndarray, optimized_xy: np.ndarray,
                      gt_xy: np.ndarray | None = None, links=None, *,
                      counts: dict | None = None) -> TrajectoryLinks | None:
    """Odometry, optimized and (when given) ground-truth frame positions, in metres.

    Accepted pair links are drawn as thin grey lines between the optimized positions,
    rejected ones in red; frames an accepted map link ties to the published map are marked
    with a green dot. ``*_xy`` are (N, 2) or (N, 3) arrays (only x, y are used); frames are
    numbered globally, as the links' ``a`` and ``b``. ``counts``: the report's ``links``
    section, whose counts the legend shows (see :func:`trajectory_links`). Returns what was
    drawn of the links (None without links).
    """
    fig = _figure()
    ax = fig.add_subplot(111)
    opt = np.asarray(optimized_xy, dtype=float)[:, :2]
    drawn = None
    if links:
        drawn = trajectory_links(opt, links, counts)
        if len(drawn.accepted):
            ax.plot(*_broken_line(drawn.accepted), "-", color="0.75", lw=0.3, label=drawn.labels["accepted"],
                    zorder=1)
        if len(drawn.rejected):
            ax.plot(*_broken_line(drawn.rejected), "-", color="red", lw=1.0, label=drawn.labels["rejected"],
                    zorder=4)
        if "anchored" in drawn.labels:
            ax.plot(drawn.anchored[:, 0], drawn.anchored[:, 1], "o", ms=2.5, color="tab:green",
                    label=drawn.labels["anchored"], zorder=5)
    odo = np.asarray(odometry_xy, dtype=float)[:, :2]
    ax.plot(odo[:, 0], odo[:, 1], "-", color="tab:orange", lw=0.8, label="odometry", zorder=2)
    if gt_xy is not None:
        gt = np.asarray(gt_xy, dtype=float)[:, :2]
        ax.plot(gt[:, 0], gt[:, 1], "-", color="tab:green", lw=2.0, alpha=0.5, label="ground truth", zorder=2)
    ax.plot(opt[:, 0], opt[:, 1], "-", color="tab:blue", lw=0.8, label="optimized", zorder=3)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("Frame trajectories")
    ax.grid(True, lw=0.3)
    ax.legend(loc="best", fontsize="small")
    _save(fig, path_png)
    return drawn


def plot_link_residuals(path_png, links) -> None:
    """Histogram of the links' translation residuals (``extra["residual_px"]``, pixels).

    Accepted links between two frames in blue, accepted links to the published map in
    green, links the optimizer rejected in red (those registration rejected have no
    residual); the counts are the report's ``links.accepted``, ``map_accepted`` and
    ``rejected_outliers`` + ``map_rejected_outliers``. Logarithmic bins (and a logarithmic
    count axis) when the residuals span more than two decades.
    """
    from pipeline.anchor import MAP_FRAME

    fig = _figure((8.0, 5.0))
    ax = fig.add_subplot(111)
    res = np.array([float(lk.extra.get("residual_px", np.nan)) for lk in links], dtype=float)
    acc = np.array([lk.status == "accepted" for lk in links], dtype=bool)
    to_map = np.array([lk.a == MAP_FRAME for lk in links], dtype=bool)
    ok = np.isfinite(res)
    vals = res[ok]
    if vals.size:
        pos = vals[vals > 0]
        lo = pos.min() if pos.size else 1e-6
        hi = max(vals.max(), lo * 10)
        log = hi / lo > 100
        bins = np.geomspace(lo, hi, 60) if log else np.linspace(0.0, hi, 60)
        def vals_of(sel: np.ndarray) -> np.ndarray:
            return np.clip(res[ok & sel], lo, None) if log else res[ok & sel]

        a, m, r = vals_of(acc & ~to_map), vals_of(acc & to_map), vals_of(~acc)
        ax.hist(a, bins=bins, histtype="stepfilled", color="tab:blue", alpha=0.8, label=f"accepted links ({a.size})")
        if m.size:
            ax.hist(m, bins=bins, histtype="stepfilled", color="tab:green", alpha=0.6, label=f"accepted map links ({m.size})")
        if r.size:
            ax.hist(r, bins=bins, histtype="stepfilled", color="red", alpha=0.8, label=f"rejected as outliers ({r.size})")
        if log:
            from matplotlib.ticker import FuncFormatter, NullFormatter

            ax.set_xscale("log")
            ax.set_yscale("log")
            for axis in (ax.xaxis, ax.yaxis):
                # Plain numbers (0.001, 10), not mathtext powers: parsing those cost a
                # tenth of a second of every build.
                axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
                axis.set_minor_formatter(NullFormatter())
        if a.size:
            rms = float(np.sqrt(np.mean(res[ok & acc & ~to_map] ** 2)))
            ax.axvline(rms, color="k", ls="--", lw=0.8, label=f"RMS accepted links {rms:.3g} px")
        ax.legend(loc="best", fontsize="small")
    else:
        ax.text(0.5, 0.5, "no links", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlabel("translation residual after optimization (px)")
    ax.set_ylabel("links")
    ax.set_title("Link residuals")
    _save(fig, path_png)


STATUS_COLOURS = {"ok": "tab:blue", "low_texture": "tab:olive", "ambiguous": "tab:orange", "lost": "tab:red",
                  "off_map": "tab:purple"}
# The route-panorama session's statuses (tracker/orp_session.py).
ORP_STATUS_COLOURS = {"ok": "tab:blue", "weak": "tab:olive", "masked": "tab:cyan", "jump": "tab:orange",
                      "off_route": "tab:purple", "lost": "tab:red", "ambiguous": "tab:pink"}


def plot_tracking(path_png, steps, odometry: np.ndarray, truth: np.ndarray | None, unit_m: float,
                  unit: str = "map px", wrong: float = 2.0, colours: dict | None = None,
                  route: np.ndarray | None = None) -> None:
    """A tracking run (``mosaicmap track``): left, the trajectories in metres (the route of a
    route panorama if given, ground truth, odometry, the tracked poses coloured by the frame's
    status, relocalizations marked); right, per frame the error of the tracked pose against
    the truth in ``unit`` (``unit_m`` metres each: the map pixel, or 0.01 for cm; log scale;
    ``wrong`` in that unit marked: an ok fix further off is wrong); without truth, the pose's
    1-sigma. ``colours``: status -> colour (default the floor tracker's)."""
    colours = STATUS_COLOURS if colours is None else colours
    fig = _figure((14.0, 6.0))
    ax, ax2 = fig.add_subplot(121), fig.add_subplot(122)
    poses = np.array([st.pose for st in steps]).reshape(-1, 3)
    status = np.array([st.status for st in steps])
    if route is not None:
        ax.plot(route[:, 0], route[:, 1], "-", color="0.3", lw=3.0, alpha=0.25, label="route (ORP)")
    if truth is not None:
        ax.plot(truth[:, 0], truth[:, 1], "-", color="tab:green", lw=2.0, alpha=0.4, label="ground truth")
    ax.plot(odometry[:, 0], odometry[:, 1], "-", color="0.6", lw=0.7, label="odometry")
    for name, colour in colours.items():
        m = status == name
        if m.any():
            ax.plot(poses[m, 0], poses[m, 1], ".", ms=2.5, color=colour, label=f"{name} ({int(m.sum())})")
    rel = np.array([st.mode == "reloc" for st in steps])
    if rel.any():
        ax.plot(poses[rel, 0], poses[rel, 1], "*", ms=4, color="k", label=f"relocalized ({int(rel.sum())})")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("Tracked poses by status")
    ax.grid(True, lw=0.3)
    ax.legend(loc="best", fontsize="small", markerscale=3)
    k = np.arange(len(steps))
    if truth is not None:
        err = np.hypot(poses[:, 0] - truth[:, 0], poses[:, 1] - truth[:, 1]) / unit_m
        for name, colour in colours.items():
            m = (status == name) & np.isfinite(err)
            if m.any():
                ax2.plot(k[m], np.maximum(err[m], 1e-3), ".", ms=2.5, color=colour, label=name)
        ax2.axhline(wrong, color="tab:red", lw=0.8, ls="--", label=f"{wrong:g} {unit} (wrong if ok)")
        ax2.set_ylabel(f"position error ({unit})")
        ax2.set_title("Error against ground truth")
    else:
        sig = np.array([st.sigma[:2].max() for st in steps]) / unit_m
        ax2.plot(k, sig, "-", color="tab:blue", lw=0.8, label="1-sigma")
        ax2.set_ylabel(f"position 1-sigma ({unit})")
        ax2.set_title("Pose uncertainty")
    ax2.set_yscale("log")
    ax2.set_xlabel("frame")
    ax2.grid(True, lw=0.3, which="both")
    ax2.legend(loc="best", fontsize="small", markerscale=3)
    _save(fig, path_png)
