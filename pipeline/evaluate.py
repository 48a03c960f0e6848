"""Ground-truth evaluation of poses, links and map diffs (simulated logs, or logs with
ground_truth.csv).

Pure functions; the build never reads ground truth, only reports these figures.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mapstore.grid import interpolate_trajectory, se2_between, se2_compose, se2_inverse

__all__ = ["align_se2", "absolute_trajectory_error", "link_errors", "ground_truth_at", "mosaic_vs_world", "seam_ratio",
           "ThresholdAgreement", "threshold_agreement",
           "FrameAlignment", "map_world_alignment", "TruthMask", "read_truth_mask", "truth_on_map",
           "TruthChange", "TruthReport", "evaluate_diff"]


def align_se2(est_xy: np.ndarray, gt_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares rigid 2D alignment (Kabsch/Umeyama without scale).

    Returns ``(R, t)`` (2x2 rotation, (2,) translation) minimising
    ``sum || R est_i + t - gt_i ||^2``.
    """
    est = np.asarray(est_xy, dtype=float).reshape(-1, 2)
    gt = np.asarray(gt_xy, dtype=float).reshape(-1, 2)
    if len(est) != len(gt) or len(est) == 0:
        raise ValueError(f"align_se2: need equal, non-zero numbers of points ({len(est)} vs {len(gt)})")
    me, mg = est.mean(axis=0), gt.mean(axis=0)
    h = (est - me).T @ (gt - mg)  # 2x2 cross-covariance
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    r = vt.T @ np.diag([1.0, d]) @ u.T
    return r, mg - r @ me


def absolute_trajectory_error(est_poses: np.ndarray, gt_poses: np.ndarray, pixel_size: float) -> dict:
    """Position error after the best rigid SE(2) alignment of ``est`` onto ``gt``, in pixels.

    Returns ``{"rms_px", "max_px", "per_frame_px"}`` (per_frame_px: (N,) array).
    """
    est = np.asarray(est_poses, dtype=float)
    gt = np.asarray(gt_poses, dtype=float)
    r, t = align_se2(est[:, :2], gt[:, :2])
    err = np.linalg.norm(est[:, :2] @ r.T + t - gt[:, :2], axis=1) / pixel_size
    return {"rms_px": float(np.sqrt(np.mean(err**2))), "max_px": float(err.max()), "per_frame_px": err}


def link_errors(links, gt_poses: np.ndarray, pixel_size: float, frame_shape: tuple[int, int] | None = None) -> np.ndarray:
    """Per link, the displacement error (pixels) of ``link.rel`` vs the ground-truth relative pose.

    The error is ``|| T_est(q) - T_gt(q) || / pixel_size`` for the point ``q`` (in frame b)
    that the ground truth puts at the centre of the overlap, approximated by the midpoint of
    the two frame centres (frame centres are the poses, so that midpoint is
    ``rel_gt.t / 2`` in frame a). ``frame_shape`` is accepted for interface stability; the
    midpoint approximation does not need it.
    """
    if not links:
        return np.zeros(0)
    gt = np.asarray(gt_poses, dtype=float)
    a = np.array([lk.a for lk in links])
    b = np.array([lk.b for lk in links])
    rel_est = np.array([lk.rel for lk in links], dtype=float)
    rel_gt = se2_between(gt[a], gt[b])
    p = np.zeros_like(rel_gt)
    p[:, :2] = rel_gt[:, :2] / 2.0  # midpoint in frame a
    q = se2_compose(se2_inverse(rel_gt), p)  # the same point in frame b (ground truth)
    pe = se2_compose(rel_est, q)  # where the link puts it in frame a
    return np.linalg.norm(pe[:, :2] - p[:, :2], axis=1) / pixel_size


def ground_truth_at(frames_t: np.ndarray, gt_csv_path: str | Path) -> np.ndarray:
    """Ground-truth poses (N, 3) at the frame times, SE(2)-interpolated from ``ground_truth.csv``."""
    from pipeline.drivelog import read_pose_csv

    samples = read_pose_csv(gt_csv_path, min_rows=2)
    return interpolate_trajectory(samples, np.asarray(frames_t, dtype=float))


def mosaic_vs_world(
    mosaic: np.ndarray,
    grid,
    texture: np.ndarray,
    texture_grid,
    rot: np.ndarray | None = None,
    trans: np.ndarray | None = None,
    erode_px: int = 4,
    *,
    wrap: bool = False,
) -> dict:
    """A rendered mosaic against the simulator's ground-truth world texture.

    Every covered map pixel (``mosaic > 0``, eroded by ``erode_px`` to leave out the map's
    ragged edge) is placed in the world by ``grid`` and by the rigid alignment ``(rot,
    trans)`` of the estimated poses onto the ground truth (:func:`align_se2`; identity when
    None), and the world texture is sampled there (cubic). Returns ``{"ncc", "psnr_db",
    "rmse", "pixels", "gain", "offset"}``: NCC, and PSNR (peak 255) and RMSE in grey levels
    after the best global linear fit ``world ≈ gain * mosaic + offset`` (the mosaic's
    exposure scale is arbitrary: gains are normalized over the frames, not to the world).
    ``wrap``: the texture tiles the world (a periodic texture, e.g. the large-render
    benchmark's): sample positions are taken modulo its size, and its edges wrap.
    """
    import cv2

    covered = (mosaic > 0).astype(np.uint8)
    if erode_px > 0:
        covered = cv2.erode(covered, np.ones((2 * erode_px + 1,) * 2, np.uint8), borderValue=0)
    rows, cols = np.nonzero(covered)
    if len(rows) == 0:
        raise ValueError("mosaic_vs_world: the mosaic covers no pixel")
    x, y = grid.pixel_to_world(cols.astype(float), rows.astype(float))
    if rot is not None:
        xy = np.column_stack([x, y]) @ np.asarray(rot).T + np.asarray(trans)
        x, y = xy[:, 0], xy[:, 1]
    tc, tr = texture_grid.world_to_pixel(x, y)
    if wrap:
        tc, tr = np.mod(tc, texture.shape[1]), np.mod(tr, texture.shape[0])
    # cv2.remap wants maps under 32767 rows: lay the samples out in rows of 4096
    n = len(tc)
    width = 4096
    pad = -n % width
    mx = np.r_[tc, np.zeros(pad)].astype(np.float32).reshape(-1, width)
    my = np.r_[tr, np.zeros(pad)].astype(np.float32).reshape(-1, width)
    ref = cv2.remap(texture.astype(np.float32), mx, my, cv2.INTER_CUBIC,
                    borderMode=cv2.BORDER_WRAP if wrap else cv2.BORDER_REFLECT).ravel()[:n]
    m = mosaic[rows, cols].astype(float)
    ref = ref.astype(float)
    mc, rc = m - m.mean(), ref - ref.mean()
    ncc = float((mc @ rc) / np.sqrt((mc @ mc) * (rc @ rc)))
    gain = float((mc @ rc) / (mc @ mc))
    offset = float(ref.mean() - gain * m.mean())
    rmse = float(np.sqrt(np.mean((gain * m + offset - ref) ** 2)))
    return {"ncc": ncc, "psnr_db": float(20 * np.log10(255.0 / max(rmse, 1e-9))), "rmse": rmse,
            "pixels": int(len(rows)), "gain": gain, "offset": offset}


@dataclass
class ThresholdAgreement:
    """How often a layer computed another way puts a cell on the same side of a threshold.

    ``cells``: cells with a reference value; ``same``: of those, the cells whose other value
    exists and lies on the same side (``>= threshold`` or not); ``fraction``: same / cells
    (1.0 with no cell); ``missing``: reference cells without another value; ``extra``: cells
    with another value but no reference; ``below_reference`` / ``below_other``: cells below
    the threshold in each (over the cells holding both for ``below_other``)."""

    cells: int
    same: int
    fraction: float
    missing: int
    extra: int
    below_reference: int
    below_other: int


def threshold_agreement(reference: np.ndarray, other: np.ndarray, threshold: float) -> ThresholdAgreement:
    """:class:`ThresholdAgreement` of two layers of the same cells (NaN = no value), e.g. the
    uniqueness layer on level 1 against level 0 at Kelly's (2000) 0.2."""
    ref, oth = np.asarray(reference, float), np.asarray(other, float)
    if ref.shape != oth.shape:
        raise ValueError(f"layers of {ref.shape} and {oth.shape} cells")
    has_ref, has_oth = np.isfinite(ref), np.isfinite(oth)
    both = has_ref & has_oth
    same = int(np.count_nonzero((ref[both] >= threshold) == (oth[both] >= threshold)))
    cells = int(np.count_nonzero(has_ref))
    return ThresholdAgreement(cells, same, same / cells if cells else 1.0, int(np.count_nonzero(has_ref & ~has_oth)),
                              int(np.count_nonzero(has_oth & ~has_ref)), int(np.count_nonzero(ref[has_ref] < threshold)),
                              int(np.count_nonzero(both & (oth < threshold))))


def seam_ratio(mosaic: np.ndarray, border_mask: np.ndarray, erode_px: int = 4) -> float:
    """Seam metric: mean squared gradient magnitude on frame borders / elsewhere.

    ``border_mask``: bool, True within a few pixels of any frame's footprint edge (inside the
    covered area). Seams that show raise the ratio above 1; invisible seams give about 1.
    """
    import cv2

    img = mosaic.astype(np.float32)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)
    energy = gx * gx + gy * gy
    covered = cv2.erode((mosaic > 0).astype(np.uint8), np.ones((2 * erode_px + 1,) * 2, np.uint8), borderValue=0) > 0
    on = covered & border_mask
    off = covered & ~border_mask
    if not on.any() or not off.any():
        return float("nan")
    return float(energy[on].mean() / energy[off].mean())


# --- map diffs against a simulator's change mask --------------------------------------------


@dataclass
class FrameAlignment:
    """Rigid transform from the map's frame to the world (ground-truth) frame:
    ``world_xy = rot @ map_xy + trans`` (metres).

    Attributes:
        source: "ground_truth" (fitted) or "identity" (nothing to fit: see ``note``).
        frames: frames whose estimated and ground-truth positions were aligned.
        rms_m: RMS position residual after alignment (metres; None for identity).
        note: what was used or why the identity was assumed.
    """

    rot: np.ndarray
    trans: np.ndarray
    source: str
    frames: int
    rms_m: float | None
    note: str

    def map_to_world(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x, y = np.asarray(x, float), np.asarray(y, float)
        return (self.rot[0, 0] * x + self.rot[0, 1] * y + self.trans[0],
                self.rot[1, 0] * x + self.rot[1, 1] * y + self.trans[1])

    def world_to_map(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        dx, dy = np.asarray(x, float) - self.trans[0], np.asarray(y, float) - self.trans[1]
        return (self.rot[0, 0] * dx + self.rot[1, 0] * dy, self.rot[0, 1] * dx + self.rot[1, 1] * dy)

    def to_dict(self) -> dict:
        return {"source": self.source, "frames": self.frames, "rms_m": self.rms_m,
                "rotation_rad": float(np.arctan2(self.rot[1, 0], self.rot[0, 0])),
                "translation_m": [float(v) for v in self.trans], "note": self.note}


def map_world_alignment(poses) -> FrameAlignment:
    """The map-frame -> world-frame alignment from a version's pose table
    (:class:`mapstore.layout.PoseTable`): the estimated frame positions against the
    ground truth of their drive logs (``ground_truth.csv`` beside each source's ``path``,
    interpolated at the frames' times), fitted with :func:`align_se2`. Logs whose ground
    truth is missing or unreadable are left out; with none left, the identity (the map's
    frame taken as the world's) and a note saying so."""
    from pipeline.errors import BadInput

    est, gt, used, skipped = [], [], [], []
    for i, src in enumerate(poses.sources):
        sel = poses.source == i
        path = Path(str(src.get("path", ""))) / "ground_truth.csv"
        if not sel.any():
            continue
        if not path.is_file():
            skipped.append(f"{src.get('log_id', i)}: no {path}")
            continue
        try:
            g = ground_truth_at(poses.t[sel], path)
        except BadInput as e:
            skipped.append(f"{src.get('log_id', i)}: {e}")
            continue
        est.append(poses.pose[sel, :2])
        gt.append(g[:, :2])
        used.append(str(src.get("log_id", i)))
    if not est:
        why = "; ".join(skipped) if skipped else "the version has no pose table"
        return FrameAlignment(np.eye(2), np.zeros(2), "identity", 0, None,
                              f"no ground truth reachable ({why}): map frame taken as the world frame")
    e, g = np.concatenate(est), np.concatenate(gt)
    rot, trans = align_se2(e, g)
    rms = float(np.sqrt(np.mean(np.sum((e @ rot.T + trans - g) ** 2, axis=1))))
    note = f"estimated poses of {', '.join(used)} aligned to their ground_truth.csv"
    if skipped:
        note += f" (left out: {'; '.join(skipped)})"
    return FrameAlignment(rot, trans, "ground_truth", len(e), rms, note)


@dataclass
class TruthMask:
    """A simulator's ground-truth change mask: ``mask`` (bool) on the world raster ``grid``,
    and the change list (``changes.json`` beside it: kind, bbox_m, area_m2; may be empty)."""

    path: Path
    mask: np.ndarray
    grid: object
    changes: list[dict] = field(default_factory=list)


def read_truth_mask(path: str | Path) -> TruthMask:
    """Read ``MASK`` (an image, 0 = unchanged, > 127 = changed) with ``grid.json`` (its
    :meth:`MapGrid.to_attrs`) and the optional ``changes.json`` in the same directory, as
    :mod:`pipeline.simulate.floor` writes them. Raises :class:`BadInput` naming the file."""
    from mapstore.grid import MapGrid
    from pipeline.errors import BadInput
    from pipeline.images import read_grey
    from pipeline.simulate.floor import CHANGES_FILE, GRID_FILE

    path = Path(path)
    if not path.is_file():
        raise BadInput(path, "truth mask not found")
    img = read_grey(path)
    gpath = path.parent / GRID_FILE
    try:
        grid = MapGrid.from_attrs(json.loads(gpath.read_text()))
    except FileNotFoundError:
        raise BadInput(gpath, "missing: the truth mask's raster description (MapGrid attributes)") from None
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
        raise BadInput(gpath, f"invalid raster description: {e}") from None
    if img.shape != grid.shape:
        raise BadInput(path, f"is {img.shape[1]} x {img.shape[0]} px, {gpath.name} says {grid.width} x {grid.height}")
    changes: list[dict] = []
    cpath = path.parent / CHANGES_FILE
    if cpath.is_file():
        try:
            changes = json.loads(cpath.read_text())
            if not isinstance(changes, list) or not all(isinstance(c, dict) and len(c.get("bbox_m", [])) == 4
                                                        for c in changes):
                raise ValueError("expected a list of {kind, bbox_m: [xmin, ymin, xmax, ymax], area_m2}")
        except (json.JSONDecodeError, ValueError) as e:
            raise BadInput(cpath, f"invalid change list: {e}") from None
    return TruthMask(path, img > 127.0, grid, changes)


def truth_on_map(truth: TruthMask, map_grid, box: tuple[int, int, int, int], alignment: FrameAlignment) -> np.ndarray:
    """The truth mask resampled (nearest) onto level-0 pixels ``box`` = (row0, row1, col0,
    col1) of ``map_grid``: each map pixel is placed in the world by ``alignment`` and looks
    up the mask there (False outside it)."""
    import cv2

    r0, r1, c0, c1 = box
    if r1 <= r0 or c1 <= c0:
        return np.zeros((max(r1 - r0, 0), max(c1 - c0, 0)), bool)
    cols, rows = np.meshgrid(np.arange(c0, c1, dtype=np.float64), np.arange(r0, r1, dtype=np.float64))
    x, y = alignment.map_to_world(*map_grid.pixel_to_world(cols, rows))
    mc, mr = truth.grid.world_to_pixel(x, y)
    out = cv2.remap(truth.mask.astype(np.uint8), mc.astype(np.float32), mr.astype(np.float32),
                    cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out > 0


def _truth_box(truth: TruthMask, map_grid, alignment: FrameAlignment, margin: int = 2) -> tuple[int, int, int, int]:
    """Level-0 pixel box of ``map_grid`` holding every changed pixel of the truth mask."""
    rows, cols = np.nonzero(truth.mask)
    if not len(rows):
        return 0, 1, 0, 1  # one pixel, holding no change (never an empty raster: cv2 cannot label one)
    corners_c = np.array([cols.min() - 0.5, cols.max() + 0.5, cols.max() + 0.5, cols.min() - 0.5])
    corners_r = np.array([rows.min() - 0.5, rows.min() - 0.5, rows.max() + 0.5, rows.max() + 0.5])
    mc, mr = map_grid.world_to_pixel(*alignment.world_to_map(*truth.grid.pixel_to_world(corners_c, corners_r)))
    r0, r1 = max(int(np.floor(mr.min())) - margin, 0), min(int(np.ceil(mr.max())) + margin + 1, map_grid.height)
    c0, c1 = max(int(np.floor(mc.min())) - margin, 0), min(int(np.ceil(mc.max())) + margin + 1, map_grid.width)
    if r1 <= r0 or c1 <= c0:
        return 0, 1, 0, 1  # the changes lie outside the map
    return r0, r1, c0, c1


@dataclass
class TruthChange:
    """One ground-truth change (a connected component of the truth mask on the map grid).

    Attributes:
        id: 1.. in decreasing area.
        kinds: the simulator's kinds of the changes in it (from changes.json; several when
            changes overlap; empty when unknown).
        area_m2: its area on the map grid.
        bbox_m: (xmin, ymin, xmax, ymax) in the map's frame (metres).
        observed_fraction: share of its pixels the TO version observed.
        status: "detected", "missed" or "unobserved" (observed_fraction below the minimum).
        recall: share of its observed pixels inside detected regions.
        iou: intersection over union with the regions matched to it, both restricted to
            the observed pixels (None when unobserved).
        regions: ids of the detected regions matched to it.
    """

    id: int
    kinds: list[str]
    area_m2: float
    bbox_m: tuple[float, float, float, float]
    observed_fraction: float
    status: str
    recall: float
    iou: float | None
    regions: list[int]


@dataclass
class TruthReport:
    """Per-change detection against the truth mask, and the detected regions matching none."""

    alignment: FrameAlignment
    changes: list[TruthChange]
    false_regions: list[dict]
    min_observed_fraction: float
    min_recall: float

    def to_dict(self) -> dict:
        obs = [c for c in self.changes if c.status != "unobserved"]
        return {
            "alignment": self.alignment.to_dict(),
            "definitions": {
                "observed": "pixels of the changed tiles that both versions cover and whose values differ "
                            "(closed): the pixels the TO version's frames looked at",
                "unobserved": f"a change with less than {self.min_observed_fraction:g} of its pixels observed",
                "detected": f"an observed change with at least {self.min_recall:g} of its observed pixels in "
                            "detected regions",
                "iou": "over observed pixels: change vs the union of the regions matched to it (a region is "
                       "matched to the change it overlaps most)",
                "false_region": "a detected region overlapping no change",
            },
            "changes": [{"id": c.id, "kinds": c.kinds, "area_m2": c.area_m2, "bbox_m": list(c.bbox_m),
                         "observed_fraction": c.observed_fraction, "status": c.status, "recall": c.recall,
                         "iou": c.iou, "regions": c.regions} for c in self.changes],
            "false_regions": self.false_regions,
            "summary": {
                "changes": len(self.changes),
                "observed": len(obs),
                "detected": sum(c.status == "detected" for c in self.changes),
                "missed": sum(c.status == "missed" for c in self.changes),
                "unobserved": sum(c.status == "unobserved" for c in self.changes),
                "min_iou_observed": min((c.iou for c in obs if c.iou is not None), default=None),
                "false_regions": len(self.false_regions),
                "max_false_area_cm2": max((f["area_m2"] * 1e4 for f in self.false_regions), default=0.0),
            },
        }


def _change_kinds(truth: TruthMask, labels: np.ndarray, box: tuple[int, int, int, int], map_grid,
                  alignment: FrameAlignment) -> dict[int, list[str]]:
    """Truth component -> kinds of the listed changes whose bounding box holds most of it."""
    out: dict[int, list[str]] = {}
    r0, _, c0, _ = box
    for ch in truth.changes:
        xa, ya, xb, yb = (float(v) for v in ch["bbox_m"])
        mx, my = alignment.world_to_map(np.array([xa, xb, xb, xa]), np.array([ya, ya, yb, yb]))
        mc, mr = map_grid.world_to_pixel(mx, my)
        a0, a1 = max(int(np.floor(mr.min())) - r0, 0), max(int(np.ceil(mr.max())) + 1 - r0, 0)
        b0, b1 = max(int(np.floor(mc.min())) - c0, 0), max(int(np.ceil(mc.max())) + 1 - c0, 0)
        sub = labels[a0:a1, b0:b1]
        ids = np.bincount(sub.ravel(), minlength=1)
        ids[0] = 0
        if ids.any():
            out.setdefault(int(ids.argmax()), []).append(str(ch.get("kind", "?")))
    return out


def evaluate_diff(result, truth: TruthMask, alignment: FrameAlignment, *, min_observed_fraction: float = 0.5,
                  min_recall: float = 0.5) -> TruthReport:
    """A map diff (:class:`mapstore.diff.DiffResult`) against a ground-truth change mask.

    The truth is resampled onto the TO grid (:func:`truth_on_map`) over the box holding
    it; its 8-connected components are the changes. A change is *observed* in the
    pixels the diff marks observed (see :mod:`mapstore.diff`); one with less than
    ``min_observed_fraction`` of its pixels observed is *unobserved* (the TO version did not
    look there: not a miss). A detected region is matched to the change it overlaps most
    (observed pixels); regions overlapping none are *false regions*. IoU and recall are
    computed over observed pixels only.
    """
    import cv2

    grid = result.grid
    s2 = grid.pixel_size ** 2
    box = _truth_box(truth, grid, alignment)
    tmask = truth_on_map(truth, grid, box, alignment)
    n, tl, stats, _ = cv2.connectedComponentsWithStats(tmask.astype(np.uint8), connectivity=8)
    order = np.argsort(-stats[1:, cv2.CC_STAT_AREA], kind="stable") + 1
    relabel = np.zeros(n, np.int32)
    relabel[order] = np.arange(1, n)
    tl = relabel[tl]
    stats = stats[np.r_[0, order]]
    nreg = len(result.regions) + 1
    obs_t = np.zeros(n, np.int64)  # observed pixels per change
    obs_r = np.zeros(nreg, np.int64)  # observed pixels per region
    pair = np.zeros((n, nreg), np.int64)  # observed pixels in change k and region r
    r0, r1, c0, c1 = box
    for cl in result.clusters:
        q0, q1, p0, p1 = cl.box
        obs_r += np.bincount(cl.labels[cl.observed], minlength=nreg)[:nreg]
        a0, a1, b0, b1 = max(q0, r0), min(q1, r1), max(p0, c0), min(p1, c1)
        if a0 >= a1 or b0 >= b1:
            continue
        t = tl[a0 - r0 : a1 - r0, b0 - c0 : b1 - c0]
        lab = cl.labels[a0 - q0 : a1 - q0, b0 - p0 : b1 - p0]
        o = cl.observed[a0 - q0 : a1 - q0, b0 - p0 : b1 - p0]
        obs_t += np.bincount(t[o], minlength=n)[:n]
        pair += np.bincount((t[o].astype(np.int64) * nreg + lab[o]), minlength=n * nreg)[: n * nreg].reshape(n, nreg)
    # each region to the change it overlaps most
    matched: dict[int, list[int]] = {}
    false_regions = []
    for reg in result.regions:
        col = pair[1:, reg.id]
        if col.any():
            matched.setdefault(int(col.argmax()) + 1, []).append(reg.id)
        else:
            false_regions.append({"id": reg.id, "area_m2": reg.area_m2, "bbox_m": list(reg.bbox_m),
                                  "centroid_m": list(reg.centroid_m)})
    kinds = _change_kinds(truth, tl, box, grid, alignment)
    changes = []
    for k in range(1, n):
        x, y, w, h, area = (int(v) for v in stats[k])
        regs = sorted(matched.get(k, []))
        inter = int(pair[k, regs].sum()) if regs else 0
        frac = float(obs_t[k] / area)
        recall = float(inter / obs_t[k]) if obs_t[k] else 0.0
        if frac < min_observed_fraction:
            status, iou = "unobserved", None
        else:
            union = obs_t[k] + int(obs_r[regs].sum()) - inter
            iou = float(inter / union) if union else 0.0
            status = "detected" if recall >= min_recall else "missed"
        xa, ya = grid.pixel_to_world(c0 + x - 0.5, r0 + y + h - 0.5)
        xb, yb = grid.pixel_to_world(c0 + x + w - 0.5, r0 + y - 0.5)
        changes.append(TruthChange(k, kinds.get(k, []), area * s2, (float(xa), float(ya), float(xb), float(yb)),
                                   frac, status, recall, iou, regs))
    return TruthReport(alignment, changes, false_regions, float(min_observed_fraction), float(min_recall))
