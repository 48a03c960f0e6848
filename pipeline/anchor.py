"""Registration of a build's new frames against the published map (incremental builds).

When the map repository already holds a version, the new frames are registered not only to
each other but also to the published level-0 mosaic: each link says where a new frame lies
in the *map* frame (the world frame the published poses are in). The optimizer turns these
*map links* into factors tying the new poses to the map, so a rebuild keeps coordinates
stable and a new day's log lands exactly on the floor it shares with the map.

Frames are visited in drive order per log, every ``map_link_stride``-th frame. The prior
of a frame is the chain (odometry corrected by the accepted sequential links) carried by
the correction the last accepted map link found; its search radius grows from that link
with the error gradient times the distance travelled since (Kelly (2000)), from a start
uncertainty ``map_start_sigma_m`` before the first one. A frame whose predicted footprint
lies mostly outside the mapped floor is not tried.

A map link is a :class:`pipeline.links.Link` with ``a = MAP_FRAME`` (-1): ``rel`` is the
pose of frame ``b`` in the map frame (metres, radians), ``cov`` its covariance.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from mapstore.grid import MapGrid, se2_compose, se2_inverse
from pipeline.candidates import FrameTable, odometry_sigmas
from pipeline.errors import JobFailed
from pipeline.links import Link
from pipeline.mosaic import frame_boxes
from pipeline.progress import progress
from pipeline.registration import RegistrationParams, register_pair

log = logging.getLogger(__name__)

MAP_FRAME = -1
MAP_LINKS_FILE = "map_links.csv"


@dataclass
class MapView:
    """Read access to a published map's level-0 intensity (uint8, 0 = no data).

    Attributes:
        array: the level-0 zarr array (rows, columns) of the map version.
        grid: its :class:`mapstore.grid.MapGrid`.
    """

    array: object
    grid: MapGrid

    def crop(self, box: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray]:
        """Level-0 pixels of ``box`` (r0, r1, c0, c1; may reach outside the map) as
        float32 grey levels with their coverage mask (False outside the map or uncovered)."""
        r0, r1, c0, c1 = (int(v) for v in box)
        out = np.zeros((r1 - r0, c1 - c0), np.uint8)
        h, w = self.grid.shape
        rr0, rr1, cc0, cc1 = max(r0, 0), min(r1, h), max(c0, 0), min(c1, w)
        if rr0 < rr1 and cc0 < cc1:
            out[rr0 - r0 : rr1 - r0, cc0 - c0 : cc1 - c0] = self.array[rr0:rr1, cc0:cc1]
        return out.astype(np.float32), out > 0


def crop_pose(grid: MapGrid, box: tuple[int, int, int, int]) -> np.ndarray:
    """World pose (metres, radians) of a map crop seen as a frame (mapstore.grid's frame
    convention: its centre pixel, heading 0, columns along +x, rows along -y)."""
    r0, r1, c0, c1 = box
    x, y = grid.pixel_to_world(c0 + (c1 - c0 - 1) / 2.0, r0 + (r1 - r0 - 1) / 2.0)
    return np.array([float(x), float(y), 0.0])


def register_to_map(
    reader,
    frames: FrameTable,
    chain: np.ndarray,
    view: MapView,
    cfg: dict,
    *,
    quiet: bool = False,
    names: list[str] | None = None,
    map_name: str = "",
) -> tuple[list[Link], int]:
    """Map links for the build's frames (see the module docstring).

    A log whose first ``[register] map_max_failed_anchors`` attempts all fail (none before
    them succeeded; frames outside the mapped floor are no attempt) matches no part of the
    map: :class:`NoMapMatch` (exit 1) stops the build there, in time bounded by that many
    registrations (0 = never stop; the publish gate min_anchored_fraction still applies).

    Args:
        reader: ``reader.get(g) -> (image float32, valid bool)`` for global frame ``g``.
        frames: the build's frames; ``chain``: (N, 3) their chained poses (site frame).
        view: the published map; cfg: the full configuration.
        names: each log's id (for the message); map_name: the map (its URL).

    Returns ``(links, outside)``: the map links tried (accepted and rejected) and the number
    of visited frames skipped because they lie mostly outside the mapped floor.
    """
    reg, opt = cfg["register"], cfg["optimize"]
    params = RegistrationParams.from_config(reg)
    models = frames.models(opt)
    stride = max(int(reg["map_link_stride"]), 1)
    px = frames.pixel_size
    max_failed = int(reg["map_max_failed_anchors"])
    links: list[Link] = []
    outside = 0
    visits = []
    for k in np.unique(frames.log):
        idx = np.flatnonzero(frames.log == k)
        if frames.registrable is not None:
            idx = idx[frames.registrable[idx]]  # (frames placed by the prior are not registered)
        if len(idx):
            visits.append(np.unique(np.r_[idx[::stride], idx[-1]]))
    total = sum(len(v) for v in visits)
    it = progress((g for v in visits for g in v), length=total, label="register to map", unit="frames", quiet=quiet)
    current_log = None
    for g in it:
        g = int(g)
        if frames.log[g] != current_log:
            current_log = frames.log[g]
            correction = np.zeros(3)  # map pose = correction ⊕ chain pose
            since = frames.path_m[g]
            start_t, start_h = float(reg["map_start_sigma_m"]), float(reg["map_start_sigma_rad"])
            failed, anchored = 0, False  # attempts of this log that failed before its first map link
        pred = se2_compose(correction, chain[g])
        sig_t, sig_h = odometry_sigmas(abs(frames.path_m[g] - since), opt, models[g])
        sig_t, sig_h = float(np.hypot(sig_t, start_t)), float(np.hypot(sig_h, start_h))
        shape = frames.shapes[int(frames.log[g])]
        half_diag = 0.5 * np.hypot(*shape) * px
        radius = reg["search_sigmas"] * np.hypot(sig_t, sig_h * half_diag) / px + reg["search_floor_px"]
        pad = int(np.ceil(radius)) + int(np.ceil(reg["coarse_exclusion_px"]))
        box = tuple(frame_boxes(view.grid, pred[None], shape, px, pad_px=pad)[0])
        crop, crop_valid = view.crop(box)
        img, valid = reader.get(g)
        footprint = frame_boxes(view.grid, pred[None], shape, px, pad_px=0)[0]
        inner = (slice(footprint[0] - box[0], footprint[1] - box[0]), slice(footprint[2] - box[2], footprint[3] - box[2]))
        if crop_valid[inner].mean() < reg["map_min_covered_fraction"]:
            outside += 1
            continue
        cp = crop_pose(view.grid, box)
        prior_rel = se2_compose(se2_inverse(cp), pred)
        r = register_pair(crop, crop_valid, img, valid, prior_rel, px, radius, sig_h, params)
        rel = se2_compose(cp, r.rel) if r.ok else pred
        link = Link(MAP_FRAME, g, rel, r.cov, r.ncc, r.uniqueness, r.overlap, r.inliers or r.pixels, r.method,
                    gain=r.gain)
        link.extra.update(iterations=r.iterations, radius_px=round(float(radius), 2), predicted_overlap="",
                          peak_z=round(float(r.peak_z), 2))
        if not r.ok:
            link.status, link.reason = "rejected", r.reason
        elif r.ncc < reg["min_ncc"]:
            link.status, link.reason = "rejected", f"low NCC against the map: {r.ncc:.3f} (min {reg['min_ncc']})"
        elif r.method != "features" and r.uniqueness < reg["min_uniqueness"]:
            link.status, link.reason = "rejected", (
                f"ambiguous against the map: uniqueness C1-C2 {r.uniqueness:.3f} (min {reg['min_uniqueness']})")
        else:
            correction = se2_compose(rel, se2_inverse(chain[g]))
            since = frames.path_m[g]
            start_t = float(np.sqrt(max(r.cov[0, 0] + r.cov[1, 1], 0.0)))
            start_h = float(np.sqrt(max(r.cov[2, 2], 0.0)))
            anchored = True
        links.append(link)
        if not anchored:
            failed += 1
            if max_failed and failed >= max_failed:
                raise NoMapMatch(names[int(current_log)] if names else str(int(current_log)),
                                 int((frames.log == current_log).sum()), failed, map_name)
    return links, outside


class NoMapMatch(JobFailed):
    """A log none of whose first ``[register] map_max_failed_anchors`` map link attempts
    succeeded: it matches no part of the map (another floor, or the wrong map)."""

    def __init__(self, log_id: str, frames: int, tried: int, map_name: str):
        self.log_id, self.frames, self.tried = log_id, frames, tried
        super().__init__(f"{log_id}: 0 of {frames} frames match the map {map_name} (tried {tried} anchors, "
                         f"[register] map_max_failed_anchors); is this the right map?")


def open_map_view(url: str, snapshot: str) -> MapView:
    """The level-0 intensity of map version ``snapshot`` in the repository at ``url``."""
    import zarr

    from mapstore.layout import read_floor
    from mapstore.repository import MapRepository

    session = MapRepository.open(url).readonly(snapshot)
    root = zarr.open_group(session.store, mode="r")
    info = read_floor(root)
    return MapView(root["floor/0"], info.grid)


@dataclass
class AnchoredUncertainty:
    """Prior uncertainty of frames anchored to the map, for revisit search radii.

    Each frame's absolute sigma (metres, radians) is that of its nearest accepted map link
    along the log plus the odometry's over the path between them; two frames' relative
    uncertainty is at most the combination of their absolute ones (each is held by the
    map), and at most what the chain of sequential links accumulated between them.
    """

    chain: object  # pipeline.candidates.ChainUncertainty
    var_t: np.ndarray
    var_h: np.ndarray

    def relative(self, frames: FrameTable, a: np.ndarray, b: np.ndarray, cfg_opt: dict) -> tuple[np.ndarray, np.ndarray]:
        sig_t, sig_h = self.chain.relative(frames, a, b, cfg_opt)
        lever = np.hypot(*(frames.prior[a, :2] - frames.prior[b, :2]).T)
        vh = self.var_h[a] + self.var_h[b]
        mt = np.sqrt(self.var_t[a] + self.var_t[b] + vh * lever**2)
        return np.minimum(sig_t, mt), np.minimum(sig_h, np.sqrt(vh))


def anchored_chain(frames: FrameTable, chain: np.ndarray, map_links: list[Link], unc, cfg_opt: dict):
    """The chain moved onto the map by the accepted map links, and its uncertainty.

    Every frame takes the correction (map pose ⊖ chain pose) of the accepted map link
    nearest to it along its log; frames of a log without any keep the chain. Returns
    ``(poses (N, 3), AnchoredUncertainty)``.
    """
    n = len(chain)
    poses = chain.copy()
    models = frames.models(cfg_opt)
    big = 1e6
    var_t = np.full(n, big)
    var_h = np.full(n, big)
    acc = {lk.b: lk for lk in map_links if lk.status == "accepted"}
    for k in np.unique(frames.log):
        idx = np.flatnonzero(frames.log == k)
        anchors = np.array([g for g in idx if g in acc], dtype=int)
        if len(anchors) == 0:
            continue
        pos = np.searchsorted(frames.path_m[anchors], frames.path_m[idx])
        lo = anchors[np.clip(pos - 1, 0, len(anchors) - 1)]
        hi = anchors[np.clip(pos, 0, len(anchors) - 1)]
        near = np.where(np.abs(frames.path_m[lo] - frames.path_m[idx]) <= np.abs(frames.path_m[hi] - frames.path_m[idx]),
                        lo, hi)
        for g, h in zip(idx.tolist(), near.tolist()):
            lk = acc[h]
            poses[g] = se2_compose(se2_compose(lk.rel, se2_inverse(chain[h])), chain[g])
            st, sh = odometry_sigmas(abs(frames.path_m[g] - frames.path_m[h]), cfg_opt, models[g])
            var_t[g] = lk.cov[0, 0] + lk.cov[1, 1] + st**2
            var_h[g] = lk.cov[2, 2] + sh**2
    return poses, AnchoredUncertainty(unc, var_t, var_h)
