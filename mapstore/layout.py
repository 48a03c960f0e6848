"""The layout of a mosaicmap map: a public contract.

A map is a zarr v3 hierarchy. It lives in an icechunk repository (one snapshot per
published version, see :mod:`mapstore.repository`), but nothing here depends on icechunk:
every function takes a :class:`zarr.Group`, so the same layout can be written to (or read
from) a plain local zarr directory, e.g. an export bundle. Other tools (the tracker, OME-Zarr
viewers, anyone's scripts) read maps through this contract; extend it only by adding
arrays or attribute keys, never by changing what is here (and bump ``format_version``
when that cannot be avoided).

Coordinates follow :mod:`mapstore.grid` (the one owner of them): world x, y in metres on
the floor plane; a map grid is north up, columns along +x, rows along -y, and ``(x0, y0)``
is the world position of the *centre* of pixel (row 0, col 0).

Hierarchy::

    /                       group; attrs:
                              format = "mosaicmap-map", format_version = 1,
                              map_id = uuid4 hex (fixed when the map is created),
                              created = ISO 8601 UTC time of creation,
                              geo_reference (optional; maps of geotagged logs only) =
                                {"crs": "EPSG:4326", "origin_latitude", "origin_longitude"
                                 (WGS 84 degrees of the world origin), "projection"}: the
                                world frame is a local east/north tangent plane around the
                                origin (:class:`mapstore.grid.GeoReference` converts);
                                absent: x, y are local metres with no place on Earth
    /floor                  group; attrs:
                              "ome": OME-Zarr 0.5 multiscales (see below)
                              "mosaicmap": {
                                 "grid": level-0 MapGrid.to_attrs() (x0_m, y0_m, pixel_size_m,
                                         width_px, height_px, axes, origin),
                                 "chunk_px", "shard_px", "layer_cell_px", "zstd_level",
                                 "levels": K + 1,
                                 "intensity": "uint8 grey levels, 0 = no data (covered pixels 1..255)",
                                 "version": publish sequence number (int, 0 before the first
                                            publish; the n-th publish writes n)}
    /floor/0 .. /floor/K    uint8 intensity, shape (rows, cols) = grid.level(k).shape;
                            chunks chunk_px x chunk_px inside shards shard_px x shard_px
                            (an array smaller than a shard is held in one partial shard;
                            shard_px == chunk_px means no sharding codec: one stored object
                            per chunk, as in an export bundle),
                            zstd(zstd_level), fill_value 0 (= no data),
                            dimension_names ["y", "x"].
                            Level k is grid.level(k) = grid.coarsened(2**k): its pixel
                            (r, c) covers level-0 pixels [2^k r, 2^k (r+1)) x [2^k c, 2^k (c+1)).
                            K is the smallest k >= 0 whose level fits in one chunk
                            (max(rows, cols) <= chunk_px).
    /floor/layers/coverage    uint16, shape grid.coarsened(layer_cell_px).shape; fill 0;
                              the most frames that saw any pixel of the cell (count; with
                              the seam composite: the frames whose weight covers the cell's
                              centre, at least those blended into any of its pixels).
    /floor/layers/texture     float32, same shape; fill NaN (no data); Kelly's (2000) texture
                              score at the cell ((grey levels / px)^2).
    /floor/layers/uniqueness  float32, same shape; fill NaN; Kelly's (2000) uniqueness C1 - C2
                              at the cell (correlation difference, < 0.2 is poor), measured
                              on level 1 with the template, radius and exclusion halved (the
                              default, [render] uniqueness_level = 1), the cells whose level-1
                              value lies in [render] uniqueness_recheck ([0.1, 0.3)) measured
                              again on level 0 (so on the same side of 0.2 as on level 0 for
                              99.99-100 % of the cells on the render benchmarks' floors); or
                              on level 0 (uniqueness_level = 0).
                            The three cell layers have chunks of (shard_px / layer_cell_px)^2
                            cells: one chunk per level-0 shard, no sharding codec; zstd.
    /floor/layers/updated     int32, shape (ceil(rows / chunk_px), ceil(cols / chunk_px)):
                              one element per level-0 chunk (tile); fill 0; the publish
                              version that last wrote the tile (0 = never).
                              Chunks of (shard_px / chunk_px)^2 tiles: one per level-0 shard.
                            Every layer array's attrs: "grid" (its own MapGrid.to_attrs(), so
                            cell (r, c) is centred at grid.pixel_to_world(c, r)), "cell_px"
                            (level-0 pixels per cell side), "description", "units".
    /floor/poses            group; the frames the map was built from, one row per frame:
                              pose    (N, 3) float64  x, y [m], theta [rad], world frame
                              sigma   (N, 3) float64  1-sigma of pose (m, m, rad); NaN = unknown
                              t       (N,)   float64  frame time [s] in its log's clock
                              source  (N,)   int32    index into attrs["sources"]
                              frame   (N,)   int32    row of the frame in that log's frames.csv
                              version (N,)   int32    publish version that added the frame
                            attrs "sources": list of {"log_id", "path", "sha256", "frames",
                            "version"} (one per drive log; frames = rows it contributed).

    /routes/<id>            route panoramas of omnidirectional cameras: their part of
                            the contract is :mod:`mapstore.routes` (lines, poses, attributes).

A partial copy of a map (an export bundle, :mod:`mapstore.bundle`) holds only some levels
and layers and no poses: its ``mosaicmap`` attributes then add ``"levels_present"`` (level
indices held; ``levels`` stays the map's K + 1) and ``"layers_present"`` (layer names held),
and the OME datasets list the levels held. Absent keys mean everything is held.

OME-Zarr 0.5 metadata of /floor (``attrs["ome"]``)::

    {"version": "0.5",
     "multiscales": [{"name": "intensity",
                      "axes": [{"name": "y", "type": "space", "unit": "meter"},
                               {"name": "x", "type": "space", "unit": "meter"}],
                      "datasets": [{"path": "<k>",
                                    "coordinateTransformations": grid.level(k).ome_transformations()},
                                   ... for k = 0 .. K]}]}

OME's ``y`` axis is the world's -y (rows run south): element (r, c) of level k lies at
OME (y, x) = (-y0_k + r s_k, x0_k + c s_k) metres (see :meth:`MapGrid.ome_transformations`).

Writing: zarr rewrites a whole shard when any part of it is written, and two writers of one
shard lose data silently. Writers must own whole shards: iterate with :func:`shard_slices`.

Growing: a map grows only to the right and bottom (:meth:`MapGrid.extended`); the origin
and pixel size never change, so existing pixels keep their coordinates and data
(:func:`resize_floor`). Coarser levels' pixels straddling the old edge must be re-rendered
by the writer, as must new levels added when K grows.

This module depends on numpy and zarr only (never on the batch pipeline).
"""

from __future__ import annotations

import csv
import io
import os
import uuid
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
import zarr

from mapstore.grid import GeoReference, MapGrid

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "LAYERS",
    "LayoutSpec",
    "FloorInfo",
    "PoseTable",
    "levels_for",
    "create_floor",
    "resize_floor",
    "read_floor",
    "write_poses",
    "read_poses",
    "shard_slices",
    "set_version",
    "tiles_shape",
    "GEO_ATTR",
    "read_geo_reference",
    "write_geo_reference",
]

FORMAT = "mosaicmap-map"
GEO_ATTR = "geo_reference"  # root attribute: the world frame's place on Earth (optional)
FORMAT_VERSION = 1
FLOOR = "floor"
LAYERS_GROUP = "floor/layers"
POSES_GROUP = "floor/poses"
INTENSITY_DESCRIPTION = "uint8 grey levels, 0 = no data (covered pixels 1..255)"

# name -> (dtype, fill value, per-cell layer (else per tile), description, units)
LAYERS: dict[str, tuple[str, float | int, bool, str, str]] = {
    "coverage": ("uint16", 0, True,
                 "most frames that saw a pixel of the cell (0 = no data)", "frames"),
    "texture": ("float32", float("nan"), True,
                "Kelly (2000) texture score at the cell (NaN = no data)", "(grey levels / px)^2"),
    "uniqueness": ("float32", float("nan"), True,
                   "Kelly (2000) uniqueness C1 - C2 at the cell: best minus second-best correlation "
                   "peak (NaN = no data; < 0.2 is poor); measured on level 1 when [render] uniqueness_level "
                   "is 1, the cells within [render] uniqueness_recheck of 0.2 on level 0", "correlation"),
    "updated": ("int32", 0, False,
                "publish version that last wrote the level-0 tile (chunk); 0 = never", "version"),
}

POSE_ARRAYS: dict[str, tuple[str, int, float | int]] = {
    # name -> (dtype, columns (0 = 1-D), fill value)
    "pose": ("float64", 3, float("nan")),
    "sigma": ("float64", 3, float("nan")),
    "t": ("float64", 0, float("nan")),
    "source": ("int32", 0, -1),
    "frame": ("int32", 0, -1),
    "version": ("int32", 0, 0),
}
POSE_CHUNK_ROWS = 65536


# --- the storage spec --------------------------------------------------------------------


@dataclass(frozen=True)
class LayoutSpec:
    """Chunking and compression of a map (configs/floor.toml [map]).

    Attributes:
        chunk_px: side of a chunk (pixels): the unit a reader fetches (a tile).
        shard_px: side of a shard (pixels): the unit written (one stored object); a
            multiple of ``chunk_px`` and of ``layer_cell_px``.
        layer_cell_px: level-0 pixels per side of a cell of the reduced layers.
        zstd_level: zstd compression level of every array.
    """

    chunk_px: int
    shard_px: int
    layer_cell_px: int
    zstd_level: int

    def __post_init__(self) -> None:
        for name in ("chunk_px", "shard_px", "layer_cell_px", "zstd_level"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"map.{name} must be a positive integer, got {v!r}")
        if self.shard_px % self.chunk_px:
            raise ValueError(f"map.shard_px ({self.shard_px}) must be a multiple of map.chunk_px ({self.chunk_px})")
        if self.shard_px % self.layer_cell_px:
            raise ValueError(
                f"map.shard_px ({self.shard_px}) must be a multiple of map.layer_cell_px ({self.layer_cell_px})")
        if self.zstd_level > 22:
            raise ValueError(f"map.zstd_level must be 1..22, got {self.zstd_level}")

    @classmethod
    def from_config(cls, cfg_map: dict) -> "LayoutSpec":
        """From the ``[map]`` table of the configuration (keys chunk_px, shard_px,
        layer_cell_px, zstd_level). Raises ValueError naming a missing or invalid key."""
        kw = {}
        for name in ("chunk_px", "shard_px", "layer_cell_px", "zstd_level"):
            if name not in cfg_map:
                raise ValueError(f"map.{name} is missing")
            kw[name] = cfg_map[name]
        return cls(**kw)

    def to_attrs(self) -> dict:
        return {"chunk_px": int(self.chunk_px), "shard_px": int(self.shard_px),
                "layer_cell_px": int(self.layer_cell_px), "zstd_level": int(self.zstd_level)}

    @property
    def compressor(self) -> zarr.codecs.ZstdCodec:
        return zarr.codecs.ZstdCodec(level=int(self.zstd_level))

    @property
    def layer_chunk_cells(self) -> int:
        """Cells per side of a cell-layer chunk (one chunk per level-0 shard)."""
        return self.shard_px // self.layer_cell_px

    @property
    def tiles_per_shard(self) -> int:
        """Level-0 chunks (tiles) per side of a shard."""
        return self.shard_px // self.chunk_px


# --- geometry helpers --------------------------------------------------------------------


def levels_for(grid: MapGrid, chunk_px: int) -> int:
    """Number of pyramid levels K + 1: K is the smallest k >= 0 with ``grid.level(k)``
    fitting in one chunk (``max(rows, cols) <= chunk_px``)."""
    k = 0
    while max(grid.level(k).shape) > chunk_px:
        k += 1
    return k + 1


def tiles_shape(grid: MapGrid, chunk_px: int) -> tuple[int, int]:
    """Shape of the per-tile ``updated`` layer: level-0 chunks along rows and columns."""
    rows, cols = grid.shape
    return -(-rows // chunk_px), -(-cols // chunk_px)


def shard_slices(grid_shape: tuple[int, int], shard_px: int) -> Iterator[tuple[tuple[int, int], tuple[slice, slice]]]:
    """The shards of an array of ``grid_shape`` (rows, cols), row-major.

    Yields ``((i, j), (rows, cols))``: shard index and the slices of the array it holds
    (clipped at the array's bottom and right edges). A writer owning whole shards writes
    exactly these slices.
    """
    rows, cols = (int(v) for v in grid_shape)
    for i in range(-(-rows // shard_px)):
        for j in range(-(-cols // shard_px)):
            yield (i, j), (slice(i * shard_px, min((i + 1) * shard_px, rows)),
                           slice(j * shard_px, min((j + 1) * shard_px, cols)))


# --- attributes --------------------------------------------------------------------------


def _ome_attrs(grid: MapGrid, levels: int | Sequence[int]) -> dict:
    """OME multiscales over levels 0 .. levels - 1 (an int), or over the listed levels."""
    held = range(levels) if isinstance(levels, (int, np.integer)) else levels
    return {
        "version": "0.5",
        "multiscales": [{
            "name": "intensity",
            "axes": [{"name": "y", "type": "space", "unit": "meter"},
                     {"name": "x", "type": "space", "unit": "meter"}],
            "datasets": [{"path": str(k), "coordinateTransformations": grid.level(k).ome_transformations()}
                         for k in held],
        }],
    }


def _mosaicmap_attrs(grid: MapGrid, spec: LayoutSpec, levels: int, version: int) -> dict:
    return {"grid": grid.to_attrs(), **spec.to_attrs(), "levels": int(levels),
            "intensity": INTENSITY_DESCRIPTION, "version": int(version)}


def _layer_grid(grid: MapGrid, spec: LayoutSpec, name: str) -> tuple[MapGrid, int]:
    """The grid of a layer (its cells) and its cell size in level-0 pixels."""
    cell = spec.layer_cell_px if LAYERS[name][2] else spec.chunk_px
    return grid.coarsened(cell), cell


def _layer_attrs(grid: MapGrid, spec: LayoutSpec, name: str) -> dict:
    lgrid, cell = _layer_grid(grid, spec, name)
    _, _, _, description, units = LAYERS[name]
    return {"grid": lgrid.to_attrs(), "cell_px": int(cell), "description": description, "units": units}


# --- creating, growing, reading ----------------------------------------------------------


def _create_level(floor: zarr.Group, k: int, grid: MapGrid, spec: LayoutSpec) -> None:
    sharded = spec.shard_px != spec.chunk_px  # equal: no sharding codec (one object per chunk)
    floor.create_array(
        str(k), shape=grid.level(k).shape, dtype="uint8", chunks=(spec.chunk_px, spec.chunk_px),
        shards=(spec.shard_px, spec.shard_px) if sharded else None, compressors=spec.compressor, fill_value=0,
        dimension_names=["y", "x"])


def create_floor(root: zarr.Group, grid: MapGrid, spec: LayoutSpec, map_id: str | None = None, *,
                 levels: Sequence[int] | None = None, layers: Sequence[str] | None = None,
                 poses: bool = True) -> None:
    """Create an empty floor map in ``root`` (root attrs when absent, /floor with every
    level, layer and the empty poses group). Raises ValueError when ``root`` already holds
    a floor or belongs to another format.

    A partial copy (an export bundle) passes ``levels`` (indices to create), ``layers``
    (names to create) and ``poses=False``; the attributes then say what is held (see the
    module docstring). ``spec.shard_px == spec.chunk_px`` creates unsharded levels.
    """
    attrs = root.attrs.asdict()
    if attrs.get("format") not in (None, FORMAT):
        raise ValueError(f"zarr group holds format {attrs.get('format')!r}, not a {FORMAT}")
    if FLOOR in root:
        raise ValueError("the map already holds a floor (grow it with resize_floor)")
    if "format" not in attrs:
        root.attrs.update({
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "map_id": map_id or uuid.uuid4().hex,
            "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        })
    levels_total = levels_for(grid, spec.chunk_px)
    held = list(range(levels_total)) if levels is None else sorted({int(k) for k in levels})
    if any(not 0 <= k < levels_total for k in held):
        raise ValueError(f"levels {held} outside the pyramid's 0..{levels_total - 1}")
    held_layers = list(LAYERS) if layers is None else [name for name in LAYERS if name in set(layers)]
    if layers is not None and set(layers) - set(LAYERS):
        raise ValueError(f"unknown layer(s) {sorted(set(layers) - set(LAYERS))} (layers: {', '.join(LAYERS)})")
    floor = root.create_group(FLOOR)
    for k in held:
        _create_level(floor, k, grid, spec)
    group = floor.create_group("layers")
    for name in held_layers:
        dtype, fill, per_cell, _, _ = LAYERS[name]
        lgrid, _ = _layer_grid(grid, spec, name)
        side = spec.layer_chunk_cells if per_cell else spec.tiles_per_shard
        group.create_array(
            name, shape=lgrid.shape, dtype=dtype, chunks=(side, side), compressors=spec.compressor,
            fill_value=fill, dimension_names=["y", "x"], attributes=_layer_attrs(grid, spec, name))
    if poses:
        write_poses(root, PoseTable.empty())
    meta = _mosaicmap_attrs(grid, spec, levels_total, 0)
    if levels is not None or layers is not None:
        meta.update({"levels_present": held, "layers_present": held_layers})
    floor.attrs.update({"ome": _ome_attrs(grid, held), "mosaicmap": meta})


def resize_floor(root: zarr.Group, new_grid: MapGrid) -> None:
    """Grow the floor to ``new_grid``: same origin and pixel size, at least as large
    (as :meth:`MapGrid.extended` returns). Existing data is kept; levels are added (empty)
    when K grows; the OME and mosaicmap attributes are rewritten.

    Raises ValueError when ``new_grid`` moves the origin, changes the pixel size or shrinks.
    """
    info = read_floor(root)
    old, spec = info.grid, info.spec
    if (new_grid.x0, new_grid.y0, new_grid.pixel_size) != (old.x0, old.y0, old.pixel_size):
        raise ValueError(
            f"cannot resize the floor to a grid with origin ({new_grid.x0}, {new_grid.y0}) m and pixel size "
            f"{new_grid.pixel_size} m: the map's are ({old.x0}, {old.y0}) m and {old.pixel_size} m")
    if new_grid.width < old.width or new_grid.height < old.height:
        raise ValueError(
            f"cannot shrink the floor from {old.width} x {old.height} px to {new_grid.width} x {new_grid.height} px")
    floor = root[FLOOR]
    levels = max(levels_for(new_grid, spec.chunk_px), info.levels)
    for k in range(levels):
        if str(k) in floor:
            arr = floor[str(k)]
            if arr.shape != new_grid.level(k).shape:
                arr.resize(new_grid.level(k).shape)
        else:
            _create_level(floor, k, new_grid, spec)
    for name in LAYERS:
        arr = floor["layers"][name]
        shape = _layer_grid(new_grid, spec, name)[0].shape
        if arr.shape != shape:
            arr.resize(shape)
        arr.attrs.update(_layer_attrs(new_grid, spec, name))
    floor.attrs.update({"ome": _ome_attrs(new_grid, levels),
                        "mosaicmap": _mosaicmap_attrs(new_grid, spec, levels, info.version)})


@dataclass
class FloorInfo:
    """What :func:`read_floor` finds: level-0 grid, storage spec, number of levels (K + 1),
    publish version (0 before the first publish) and the map's id."""

    grid: MapGrid
    spec: LayoutSpec
    levels: int
    version: int
    map_id: str
    created: str = ""

    def level_grid(self, k: int) -> MapGrid:
        return self.grid.level(k)

    def layer_grid(self, name: str) -> MapGrid:
        """The grid of layer ``name`` (cells for coverage/texture/uniqueness, tiles for updated)."""
        if name not in LAYERS:
            raise ValueError(f"unknown layer {name!r} (layers: {', '.join(LAYERS)})")
        return _layer_grid(self.grid, self.spec, name)[0]


def read_floor(root: zarr.Group) -> FloorInfo:
    """Read and check the floor's description. Raises ValueError when ``root`` is not a
    mosaicmap map, its format version is unknown, or it holds no floor."""
    attrs = root.attrs.asdict()
    if attrs.get("format") != FORMAT:
        raise ValueError(f"not a mosaicmap map (root attribute format is {attrs.get('format')!r}, "
                         f"expected {FORMAT!r})")
    fv = attrs.get("format_version")
    if fv != FORMAT_VERSION:
        raise ValueError(f"unknown map format version {fv!r} (this mosaicmap reads version {FORMAT_VERSION})")
    if FLOOR not in root:
        raise ValueError("the map holds no floor")
    meta = root[FLOOR].attrs.get("mosaicmap")
    if not isinstance(meta, dict):
        raise ValueError("floor attributes lack the 'mosaicmap' description")
    try:
        grid = MapGrid.from_attrs(meta["grid"])
        spec = LayoutSpec(int(meta["chunk_px"]), int(meta["shard_px"]), int(meta["layer_cell_px"]),
                          int(meta.get("zstd_level", 3)))
        levels, version = int(meta["levels"]), int(meta["version"])
    except (KeyError, TypeError) as e:
        raise ValueError(f"floor attribute 'mosaicmap' is incomplete: {e}") from None
    return FloorInfo(grid, spec, levels, version, str(attrs.get("map_id", "")), str(attrs.get("created", "")))


def set_version(root: zarr.Group, n: int) -> None:
    """Record publish version ``n`` in the floor's attributes (mosaicmap.version)."""
    floor = root[FLOOR]
    meta = dict(floor.attrs["mosaicmap"])
    meta["version"] = int(n)
    floor.attrs.update({"mosaicmap": meta})


def read_geo_reference(root: zarr.Group) -> GeoReference | None:
    """The map's geographic reference (root attribute ``geo_reference``), None when the map
    has none (its x, y are local metres). ValueError when the attribute is malformed."""
    attrs = root.attrs.get(GEO_ATTR)
    if attrs is None:
        return None
    if not isinstance(attrs, dict):
        raise ValueError(f"root attribute {GEO_ATTR} must be an object, got {type(attrs).__name__}")
    return GeoReference.from_attrs(attrs)


def write_geo_reference(root: zarr.Group, ref: GeoReference) -> None:
    """Record ``ref`` as the map's geographic reference (root attribute ``geo_reference``)."""
    root.attrs.update({GEO_ATTR: ref.to_attrs()})


# --- poses -------------------------------------------------------------------------------


@dataclass
class PoseTable:
    """The frames a map was built from (one row per frame; see the module docstring).

    Attributes:
        pose: (N, 3) x, y [m], theta [rad] in the world frame.
        sigma: (N, 3) 1-sigma of pose (m, m, rad); NaN = unknown.
        t: (N,) frame time [s].
        source: (N,) index into ``sources``.
        frame: (N,) row of the frame in its log's frames.csv.
        version: (N,) publish version that added the frame.
        sources: one dict per drive log: log_id, path, sha256, frames, version.
    """

    pose: np.ndarray
    sigma: np.ndarray
    t: np.ndarray
    source: np.ndarray
    frame: np.ndarray
    version: np.ndarray
    sources: list[dict] = field(default_factory=list)

    def __post_init__(self) -> None:
        for name, (dtype, cols, _) in POSE_ARRAYS.items():
            arr = np.asarray(getattr(self, name), dtype=dtype)
            if cols:
                arr = arr.reshape(-1, cols)
            else:
                arr = arr.reshape(-1)
            setattr(self, name, arr)
        n = len(self.t)
        for name in POSE_ARRAYS:
            if len(getattr(self, name)) != n:
                raise ValueError(f"pose table: {name} has {len(getattr(self, name))} rows, t has {n}")
        if n and (self.source.min() < 0 or self.source.max() >= len(self.sources)):
            raise ValueError(f"pose table: source indices must lie in 0..{len(self.sources) - 1}")

    @classmethod
    def empty(cls) -> "PoseTable":
        return cls(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int32),
                   np.zeros(0, np.int32), np.zeros(0, np.int32), [])

    def __len__(self) -> int:
        return len(self.t)

    def to_csv(self, path: str | Path) -> None:
        """Write ``t,x,y,theta,log_id,frame,sigma_x,sigma_y,sigma_theta,version`` (seconds,
        metres, radians; floats in repr form, unknown sigma as nan), atomically."""
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(["t", "x", "y", "theta", "log_id", "frame", "sigma_x", "sigma_y", "sigma_theta", "version"])
        ids = [str(s.get("log_id", i)) for i, s in enumerate(self.sources)]
        for i in range(len(self)):
            w.writerow([repr(float(self.t[i])), *(repr(float(v)) for v in self.pose[i]), ids[self.source[i]],
                        int(self.frame[i]), *(repr(float(v)) for v in self.sigma[i]), int(self.version[i])])
        _write_text_atomic(Path(path), buf.getvalue())


def write_poses(root: zarr.Group, table: PoseTable) -> None:
    """Replace the pose table of the map (every array of /floor/poses, written whole)."""
    if POSES_GROUP in root:
        del root[POSES_GROUP]
    group = root.require_group(FLOOR).create_group("poses")
    n = len(table)
    rows = max(1, min(n, POSE_CHUNK_ROWS))
    for name, (dtype, cols, fill) in POSE_ARRAYS.items():
        shape = (n, cols) if cols else (n,)
        chunks = (rows, cols) if cols else (rows,)
        arr = group.create_array(name, shape=shape, dtype=dtype, chunks=chunks, fill_value=fill,
                                 compressors=zarr.codecs.ZstdCodec(level=3))
        if n:
            arr[...] = getattr(table, name)
    group.attrs.update({"sources": [_jsonable(s) for s in table.sources]})


def read_poses(root: zarr.Group) -> PoseTable:
    """The map's pose table (an empty one when the map has none)."""
    if POSES_GROUP not in root:
        return PoseTable.empty()
    group = root[POSES_GROUP]
    values = {name: group[name][...] if name in group else None for name in POSE_ARRAYS}
    if any(v is None for v in values.values()):
        missing = [k for k, v in values.items() if v is None]
        raise ValueError(f"floor/poses lacks array(s) {', '.join(missing)}")
    return PoseTable(**values, sources=list(group.attrs.get("sources", [])))


# --- small helpers -----------------------------------------------------------------------


def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    if isinstance(obj, Path):
        return str(obj)
    return obj


def _write_text_atomic(path: Path, text: str) -> None:
    """Write under a temporary name beside ``path`` and rename into place (no half files)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".tmp-{path.name}-{os.getpid()}")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
