"""The stage protocol: every stage of the build is ``run(ws, params) -> report sections``.

- ``ws``: the :class:`pipeline.stages.workspace.Workspace`, the one owner of the work
  directory's paths (the stage's own files resolve into its temporary directory);
- ``params``: :class:`StageParams`, the configuration tables the stage declares
  (:attr:`Stage.params_tables`, all it is given, and what its cache fingerprint is derived
  from), the typed :class:`BuildContext` (logs, published base, map URL, tag) and the report
  so far.

A stage module defines its entry and one :class:`Stage` object (``STAGE``) declaring it;
:data:`pipeline.stages.build.STAGES` lists them in build order.
"""

from __future__ import annotations

import resource
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

from pipeline.stages.workspace import OUTPUTS, Workspace


@dataclass(frozen=True)
class BuildContext:
    """One build's inputs, fixed before its first stage runs.

    Attributes:
        logs: the validated drive logs (:class:`pipeline.drivelog.DriveLog`), in build order.
        inputs: per log ``{"log_id", "path", "sha256"}`` (the report's ``logs``).
        map_url: the map repository (a directory or ``s3://bucket/prefix``), or None.
        branch: the branch the build publishes on (``[publish] branch``).
        tag: the new version's tag (``--tag``), or None for ``[publish] tag_format``.
        base: ``{"url", "snapshot", "version", "pixel_size"}`` of the published map version
            the build extends (:func:`pipeline.stages.build.find_base`), or None.
        route_base: the version the build reads stored route panoramas from (``base``, or a
            map of routes only: :func:`pipeline.stages.build.find_route_base`), or None.
        build_key: hash of the inputs, configuration and mosaicmap version (a rerun of the
            same build has the same key).
        config_hash: hash of the whole configuration (pixel size resolved), recorded by publish.
        quiet: no progress output.
    """

    logs: tuple = ()
    inputs: tuple[dict, ...] = ()
    map_url: str | None = None
    branch: str = "main"
    tag: str | None = None
    base: dict | None = None
    route_base: dict | None = None
    build_key: str = ""
    config_hash: str = ""
    quiet: bool = False

    @property
    def base_version(self) -> int:
        """The published version the build extends (0: a new map)."""
        return 0 if self.base is None else int(self.base["version"])


@dataclass(frozen=True)
class StageParams:
    """What a stage reads besides the work directory.

    Attributes:
        cfg: the configuration tables the stage declares (:attr:`Stage.params_tables`), nested
            as in the configuration (``"tracker.orp"`` gives ``cfg["tracker"]["orp"]``), and no
            other: a stage that reads an undeclared table fails at once (KeyError) instead of
            going stale in the build's cache.
        build: the build's inputs (:class:`BuildContext`).
        report: the build's report so far (the sections of the stages before this one).
        build_id: this stage run's cache fingerprint (publish records it in its commit).
    """

    cfg: dict[str, Any]
    build: BuildContext = BuildContext()
    report: Mapping[str, Any] = field(default_factory=dict)
    build_id: str = ""

    @property
    def quiet(self) -> bool:
        return self.build.quiet


@dataclass(frozen=True)
class Stage:
    """One stage of the build: ``run(ws, params) -> report sections`` and what the build needs
    to know to cache, order and guard it.

    Attributes:
        name: the stage's name (its directory in the work directory, its report line).
        run: the stage: reads other stages' files through the :class:`Workspace`, writes its
            own (``ws`` as :meth:`Workspace.writing` gives it), returns report sections
            ``{section: {key: value}}`` (also kept in its manifest for a skipped rerun).
        params_tables: the configuration tables it reads (dotted for a sub-table:
            ``"tracker.orp"``); its cache fingerprint is derived from them, and they are all
            it is given (:class:`StageParams`).
        reads_base: its output depends on the published map version the build extends.
        needs_map: it needs a map repository (``--map``); without one the build stops before it.
        side: it runs only for some logs (the route panoramas of omni logs) and feeds publish
            only: the stages after it keep the previous stage's fingerprint as their upstream.
        gated: the publish quality gates are checked before it runs (a failing build stops
            early, :func:`pipeline.stages.publish.check_gates`).
        publishes: it writes the map repository (its failures name the repository; its
            fingerprint holds the map URL and the side stages').
        after: run once the stage is done or found up to date (e.g. copies for a user).
    """

    name: str
    run: Callable[[Workspace, StageParams], dict]
    params_tables: tuple[str, ...]
    reads_base: bool = False
    needs_map: bool = False
    side: bool = False
    gated: bool = False
    publishes: bool = False
    after: Callable[[Workspace], None] | None = None

    @property
    def outputs(self) -> tuple[str, ...]:
        """The files the stage writes (:data:`pipeline.stages.workspace.OUTPUTS`)."""
        return OUTPUTS[self.name]

    def params(self, cfg: Mapping[str, Any], build: BuildContext = BuildContext(),
               report: Mapping[str, Any] | None = None, build_id: str = "") -> StageParams:
        """The stage's params: its declared tables of ``cfg`` and the build's context."""
        return StageParams(declared_tables(cfg, self.params_tables), build, {} if report is None else report, build_id)


# Knobs that say how a stage's work is executed, not what it computes: the scheduler and
# the number of workers. Outputs are the same bytes on every scheduler and worker count
# (tests/test_map_build.py, tests/test_cluster_workers.py), so they are left out of the
# fingerprints: a build resumed on another scheduler re-uses the stages already done.
EXECUTION_KEYS = frozenset({"scheduler", "workers", "threads_min_frame_px", "processes_min_frames",
                            "processes_min_mpix"})


def fingerprint_tables(cfg: Mapping[str, Any], tables: tuple[str, ...]) -> dict:
    """:func:`config_tables` without the :data:`EXECUTION_KEYS` of each table (what a
    stage's cache fingerprint hashes)."""
    return {name: {k: v for k, v in table.items() if k not in EXECUTION_KEYS} if isinstance(table, Mapping) else table
            for name, table in config_tables(cfg, tables).items()}


def config_tables(cfg: Mapping[str, Any], tables: tuple[str, ...]) -> dict:
    """The configuration (sub)tables ``tables`` by dotted name: ``{"tracker.orp": {...}}``
    (what a stage's fingerprint and manifest hash)."""
    out = {}
    for name in tables:
        node = cfg
        for part in name.split("."):
            node = node[part]
        out[name] = node
    return out


def declared_tables(cfg: Mapping[str, Any], tables: tuple[str, ...]) -> dict:
    """``cfg`` cut down to ``tables``, nested as in the configuration: ``("map", "tracker.orp")``
    gives ``{"map": cfg["map"], "tracker": {"orp": cfg["tracker"]["orp"]}}``."""
    out: dict = {}
    for name, table in config_tables(cfg, tables).items():
        *parents, last = name.split(".")
        node = out
        for part in parents:
            node = node.setdefault(part, {})
        node[last] = table
    return out


def process_cpu_seconds() -> float:
    """CPU seconds (user + system) of this process, every thread, and of its finished child
    processes (the ``processes`` scheduler's workers, counted once their pool has closed):
    what a stage costs on a shared machine, beside its wall seconds. (A dask.distributed
    cluster's workers are not counted.)"""
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime
