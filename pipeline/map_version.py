"""Open a map repository and one of its versions, with errors in mosaicmap's terms.

The one place the library runs of the map commands (:mod:`pipeline.export_run`,
:mod:`pipeline.diff_run`) and the commands of :mod:`pipeline.cli.map` open a map: a wrong
URL or version is a :class:`pipeline.errors.BadInput` naming the URL (exit code 2), a
storage that cannot be opened a :class:`pipeline.errors.JobFailed` (exit code 1).

REPO is a local directory (or ``file://DIR``) or ``s3://BUCKET/PREFIX``. A VERSION is
``latest`` / None (the branch tip), a tag, a snapshot id (or a unique prefix of one of at
least 6 characters) or a branch name.
"""

from __future__ import annotations

from pipeline.errors import BadInput, JobFailed

__all__ = ["open_repo", "open_version"]


def open_repo(url: str):
    """The :class:`mapstore.repository.MapRepository` at ``url``; BadInput when there is
    none, JobFailed when its storage cannot be opened."""
    import icechunk

    from mapstore.repository import MapRepository, icechunk_message

    try:
        return MapRepository.open(url)
    except ValueError as e:
        if "no map repository" in str(e):
            raise BadInput(url, "no map repository there") from None
        raise BadInput(url, str(e)) from None
    except icechunk.IcechunkError as e:
        raise JobFailed(f"{url}: cannot open the map repository: {icechunk_message(e)}") from None


def open_version(url: str, version: str | None, branch: str = "main", routes_only_ok: bool = False):
    """(repository, snapshot id, zarr root group, FloorInfo) of ``version`` on ``branch``;
    with ``routes_only_ok`` a map holding only route panoramas gives FloorInfo None.
    BadInput naming ``url`` for an unknown version or a version holding no map."""
    import zarr

    from mapstore.layout import read_floor
    from mapstore.routes import ROUTES_GROUP

    repo = open_repo(url)
    try:
        sid = repo.resolve(version, branch)
    except ValueError as e:
        raise BadInput(url, str(e)) from None
    try:
        root = zarr.open_group(repo.repo.readonly_session(snapshot_id=sid).store, mode="r")
    except (zarr.errors.GroupNotFoundError, FileNotFoundError, KeyError):
        raise BadInput(url, f"version {version or 'latest'} ({sid}): not a mosaicmap map (empty repository)") from None
    if routes_only_ok and "floor" not in root and ROUTES_GROUP in root:
        return repo, sid, root, None
    try:
        info = read_floor(root)
    except ValueError as e:
        raise BadInput(url, f"version {version or 'latest'} ({sid}): {e}") from None
    return repo, sid, root, info
