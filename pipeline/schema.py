"""The schema of the configuration: every table of ``configs/*.toml`` and the frozen dataclass
that gives its keys' types and ranges (:mod:`mapstore.knobs`).

:func:`pipeline.config.load_config` checks the defaults and a user file against it;
:func:`settings` turns a (checked) table of the configuration into its dataclass, the one way
code reads configuration values by attribute.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, TypeVar

from mapstore.bundle import BundleLimits
from mapstore.diff import RouteDiffParams
from mapstore.knobs import from_table, knob
from pipeline import schema_diff as sd
from pipeline import schema_export as se
from pipeline import schema_floor as sf
from pipeline import schema_omni as so
from pipeline import schema_simulate as ss
from tracker.floor import FloorTrackerParams
from tracker.orp import ORPParams
from tracker.orp_reloc import ORPRelocParams
from tracker.orp_session import ORPSessionParams
from tracker.reloc import RelocParams
from tracker.session import SessionParams

__all__ = ["TABLES", "TrackerBundleConfig", "settings", "check_table", "scalars"]

T = TypeVar("T")


@dataclass(frozen=True)
class TrackerBundleConfig(BundleLimits):
    """``[tracker.bundle]``: the limits of :class:`mapstore.bundle.BundleLimits` and the public
    keys (KEY.pub paths or their one-line text) a vehicle bundle must be signed by."""

    trusted_keys: tuple[str, ...] = knob(default=())


#: Dotted table name -> its dataclass. Every table of configs/*.toml has one (tested).
TABLES: dict[str, type] = {
    # configs/floor.toml
    "map": sf.MapConfig,
    "render": sf.RenderConfig,
    "publish": sf.PublishConfig,
    "ingest": sf.IngestConfig,
    "ingest.flatfield": sf.FlatFieldConfig,
    "ingest.ground_plane": sf.GroundPlaneConfig,
    "ingest.photometry": sf.PhotometryConfig,
    "ingest.quality": sf.QualityConfig,
    "build": sf.BuildConfig,
    "optimize": sf.OptimizeConfig,
    "register": sf.RegisterConfig,
    # configs/diff.toml
    "diff": sd.DiffConfig,
    "diff.impact": sd.DiffImpactConfig,
    "diff.routes": RouteDiffParams,
    "diff.truth": sd.DiffTruthConfig,
    "diff.report": sd.DiffReportConfig,
    # configs/export.toml, omni.toml, orp.toml
    "export": se.ExportConfig,
    "omni": so.OmniConfig,
    "orp": so.OrpConfig,
    # configs/simulate.toml
    "simulate": ss.SimulateConfig,
    "simulate.floor": ss.SimFloorConfig,
    "simulate.floor.camera": ss.SimFloorCameraConfig,
    "simulate.floor.motion": ss.SimFloorMotionConfig,
    "simulate.floor.routes": ss.SimFloorRoutesConfig,
    "simulate.floor.odometry": ss.SimOdometryConfig,
    "simulate.floor.sensor": ss.SimSensorConfig,
    "simulate.floor.textures": ss.SimTexturesConfig,
    "simulate.floor.change_kinds": ss.SimChangeKindsConfig,
    "simulate.tiles": ss.SimTilesConfig,
    "simulate.omni": ss.SimOmniConfig,
    "simulate.omni.camera": ss.SimOmniCameraConfig,
    "simulate.omni.motion": ss.SimOmniMotionConfig,
    "simulate.omni.routes": ss.SimOmniRoutesConfig,
    "simulate.omni.odometry": ss.SimOdometryConfig,
    "simulate.omni.sensor": ss.SimSensorConfig,
    "simulate.omni.world": ss.SimOmniWorldConfig,
    # configs/tracker.toml: the tracker's own settings dataclasses (tracker/ imports no pipeline)
    "tracker.bundle": TrackerBundleConfig,
    "tracker.floor": FloorTrackerParams,
    "tracker.reloc": RelocParams,
    "tracker.session": SessionParams,
    "tracker.orp": ORPParams,
    "tracker.orp_session": ORPSessionParams,
    "tracker.orp_reloc": ORPRelocParams,
}

_NAMES: dict[type, str] = {}
for _name, _cls in TABLES.items():
    _NAMES.setdefault(_cls, _name)


def scalars(table: Mapping, name: str) -> dict:
    """The keys of configuration table ``name`` that are its own (its sub-tables left out)."""
    return {k: v for k, v in table.items() if not (isinstance(v, Mapping) and f"{name}.{k}" in TABLES)}


def check_table(name: str, table: Mapping) -> Any:
    """The dataclass of table ``name`` (dotted) built from ``table`` (its sub-tables left out):
    every key known, present, of its type and in its range, else
    :class:`mapstore.knobs.ConfigError`."""
    return from_table(TABLES[name], scalars(table, name), name=name)


def settings(cls: type[T], table: Mapping, name: str | None = None) -> T:
    """Table ``table`` of the configuration as its dataclass ``cls`` (one of :data:`TABLES`;
    ``name`` for a class serving several tables, e.g. the odometry of both simulators)."""
    name = name or _NAMES[cls]
    return from_table(cls, scalars(table, name), name=name)
