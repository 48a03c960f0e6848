"""What a stage is given: the typed build context (the build's inputs and the published
version it extends)."""

from __future__ import annotations

from dataclasses import dataclass


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
            the build extends (:func:`pipeline.build.find_base`), or None.
        route_base: the version the build reads stored route panoramas from (``base``, or a
            map of routes only: :func:`pipeline.build.find_route_base`), or None.
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
