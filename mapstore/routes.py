"""Omnidirectional route panoramas (ORP, Yagi et al. (2005)) in a map: the ``/routes`` part of the layout.

Part of the public map contract (:mod:`mapstore.layout` holds the floor part; the same rules:
extend by adding, never change). A map may hold any number of routes beside its floor::

    /routes                     group (absent when the map has no route)
    /routes/<route_id>          group; route_id matches ROUTE_ID_PATTERN ([A-Za-z0-9_.-]{1,64});
                                attrs "mosaicmap_route": {
                                  "s0_m": path length of row 0 (metres; negative once a
                                          refresh grew the route before its first row),
                                  "spacing_m": row spacing along the path (metres),
                                  "samples_per_degree": azimuth samples per degree,
                                  "rows": M, "azimuths": A (= 360 * samples_per_degree),
                                  "rows_per_chunk": rows per stored chunk,
                                  "horizon_band_deg": elevation band averaged into a line (deg),
                                  "version": publish version that last wrote the route,
                                  "sources": [{"log_id", "path", "sha256", "frames", "version"}],
                                  "lines": "uint8 grey levels at the horizon (elevation 0)",
                                  ... further keys of the build (e.g. "runs", "registration")}
    /routes/<id>/lines          uint8 (M, A): row i = the horizon line at path length
                                s0_m + i * spacing_m; column j = camera azimuth
                                j / samples_per_degree degrees (0 = vehicle +x, counter-clockwise);
                                chunks (rows_per_chunk, A), zstd; fill 0.
    /routes/<id>/poses          float32 (M, 3): the route pose of each row, x, y [m], theta
                                [rad], world frame (:mod:`mapstore.grid`); chunks
                                (rows_per_chunk, 3), zstd; fill NaN.

At 1 sample/degree and 10 cm spacing a kilometre is 10 000 rows: 3.6 MB of lines plus
0.12 MB of poses before compression.

Nothing here depends on icechunk or on the tracker: functions take a :class:`zarr.Group`
(a repository session's root, a plain zarr directory, a bundle). The tracker turns a
:class:`RouteRecord` into its ``tracker.orp.ORP``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np
import zarr

__all__ = [
    "ROUTES_GROUP",
    "ROUTE_ATTRS",
    "ROUTE_ID_PATTERN",
    "DEFAULT_ROWS_PER_CHUNK",
    "RouteRecord",
    "check_route_id",
    "list_routes",
    "write_route",
    "read_route",
    "route_attrs",
    "delete_route",
]

ROUTES_GROUP = "routes"
ROUTE_ATTRS = "mosaicmap_route"
ROUTE_ID_PATTERN = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
DEFAULT_ROWS_PER_CHUNK = 1000
LINES_DESCRIPTION = "uint8 grey levels at the horizon (elevation 0)"


def check_route_id(route_id: str) -> str:
    """``route_id`` if it is a valid route name, else ValueError saying what is wrong."""
    if not isinstance(route_id, str) or not ROUTE_ID_PATTERN.match(route_id) or route_id in (".", ".."):
        raise ValueError(f"route id {route_id!r}: use 1-64 of the characters A-Z a-z 0-9 _ . -")
    return route_id


@dataclass
class RouteRecord:
    """One stored route panorama.

    Attributes:
        lines: ``(M, A)`` uint8 horizon lines; row ``i`` at path length ``s0_m + i * spacing_m``.
        poses: ``(M, 3)`` float32 route poses x, y (metres), theta (radians), world frame.
        s0_m: path length of row 0 (metres). spacing_m: row spacing (metres).
        samples_per_degree: azimuth samples per degree (``A = 360 * samples_per_degree``).
        horizon_band_deg: elevation band averaged into each line (degrees).
        version: publish version that last wrote the route (0 = not yet published).
        sources: the drive logs merged into it (log_id, path, sha256, frames, version).
        meta: further JSON-able keys stored in the attributes (build figures, runs).
    """

    lines: np.ndarray
    poses: np.ndarray
    s0_m: float = 0.0
    spacing_m: float = 0.1
    samples_per_degree: float = 1.0
    horizon_band_deg: float = 1.0
    version: int = 0
    sources: list[dict] = field(default_factory=list)
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.lines = np.asarray(self.lines)
        self.poses = np.asarray(self.poses, np.float32).reshape(-1, 3)
        if self.lines.ndim != 2 or self.lines.dtype != np.uint8:
            raise ValueError(f"route lines must be a 2-D uint8 array, got {self.lines.dtype} {self.lines.shape}")
        if len(self.lines) != len(self.poses):
            raise ValueError(f"route has {len(self.lines)} lines and {len(self.poses)} poses")
        if not (self.spacing_m > 0 and self.samples_per_degree > 0):
            raise ValueError("route spacing_m and samples_per_degree must be positive")
        a = 360.0 * self.samples_per_degree
        if abs(a - round(a)) > 1e-9 or int(round(a)) != self.lines.shape[1]:
            raise ValueError(f"route lines have {self.lines.shape[1]} azimuths, samples_per_degree "
                             f"{self.samples_per_degree} needs {a:g}")
        if len(self.poses) and not np.isfinite(self.poses).all():
            raise ValueError("route poses hold NaN or infinite values")

    @property
    def rows(self) -> int:
        return int(len(self.lines))

    @property
    def length_m(self) -> float:
        """Path length covered by the rows (metres)."""
        return self.spacing_m * max(self.rows - 1, 0)

    @property
    def s(self) -> np.ndarray:
        """``(M,)`` path length of each row (metres)."""
        return self.s0_m + self.spacing_m * np.arange(self.rows)

    def attrs(self, rows_per_chunk: int) -> dict:
        """The ``mosaicmap_route`` attributes of this record."""
        out = dict(self.meta)
        out.update({
            "s0_m": float(self.s0_m), "spacing_m": float(self.spacing_m),
            "samples_per_degree": float(self.samples_per_degree), "rows": self.rows,
            "azimuths": int(self.lines.shape[1]), "rows_per_chunk": int(rows_per_chunk),
            "horizon_band_deg": float(self.horizon_band_deg), "version": int(self.version),
            "sources": [dict(s) for s in self.sources], "lines": LINES_DESCRIPTION,
        })
        return out


def list_routes(root: zarr.Group) -> list[str]:
    """Sorted ids of the routes the map holds (empty when it has none)."""
    if ROUTES_GROUP not in root:
        return []
    group = root[ROUTES_GROUP]
    return sorted(name for name, _ in group.groups())


def write_route(root: zarr.Group, route_id: str, record: RouteRecord, *, zstd_level: int = 3,
                rows_per_chunk: int = DEFAULT_ROWS_PER_CHUNK) -> None:
    """Write (or replace) ``/routes/<route_id>`` with ``record`` (every array written whole)."""
    check_route_id(route_id)
    if rows_per_chunk < 1:
        raise ValueError(f"rows_per_chunk must be positive, got {rows_per_chunk}")
    routes = root.require_group(ROUTES_GROUP)
    if route_id in routes:
        del routes[route_id]
    g = routes.create_group(route_id)
    m, a = record.lines.shape
    rows = max(1, min(m, rows_per_chunk))
    codec = zarr.codecs.ZstdCodec(level=int(zstd_level))
    lines = g.create_array("lines", shape=(m, a), dtype="uint8", chunks=(rows, a), fill_value=0,
                           compressors=codec, dimension_names=["s", "azimuth"])
    poses = g.create_array("poses", shape=(m, 3), dtype="float32", chunks=(rows, 3), fill_value=float("nan"),
                           compressors=codec, dimension_names=["s", "pose"])
    if m:
        lines[...] = record.lines
        poses[...] = record.poses
    g.attrs[ROUTE_ATTRS] = record.attrs(rows)


def read_route(root: zarr.Group, route_id: str) -> RouteRecord:
    """The stored route ``route_id``; KeyError when the map has no such route, ValueError when
    it is malformed (naming what is wrong)."""
    check_route_id(route_id)
    if ROUTES_GROUP not in root or route_id not in root[ROUTES_GROUP]:
        raise KeyError(f"the map has no route {route_id!r} (routes: {', '.join(list_routes(root)) or 'none'})")
    g = root[ROUTES_GROUP][route_id]
    attrs = dict(g.attrs.get(ROUTE_ATTRS) or {})
    for key in ("s0_m", "spacing_m", "samples_per_degree"):
        if key not in attrs:
            raise ValueError(f"routes/{route_id}: attribute {ROUTE_ATTRS}.{key} is missing")
    for name in ("lines", "poses"):
        if name not in g:
            raise ValueError(f"routes/{route_id}: array {name} is missing")
    known = {"s0_m", "spacing_m", "samples_per_degree", "horizon_band_deg", "version", "sources", "rows",
             "azimuths", "rows_per_chunk", "lines"}
    return RouteRecord(
        lines=g["lines"][...], poses=g["poses"][...], s0_m=float(attrs["s0_m"]),
        spacing_m=float(attrs["spacing_m"]), samples_per_degree=float(attrs["samples_per_degree"]),
        horizon_band_deg=float(attrs.get("horizon_band_deg", 1.0)), version=int(attrs.get("version", 0)),
        sources=list(attrs.get("sources", [])), meta={k: v for k, v in attrs.items() if k not in known})


def route_attrs(root: zarr.Group, route_id: str) -> dict:
    """The ``mosaicmap_route`` attributes of ``/routes/<route_id>`` (version, sources, spacing,
    ...) without reading its arrays; KeyError when the map has no such route."""
    check_route_id(route_id)
    if ROUTES_GROUP not in root or route_id not in root[ROUTES_GROUP]:
        raise KeyError(f"the map has no route {route_id!r}")
    return dict(root[ROUTES_GROUP][route_id].attrs.get(ROUTE_ATTRS) or {})


def delete_route(root: zarr.Group, route_id: str) -> None:
    """Remove ``/routes/<route_id>`` (KeyError when absent)."""
    check_route_id(route_id)
    if ROUTES_GROUP not in root or route_id not in root[ROUTES_GROUP]:
        raise KeyError(f"the map has no route {route_id!r}")
    del root[ROUTES_GROUP][route_id]
