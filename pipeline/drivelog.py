"""Drive log v1: read with full validation, and write (a public contract).

The drive log is what a recorder (or an importer, ``pipeline/importers/``) hands the
pipeline: the format below is a public contract. Extend it only by adding optional keys,
tables or columns, never by changing what is here (and bump ``format_version`` when that
cannot be avoided). A drive log is a directory::

    drive.toml          format_version = 1, [log] id, [camera] model and calibration,
                        optional [route] id (the route an omni log drives)
    frames.csv          t,image          (seconds; image path relative to the log)
    odometry.csv        t,x,y,theta      (seconds, metres, metres, radians; odometry frame)
    ground_truth.csv    t,x,y,theta      optional, for evaluation only (the build never reads it)

Optional extension column of frames.csv: ``height_m``, the camera's height above the floor
for that frame (metres; cameras whose height varies, e.g. aerial). With intrinsics, ingest
then rectifies each frame at its own height; ``[camera] height_m`` stays the reference.

Poses follow :mod:`mapstore.grid`: the image centre's position on the floor and the heading.
Camera ``model = "downward"`` takes either ``pixel_size_m`` (the images are already
rectified ground images) or intrinsics ``fx, fy, cx, cy`` (pixels) with ``height_m`` (the
optical centre's height above the floor, metres) and optional distortion ``k1, k2, p1, p2``
(OpenCV's radial-tangential model). Optional for both: ``vignetting = [v1, v2]`` (observed =
true x (1 + v1 r^2 + v2 r^4), r the distance from the principal point in focal lengths, or
for rectified images in half-diagonals) and ``flat_field`` (an image file, relative to the
log, of the sensor's relative gain).

Camera ``model = "omni"`` takes ``mirror = "hyperboloid"`` (Yagi et al. (2005): ``a_m, b_m``
metres, ``f_px, cx, cy`` pixels, ``height_m`` of the viewpoint) or ``mirror = "mei"``
(``cv2.omnidir``'s unified model: ``xi, fx, fy, cx, cy``, optional ``skew, k1, k2, p1, p2``,
``height_m``), both with optional ``rim_radius_px, hole_radius_px`` (the image annulus) and
the optional ``vignetting`` (r in rim radii) and ``flat_field``; :mod:`tracker.omnicam`
owns the models. Ingest turns each omni frame into a bird's-eye floor frame and a horizon
line (:mod:`pipeline.omni_ingest`).

Optional ``[route] id = "..."`` names the route the log drives (route panoramas:
runs with the same id are merged into one route); validated with
:func:`mapstore.routes.check_route_id`, :attr:`DriveLog.route_id` (None when absent).

Optional ``[odometry]`` table: the prior's own error model (``error_gradient``,
``sigma_floor_m``, ``heading_sigma_per_m``, ``heading_sigma_floor_rad``; any subset, each
overriding the build's ``[optimize] odometry_*`` default for this log), or ``kind =
"absolute"`` with ``sigma_m`` and ``heading_sigma_rad``: each frame's own absolute prior (a
microscope stage's positions, GPS);
:mod:`pipeline.odometry_model`, :attr:`DriveLog.odometry_model` ({} when absent).

Every reader error is a :class:`~pipeline.errors.BadInput` naming the file, line or field.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mapstore.routes import check_route_id
from pipeline.odometry_model import parse_odometry_table
from pipeline.config import dump_toml, read_toml
from pipeline.errors import BadInput, one_line
from pipeline.fsutil import write_text_atomic
from tracker.omnicam import CameraFieldError, OmniCamera, camera_from_table

FORMAT_VERSION = 1
CAMERA_MODELS = ("downward", "omni")
POSE_COLUMNS = ("t", "x", "y", "theta")
FRAME_COLUMNS = ("t", "image")
# Odometry beyond these is not a vehicle's: |x|, |y| in metres (10,000 km), |theta| in
# radians (an unwrapped heading of 160,000 turns). A wild row is refused at ingest, naming its
# line, before it can overflow pixel coordinates downstream.
MAX_ODOMETRY_M = 1.0e7
MAX_ODOMETRY_RAD = 1.0e6
# Calibration beyond these is a typo, not a camera: focal lengths (pixels), and the
# radial-tangential distortion coefficients' magnitude (normalized image coordinates).
MAX_FOCAL_PX = 1.0e6
MAX_DISTORTION = 10.0
# A log id names the log in CSV files, reports and the map's sources: printable, no comma,
# at most this many characters.
MAX_LOG_ID_CHARS = 200


@dataclass(frozen=True)
class CameraSpec:
    """A camera's calibration as declared in ``drive.toml`` (pixels, metres).

    ``model = "downward"``: the fields below. ``model = "omni"``: ``omni`` holds the
    catadioptric model (:mod:`tracker.omnicam`: ``mirror = "hyperboloid"`` or ``"mei"``);
    only ``vignetting`` and ``flat_field`` of the fields below apply, and the downward
    geometry (``rectified``, ``ground_pixel_size``, ``camera_matrix``) raises ValueError
    (:mod:`pipeline.omni_ingest` owns the omni geometry at ingest).
    """

    model: str = "downward"
    pixel_size_m: float | None = None
    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    height_m: float | None = None
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    vignetting: tuple[float, float] | None = None
    flat_field: str | None = None
    omni: OmniCamera | None = None

    @property
    def is_omni(self) -> bool:
        """True for ``model = "omni"`` (the geometry is :attr:`omni`)."""
        return self.model == "omni"

    def _downward_only(self) -> None:
        if self.is_omni:
            raise ValueError('camera model "omni" has no downward geometry (see pipeline.omni_ingest)')

    @property
    def rectified(self) -> bool:
        """True when the images are already rectified ground images (``pixel_size_m``)."""
        self._downward_only()
        return self.pixel_size_m is not None

    @property
    def ground_pixel_size(self) -> tuple[float, float]:
        """Native ground sampling (metres per pixel) along image columns and rows."""
        if self.rectified:
            return self.pixel_size_m, self.pixel_size_m
        return self.height_m / self.fx, self.height_m / self.fy

    def camera_matrix(self) -> np.ndarray:
        self._downward_only()
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def distortion(self) -> np.ndarray:
        return np.array([self.k1, self.k2, self.p1, self.p2])

    def to_toml_dict(self) -> dict:
        if self.is_omni:
            d = self.omni.to_toml_dict()
            if self.vignetting is not None:
                d["vignetting"] = list(self.vignetting)
            if self.flat_field is not None:
                d["flat_field"] = self.flat_field
            return d
        d = {"model": self.model}
        if self.rectified:
            d["pixel_size_m"] = self.pixel_size_m
        else:
            d.update(fx=self.fx, fy=self.fy, cx=self.cx, cy=self.cy, height_m=self.height_m)
            d.update(k1=self.k1, k2=self.k2, p1=self.p1, p2=self.p2)
        if self.vignetting is not None:
            d["vignetting"] = list(self.vignetting)
        if self.flat_field is not None:
            d["flat_field"] = self.flat_field
        return d


@dataclass
class DriveLog:
    """A validated drive log.

    Attributes:
        path: the log directory.
        log_id: ``[log] id`` from drive.toml, else the directory name.
        camera: the calibration.
        frame_t: (N,) frame times, seconds, strictly increasing.
        frame_images: N image paths relative to ``path``.
        odometry: (M, 4) ``t, x, y, theta`` in the log's odometry frame, t strictly increasing.
        meta: any other tables of drive.toml (kept, not interpreted).
        frame_heights: (N,) per-frame camera heights (metres) from the optional
            ``height_m`` column of frames.csv, or None.
        route_id: ``[route] id`` of drive.toml (the route an omni log drives), or None.
        odometry_model: the optional ``[odometry]`` table of drive.toml: the prior's error
            model (:mod:`pipeline.odometry_model`), {} when absent.
    """

    path: Path
    log_id: str
    camera: CameraSpec
    frame_t: np.ndarray
    frame_images: list[str]
    odometry: np.ndarray
    meta: dict = field(default_factory=dict)
    frame_heights: np.ndarray | None = None
    route_id: str | None = None
    odometry_model: dict = field(default_factory=dict)

    def image_path(self, i: int) -> Path:
        return self.path / self.frame_images[i]

    def files(self) -> list[Path]:
        """Every file the build reads from this log (for input checksums)."""
        out = [self.path / "drive.toml", self.path / "frames.csv", self.path / "odometry.csv"]
        if self.camera.flat_field:
            out.append(self.path / self.camera.flat_field)
        out.extend(self.image_path(i) for i in range(len(self.frame_images)))
        return out


# --- reading -----------------------------------------------------------------------------


def parse_number(path: Path, lineno: int, name: str, text: str) -> float:
    """Field ``name`` of line ``lineno`` of ``path`` as a finite float; BadInput naming them otherwise."""
    try:
        v = float(text)
    except ValueError:
        raise BadInput(f"{path}:{lineno}", f"{name} is not a number: {text.strip()!r}") from None
    if not math.isfinite(v):
        raise BadInput(f"{path}:{lineno}", f"{name} is {text.strip()} (must be finite)")
    return v


def _open_text(path: Path):
    """``path`` opened as UTF-8 text (a leading byte-order mark is skipped); :class:`BadInput`
    naming the file when it is missing or cannot be opened."""
    try:
        return open(path, newline="", encoding="utf-8-sig")
    except FileNotFoundError:
        raise BadInput(path, "file not found") from None
    except IsADirectoryError:
        raise BadInput(path, "is a directory, not a file") from None
    except OSError as e:
        raise BadInput(path, f"cannot open: {e.strerror}") from None


def _rows(path: Path, columns: tuple[str, ...]):
    """Yield ``(lineno, fields)`` of a CSV with exactly ``columns`` as its header (UTF-8, an
    optional byte-order mark skipped)."""
    f = _open_text(path)
    with f:
        reader = csv.reader(f)
        try:
            header = next(reader, None)
            if header is None:
                raise BadInput(path, "file is empty (expected a header line " + ",".join(columns) + ")")
            header = [h.strip() for h in header]
            if tuple(header[: len(columns)]) != columns:
                raise BadInput(
                    f"{path}:1", f"header must start with {','.join(columns)}, got {one_line(','.join(header))}"
                )
            for fields in reader:
                lineno = reader.line_num
                if not fields or all(not x.strip() for x in fields):
                    continue
                if len(fields) != len(header):
                    raise BadInput(
                        f"{path}:{lineno}", f"expected {len(header)} fields, got {len(fields)}"
                    )
                yield lineno, fields
        except UnicodeDecodeError:
            raise BadInput(path, "not a UTF-8 text file") from None
        except csv.Error as e:
            raise BadInput(f"{path}:{reader.line_num}", f"unparsable CSV: {e}") from None


def _check_increasing(path: Path, lineno: int, t: float, prev: tuple[int, float] | None) -> None:
    if prev is None:
        return
    prev_line, prev_t = prev
    if t == prev_t:
        raise BadInput(f"{path}:{lineno}", f"duplicate timestamp {t!r} (also on line {prev_line})")
    if t < prev_t:
        raise BadInput(
            f"{path}:{lineno}",
            f"timestamp {t!r} goes backwards (line {prev_line} has {prev_t!r})",
        )


def read_pose_csv(path: str | Path, *, min_rows: int = 1, bounded: bool = False) -> np.ndarray:
    """Read a ``t,x,y,theta`` CSV (odometry, ground truth, poses) -> (N, 4) float64.

    Validates: header, field count, finite numbers, strictly increasing t; with ``bounded``
    also |x|, |y| <= :data:`MAX_ODOMETRY_M` and |theta| <= :data:`MAX_ODOMETRY_RAD`.
    """
    path = Path(path)
    rows = []
    prev = None
    for lineno, fields in _rows(path, POSE_COLUMNS):
        vals = [parse_number(path, lineno, name, fields[i]) for i, name in enumerate(POSE_COLUMNS)]
        if bounded:
            for name, v, cap in (("x", vals[1], MAX_ODOMETRY_M), ("y", vals[2], MAX_ODOMETRY_M),
                                 ("theta", vals[3], MAX_ODOMETRY_RAD)):
                if abs(v) > cap:
                    raise BadInput(f"{path}:{lineno}", f"{name} = {fields[POSE_COLUMNS.index(name)].strip()} is "
                                                       f"beyond any vehicle's odometry (|{name}| <= {cap:g})")
        _check_increasing(path, lineno, vals[0], prev)
        prev = (lineno, vals[0])
        rows.append(vals)
    if len(rows) < min_rows:
        raise BadInput(path, f"has {len(rows)} data rows, need at least {min_rows}")
    return np.asarray(rows, dtype=float).reshape(-1, 4)


def check_inside(log_dir: Path, rel: str, where: str, what: str, *, follow_symlinks: bool) -> Path:
    """``log_dir / rel`` for a path field of a drive log, checked: relative, no ``..``, and
    (unless ``follow_symlinks``) resolving inside ``log_dir`` (a symlinked file or directory
    leading outside is refused); :class:`BadInput` at ``where`` otherwise, also for a name the
    file system refuses (too long). ``what`` names the field in messages ("image")."""
    if Path(rel).is_absolute() or ".." in Path(rel).parts:
        raise BadInput(where, f"{what} path {rel!r} must be relative to the log and stay inside it")
    full = log_dir / rel
    try:
        if not full.is_file():
            raise BadInput(where, f"{what} {rel!r} not found")
        if not follow_symlinks:
            target = full.resolve(strict=True)
            if not target.is_relative_to(log_dir.resolve(strict=True)):
                raise BadInput(where, f"{what} {rel!r} resolves outside the log directory (to {str(target)!r}); "
                                      "set [ingest] follow_symlinks = true to allow links out of the log")
    except OSError as e:
        raise BadInput(where, f"{what} path {rel!r}: {e.strerror or e}") from None
    return full


def _read_frames(path: Path, log_dir: Path, *, follow_symlinks: bool = False
                 ) -> tuple[np.ndarray, list[str], np.ndarray | None]:
    ts, images, heights = [], [], []
    prev = None
    with _open_text(path) as f:
        try:
            header = [h.strip() for h in f.readline().split(",")]
        except UnicodeDecodeError:
            raise BadInput(path, "not a UTF-8 text file") from None
    h_col = header.index("height_m") if "height_m" in header else None
    for lineno, fields in _rows(path, FRAME_COLUMNS):
        t = parse_number(path, lineno, "t", fields[0])
        if h_col is not None:
            h = parse_number(path, lineno, "height_m", fields[h_col])
            if h <= 0:
                raise BadInput(f"{path}:{lineno}", f"height_m must be positive, got {h!r}")
            heights.append(h)
        _check_increasing(path, lineno, t, prev)
        prev = (lineno, t)
        image = fields[1].strip()
        if not image:
            raise BadInput(f"{path}:{lineno}", "image path is empty")
        if "\0" in image:
            raise BadInput(f"{path}:{lineno}", f"image path {image!r} holds a NUL character")
        check_inside(log_dir, image, f"{path}:{lineno}", "image", follow_symlinks=follow_symlinks)
        ts.append(t)
        images.append(image)
    if not ts:
        raise BadInput(path, "has no frames")
    return np.asarray(ts, dtype=float), images, (np.asarray(heights, float) if h_col is not None else None)


def parse_camera(path: Path, table: object) -> CameraSpec:
    """Validate a ``[camera]`` table read from ``path`` (errors name ``path[camera.field]``)."""
    where = f"{path}[camera]"
    if not isinstance(table, dict):
        raise BadInput(where, "missing table [camera]")
    model = table.get("model")
    if model is None:
        raise BadInput(f"{path}[camera.model]", "missing calibration field")
    if model not in CAMERA_MODELS:
        raise BadInput(
            f"{path}[camera.model]", f"unknown camera model {model!r} (known: {', '.join(CAMERA_MODELS)})"
        )

    def num(name: str, *, required: bool, positive: bool = False, default: float | None = None):
        if name not in table:
            if required:
                raise BadInput(f"{path}[camera.{name}]", "missing calibration field")
            return default
        v = table[name]
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise BadInput(f"{path}[camera.{name}]", f"must be a number, got {v!r}")
        v = float(v)
        if not math.isfinite(v):
            raise BadInput(f"{path}[camera.{name}]", f"is {v} (must be finite)")
        if positive and v <= 0:
            raise BadInput(f"{path}[camera.{name}]", f"must be positive, got {v}")
        return v

    if model == "omni":
        try:
            omni = camera_from_table(table, ignore=("model", "vignetting", "flat_field"))
        except CameraFieldError as e:
            raise BadInput(f"{path}[camera.{e.field}]", e.what) from None
        kw = {"model": model, "omni": omni}
        _photometric(path, table, kw)
        return CameraSpec(**kw)

    intrinsics = ("fx", "fy", "cx", "cy", "height_m")
    has_ps = "pixel_size_m" in table
    has_k = any(k in table for k in intrinsics)
    if has_ps and has_k:
        raise BadInput(where, "give either pixel_size_m (rectified images) or intrinsics fx, fy, cx, cy, height_m, not both")
    if not has_ps and not has_k:
        raise BadInput(f"{path}[camera.pixel_size_m]", "missing calibration field (or give fx, fy, cx, cy, height_m)")
    kw: dict = {"model": model}
    if has_ps:
        kw["pixel_size_m"] = num("pixel_size_m", required=True, positive=True)
        for k in ("k1", "k2", "p1", "p2"):
            if k in table:
                raise BadInput(f"{path}[camera.{k}]", "distortion is only meaningful with intrinsics, not with pixel_size_m")
    else:
        for k in ("fx", "fy", "height_m"):
            kw[k] = num(k, required=True, positive=True)
        for k in ("cx", "cy"):
            kw[k] = num(k, required=True)
        for k in ("k1", "k2", "p1", "p2"):
            kw[k] = num(k, required=False, default=0.0)
        _check_intrinsics(path, kw)
    _photometric(path, table, kw)
    known = set(intrinsics) | {"model", "pixel_size_m", "k1", "k2", "p1", "p2", "vignetting", "flat_field"}
    unknown = sorted(set(table) - known)
    if unknown:
        raise BadInput(f"{path}[camera.{unknown[0]}]", "unknown calibration field")
    return CameraSpec(**kw)


def _check_intrinsics(path: Path, kw: dict) -> None:
    """Focal lengths and distortion within what a camera can have (:data:`MAX_FOCAL_PX`,
    :data:`MAX_DISTORTION`, pixels square within a factor 100): beyond them the rectifier's
    tables degenerate (a 1e12 px focal length, k1 = 1e6)."""
    for k in ("fx", "fy", "cx", "cy"):
        if abs(kw[k]) > MAX_FOCAL_PX:
            raise BadInput(f"{path}[camera.{k}]", f"{kw[k]:g} px is beyond any camera (at most {MAX_FOCAL_PX:g} px)")
    ratio = kw["fx"] / kw["fy"]
    if not 0.01 <= ratio <= 100.0:
        raise BadInput(f"{path}[camera.fx]", f"fx / fy = {ratio:g}: pixels more than 100x longer than wide")
    for k in ("k1", "k2", "p1", "p2"):
        if abs(kw[k]) > MAX_DISTORTION:
            raise BadInput(f"{path}[camera.{k}]", f"distortion coefficient {kw[k]:g} is beyond any lens "
                                                  f"(|{k}| <= {MAX_DISTORTION:g})")


def check_log_id(log_id: str) -> str:
    """A log id: non-empty, at most :data:`MAX_LOG_ID_CHARS` characters, printable (no control
    character or newline), no comma (it is a CSV field); ValueError saying what is wrong."""
    if not log_id.strip():
        raise ValueError("log id is empty")
    if len(log_id) > MAX_LOG_ID_CHARS:
        raise ValueError(f"log id has {len(log_id)} characters (at most {MAX_LOG_ID_CHARS})")
    bad = next((c for c in log_id if not c.isprintable() or c == ","), None)
    if bad is not None:
        raise ValueError(f"log id {log_id!r} holds {bad!r} (a log id is printable text without commas)")
    return log_id


def _is_file(path: Path) -> bool:
    """``path.is_file()``, False also for a name the file system refuses (too long)."""
    try:
        return path.is_file()
    except OSError:
        return False


def _photometric(path: Path, table: dict, kw: dict) -> None:
    """Validate the optional ``vignetting`` and ``flat_field`` fields into ``kw`` (any model)."""
    if "vignetting" in table:
        v = table["vignetting"]
        if (
            not isinstance(v, list)
            or len(v) != 2
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)
        ):
            raise BadInput(f"{path}[camera.vignetting]", f"must be two finite numbers [v1, v2], got {v!r}")
        kw["vignetting"] = (float(v[0]), float(v[1]))
    if "flat_field" in table:
        ff = table["flat_field"]
        if not isinstance(ff, str) or not _is_file(path.parent / ff):
            raise BadInput(f"{path}[camera.flat_field]", f"flat-field image {ff!r} not found")
        kw["flat_field"] = ff


def read_drive_log(log_dir: str | Path, *, follow_symlinks: bool = False) -> DriveLog:
    """Read and validate a drive log directory. Raises :class:`BadInput` naming the culprit.

    Every file the log names (images, ``flat_field``) and its own files must resolve inside
    the log directory unless ``follow_symlinks`` (``[ingest] follow_symlinks``)."""
    log_dir = Path(log_dir)
    try:
        if not log_dir.is_dir():
            raise BadInput(log_dir, "drive log directory not found")
    except OSError as e:
        raise BadInput(log_dir, f"drive log directory: {e.strerror or e}") from None
    toml_path = log_dir / "drive.toml"
    for name in ("drive.toml", "frames.csv", "odometry.csv"):  # nothing is read from outside the log
        if (log_dir / name).is_symlink():
            check_inside(log_dir, name, str(log_dir / name), "file", follow_symlinks=follow_symlinks)
    meta = read_toml(toml_path, missing="file not found (not a drive log?)")
    version = meta.get("format_version")
    if version is None:
        raise BadInput(f"{toml_path}[format_version]", "missing field")
    if version != FORMAT_VERSION:
        raise BadInput(
            f"{toml_path}[format_version]",
            f"unknown format version {version!r} (this mosaicmap reads {FORMAT_VERSION})",
        )
    camera = parse_camera(toml_path, meta.get("camera"))
    if camera.flat_field is not None:
        check_inside(log_dir, camera.flat_field, f"{toml_path}[camera.flat_field]", "flat-field image",
                     follow_symlinks=follow_symlinks)
    log_table = meta.get("log", {})
    log_id = str(log_table.get("id", log_dir.resolve().name)) if isinstance(log_table, dict) else log_dir.name
    try:
        check_log_id(log_id)
    except ValueError as e:
        raise BadInput(f"{toml_path}[log.id]", f"{e}; set [log] id to a plain name") from None
    frame_t, images, heights = _read_frames(log_dir / "frames.csv", log_dir, follow_symlinks=follow_symlinks)
    if heights is not None and camera.is_omni:
        raise BadInput(log_dir / "frames.csv", "column height_m is for downward cameras, not model = \"omni\"")
    if heights is not None and camera.rectified:
        raise BadInput(log_dir / "frames.csv", "column height_m needs a camera with intrinsics, not pixel_size_m")
    route_id = parse_route_id(toml_path, meta)
    odometry_model = parse_odometry_table(toml_path, meta)
    odometry = read_pose_csv(log_dir / "odometry.csv", min_rows=2, bounded=True)
    extra = {k: v for k, v in meta.items() if k not in ("format_version", "camera", "log", "route", "odometry")}
    return DriveLog(log_dir, log_id, camera, frame_t, images, odometry, extra, heights, route_id, odometry_model)


def parse_route_id(path: Path, meta: dict) -> str | None:
    """The optional ``[route] id`` of a drive.toml read from ``path`` (None when there is no
    ``[route]`` table); :class:`BadInput` naming ``path[route.id]`` when it is invalid."""
    if "route" not in meta:
        return None
    table = meta["route"]
    if not isinstance(table, dict):
        raise BadInput(f"{path}[route]", "must be a table with id = \"...\"")
    if "id" not in table:
        raise BadInput(f"{path}[route.id]", "missing field (the route's name)")
    unknown = sorted(set(table) - {"id"})
    if unknown:
        raise BadInput(f"{path}[route.{unknown[0]}]", "unknown field (the [route] table holds id only)")
    try:
        return check_route_id(table["id"])
    except ValueError as e:
        raise BadInput(f"{path}[route.id]", str(e)) from None


# --- writing -----------------------------------------------------------------------------


def write_pose_csv(path: str | Path, poses: np.ndarray) -> None:
    """Write an (N, 4) ``t,x,y,theta`` array (seconds, metres, radians), full precision."""
    poses = np.asarray(poses, dtype=float).reshape(-1, 4)
    lines = [",".join(POSE_COLUMNS)]
    lines += [f"{t!r},{x!r},{y!r},{th!r}" for t, x, y, th in poses.tolist()]
    write_text_atomic(path, "\n".join(lines) + "\n")


def write_drive_log(
    log_dir: str | Path,
    camera: CameraSpec,
    frame_t: np.ndarray,
    frame_images: list[str],
    odometry: np.ndarray,
    *,
    ground_truth: np.ndarray | None = None,
    log_id: str | None = None,
    extra: dict | None = None,
    route_id: str | None = None,
) -> None:
    """Write the text files of a drive log into ``log_dir`` (images are the caller's).

    ``extra`` adds tables to drive.toml (e.g. ``[simulation]`` provenance); ``route_id``
    writes ``[route] id`` (validated: ValueError when it is not a valid route id).
    """
    log_dir = Path(log_dir)
    log_dir.mkdir(parents=True, exist_ok=True)
    doc: dict = {"format_version": FORMAT_VERSION}
    if log_id is not None:
        doc["log"] = {"id": log_id}
    doc["camera"] = camera.to_toml_dict()
    if route_id is not None:
        doc["route"] = {"id": check_route_id(route_id)}
    doc.update(extra or {})
    header = "# mosaicmap drive log v1 (format: docs/drive-log.md)\n"
    write_text_atomic(log_dir / "drive.toml", header + dump_toml(doc))
    lines = ["t,image"] + [f"{t!r},{img}" for t, img in zip(np.asarray(frame_t, float).tolist(), frame_images)]
    write_text_atomic(log_dir / "frames.csv", "\n".join(lines) + "\n")
    write_pose_csv(log_dir / "odometry.csv", odometry)
    if ground_truth is not None:
        write_pose_csv(log_dir / "ground_truth.csv", ground_truth)
