"""The work directory of a build: the one owner of its paths (as OpenSfM's ``DataSet``).

A stage never builds a path into the work directory itself: it asks the :class:`Workspace`
for the file it reads (another stage's output) or writes (its own). Layout::

    WORKDIR/.lock                      held by the running build (one build per work directory)
    WORKDIR/<stage>/manifest.json      a finished stage's manifest (written last, renamed in)
    WORKDIR/ingest/frames.zarr         the frames store (pipeline.framestore)
    WORKDIR/ingest/horizons/<k>.npz    omni logs' horizon lines (pipeline.omni_ingest)
    WORKDIR/register/links.csv         candidate pairs and their links; prior.csv (the prior as
                                       corrected), odometry_models.json, map_links.csv (links
                                       to a published map)
    WORKDIR/optimize/poses.csv         optimized poses; links.csv, map_links.csv (residuals),
                                       dropped.csv (frames left out), trajectory.png, residuals.png
    WORKDIR/orp/<route_id>.npz         route panoramas; runs.csv (the runs' poses)
    WORKDIR/render/map.zarr            the shards this build touched; touched.json, gains.csv
    WORKDIR/poses.csv, links.csv       copies of optimize's, for a user

The work directory is the build's own: not a public contract (the map layout,
:mod:`mapstore.layout` and :mod:`mapstore.routes`, the bundle format, :mod:`mapstore.bundle`,
and the drive log, :mod:`pipeline.drivelog`, are). Stages exchange these files through this
class only, so a renamed file changes here and in :data:`OUTPUTS` alone.

A stage writes its directory under a temporary name (:func:`pipeline.fsutil.atomic_dir`),
renamed into place when it finished: :meth:`Workspace.writing` gives the workspace seen by
that stage, whose own files resolve into the temporary directory and every other stage's
into the finished ones.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

from pipeline.anchor import MAP_LINKS_FILE
from pipeline.framestore import STORE_NAME
from pipeline.geometry_gate import DROPPED_FILE
from pipeline.omni_ingest import HORIZONS_DIR, horizons_path

MANIFEST = "manifest.json"
LOCK_FILE = ".lock"

# register
LINKS_FILE = "links.csv"
# The prior poses the build used (the frames store's, or corrected: pipeline.prior_bias).
PRIOR_FILE = "prior.csv"
# Each log's prior error model as the build used it (drive.toml [odometry], grown where the
# links showed the prior noisier: pipeline.prior_bias.calibrate_models).
MODELS_FILE = "odometry_models.json"
# optimize
POSES_FILE = "poses.csv"
PLOTS = ("trajectory", "residuals")
# orp
ROUTE_SUFFIX = ".npz"
RUNS_FILE = "runs.csv"
# render
RENDER_STORE = "map.zarr"
TOUCHED_FILE = "touched.json"
GAINS_FILE = "gains.csv"

# Stage -> the files it writes into WORKDIR/<stage>/ (besides its manifest): what other
# stages, publish and users read. Their names enter the stage's cache fingerprint
# (pipeline.stages.build), so renaming one reruns the stage. The orp stage's route files are
# named by their route: ``<route_id>.npz``.
OUTPUTS: dict[str, tuple[str, ...]] = {
    "ingest": (STORE_NAME, HORIZONS_DIR),
    "register": (LINKS_FILE, PRIOR_FILE, MODELS_FILE, MAP_LINKS_FILE),
    "optimize": (POSES_FILE, LINKS_FILE, MAP_LINKS_FILE, DROPPED_FILE, *(f"{p}.png" for p in PLOTS)),
    "orp": (f"<route_id>{ROUTE_SUFFIX}", RUNS_FILE),
    "render": (RENDER_STORE, TOUCHED_FILE, GAINS_FILE),
    "publish": (),
}


@dataclass(frozen=True)
class Workspace:
    """The paths of one work directory.

    Attributes:
        root: the work directory, as given (a relative path stays relative: messages name it so).
        stage: the stage writing, or None; its files resolve into ``out``.
        out: that stage's temporary directory (renamed to ``root/stage`` when it finished).
    """

    root: Path
    stage: str | None = None
    out: Path | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "root", Path(self.root))

    def writing(self, stage: str, out: Path) -> Workspace:
        """The workspace as ``stage`` sees it while it writes into ``out``."""
        return replace(self, stage=stage, out=Path(out))

    def stage_dir(self, stage: str) -> Path:
        """``WORKDIR/<stage>``, or the temporary directory when ``stage`` is the one writing."""
        if stage == self.stage and self.out is not None:
            return self.out
        return self.root / stage

    def manifest(self, stage: str) -> Path:
        return self.stage_dir(stage) / MANIFEST

    @property
    def lock_file(self) -> Path:
        return self.root / LOCK_FILE

    # --- ingest ---------------------------------------------------------------------------

    @property
    def frames_store(self) -> Path:
        """The frames store (zarr directory, :mod:`pipeline.framestore`)."""
        return self.stage_dir("ingest") / STORE_NAME

    @property
    def horizons_dir(self) -> Path:
        """The omni logs' horizon line files (``<k:03d>.npz``, :mod:`pipeline.omni_ingest`)."""
        return self.stage_dir("ingest") / HORIZONS_DIR

    def horizons_file(self, index: int) -> Path:
        """The horizon lines of the ingest's log ``index``."""
        return horizons_path(self.stage_dir("ingest"), index)

    # --- register -------------------------------------------------------------------------

    @property
    def register_links(self) -> Path:
        return self.stage_dir("register") / LINKS_FILE

    @property
    def register_map_links(self) -> Path:
        """Links to the published map (written only over a published map)."""
        return self.stage_dir("register") / MAP_LINKS_FILE

    @property
    def register_prior(self) -> Path:
        return self.stage_dir("register") / PRIOR_FILE

    @property
    def register_models(self) -> Path:
        return self.stage_dir("register") / MODELS_FILE

    # --- optimize -------------------------------------------------------------------------

    @property
    def poses(self) -> Path:
        """The optimized poses (``optimize/poses.csv``)."""
        return self.stage_dir("optimize") / POSES_FILE

    @property
    def optimize_links(self) -> Path:
        """The links with their residuals after optimization."""
        return self.stage_dir("optimize") / LINKS_FILE

    @property
    def optimize_map_links(self) -> Path:
        return self.stage_dir("optimize") / MAP_LINKS_FILE

    @property
    def dropped(self) -> Path:
        """Frames the optimize stage left out (:mod:`pipeline.geometry_gate`)."""
        return self.stage_dir("optimize") / DROPPED_FILE

    def plot(self, name: str) -> Path:
        """One of the optimize stage's plots (:data:`PLOTS`) as PNG."""
        return self.stage_dir("optimize") / f"{name}.png"

    @property
    def result_poses(self) -> Path:
        """``WORKDIR/poses.csv``: the optimized poses, copied for a user."""
        return self.root / POSES_FILE

    @property
    def result_links(self) -> Path:
        """``WORKDIR/links.csv``: the optimized links, copied for a user."""
        return self.root / LINKS_FILE

    # --- orp ------------------------------------------------------------------------------

    @property
    def routes_dir(self) -> Path:
        return self.stage_dir("orp")

    def route_file(self, route_id: str) -> Path:
        return self.stage_dir("orp") / f"{route_id}{ROUTE_SUFFIX}"

    def route_files(self) -> dict[str, Path]:
        """Route id -> the orp stage's output file (empty when the stage made none)."""
        d = self.stage_dir("orp")
        return {p.stem: p for p in sorted(d.glob("*" + ROUTE_SUFFIX))} if d.is_dir() else {}

    @property
    def route_runs(self) -> Path:
        return self.stage_dir("orp") / RUNS_FILE

    # --- render ---------------------------------------------------------------------------

    @property
    def render_store(self) -> Path:
        """The rendered shards (a zarr directory in the map layout)."""
        return self.stage_dir("render") / RENDER_STORE

    @property
    def touched(self) -> Path:
        """The shards the render stage touched, per array (JSON)."""
        return self.stage_dir("render") / TOUCHED_FILE

    @property
    def gains(self) -> Path:
        return self.stage_dir("render") / GAINS_FILE
