"""The versioned map repository: an icechunk repository holding the map layout
(:mod:`mapstore.layout`), one snapshot per published version.

Versions
    Every publish is one icechunk commit on a branch (default ``main``) with commit
    metadata (the build's report) and a tag (``v20261122-1``, see :meth:`MapRepository.next_tag`).
    A *version* given by a user is resolved in this order: ``None`` or ``"latest"`` = the
    branch tip; a tag name; a snapshot id (20 characters of base32, e.g.
    ``YJ4CTEB3BBP7C8N5XPQ0``); a branch name; a unique prefix (>= 6 characters) of a
    snapshot id on some branch (as ``mosaicmap log`` prints them).

Concurrency
    icechunk on a local filesystem is not safe for two processes committing at once, so
    every change of a branch (commit, rollback) goes through :meth:`MapRepository.commit_lock`:
    an exclusive ``flock`` on ``<repo dir>/.mosaicmap.lock`` (icechunk ignores the file).
    On S3 the lock is a no-op: of two commits on one branch at once, icechunk lets the first
    through and refuses the other (``icechunk.ConflictError``: its parent is no longer the
    branch tip), through the store's conditional writes; nothing of the refused commit
    becomes visible, and it can be redone on top of the new tip.

Storage URLs
    A local path (or ``file://PATH``), or ``s3://BUCKET/PREFIX`` with credentials from the
    environment (``AWS_ACCESS_KEY_ID`` ...) and an optional ``AWS_ENDPOINT_URL`` (MinIO,
    Ceph, versitygw, ...: path-style addressing, plain http allowed when the endpoint says
    http://; region ``AWS_REGION`` or ``AWS_DEFAULT_REGION``, else ``us-east-1`` with an
    endpoint). The store must honour S3's conditional writes (``If-None-Match: *`` and
    ``If-Match: ETag`` on PUT): they are what makes a second committer fail.
    A store that cannot be used (endpoint unreachable, credentials refused, no such bucket)
    raises :class:`StorageError` with one line saying which.

This module depends on icechunk and zarr only (never on the batch pipeline).
"""

from __future__ import annotations

import fcntl
import logging
import os
import re
import socket
import threading
import time
from contextlib import contextmanager
from datetime import date, datetime, timezone
from pathlib import Path
from typing import Iterator

import icechunk

__all__ = ["open_storage", "MapRepository", "SNAPSHOT_ID_RE", "icechunk_message", "check_tag_name", "MAX_TAG_CHARS",
           "StorageError", "storage_error"]

log = logging.getLogger(__name__)

LOCK_NAME = ".mosaicmap.lock"
# icechunk snapshot ids: 12 bytes in Crockford base32 (no I, L, O, U).
SNAPSHOT_ID_RE = re.compile(r"^[0-9A-HJKMNP-TV-Z]{20}$")
MIN_PREFIX = 6
# Longest tag name (characters): tags are typed, printed in `log` and carried in reports.
MAX_TAG_CHARS = 100
# Seconds to wait for a TCP connection to AWS_ENDPOINT_URL before calling it unreachable
# (icechunk itself retries a refused connection for ~50 s before it gives up).
ENDPOINT_CONNECT_TIMEOUT_S = 5.0
# Region signed into requests to an S3-compatible endpoint when the environment names none
# (without one the AWS SDK asks the EC2 instance metadata service, which is not there).
DEFAULT_ENDPOINT_REGION = "us-east-1"
# S3 error codes meaning "these credentials may not do this" (versitygw: XAdminUserNotFound).
_DENIED_CODES = frozenset({"AccessDenied", "InvalidAccessKeyId", "SignatureDoesNotMatch", "XAdminUserNotFound",
                           "ExpiredToken", "InvalidToken", "TokenRefreshRequired", "AllAccessDisabled",
                           "InvalidClientTokenId", "AuthorizationHeaderMalformed"})
_CODE_RE = re.compile(r'code: "(\w+)"|unhandled error \((\w+)\)|\b(NoSuchBucket)\b')
_reachable: set[str] = set()


class StorageError(ValueError):
    """The storage behind a map repository URL cannot be used: ``kind`` is ``unreachable``
    (no answer from the endpoint), ``denied`` (credentials refused) or ``no-bucket``. The
    message is one line saying what and what to check (it does not repeat the URL)."""

    def __init__(self, kind: str, message: str):
        self.kind = kind
        super().__init__(message)


def _endpoint() -> str | None:
    return os.environ.get("AWS_ENDPOINT_URL") or None


def storage_error(url: str, e: BaseException) -> StorageError | None:
    """The :class:`StorageError` an icechunk error on ``url`` amounts to (credentials refused,
    no such bucket, endpoint unreachable), or None for another error."""
    text = str(e)
    codes = [next(g for g in m.groups() if g) for m in _CODE_RE.finditer(text)]
    endpoint = _endpoint() or "the S3 endpoint"
    denied = next((c for c in codes if c in _DENIED_CODES), None)
    if denied is not None:
        return StorageError("denied", f"{endpoint} refused the credentials ({denied}); check AWS_ACCESS_KEY_ID "
                                      "and AWS_SECRET_ACCESS_KEY")
    if "NoSuchBucket" in codes:
        bucket = url.partition("://")[2].partition("/")[0]
        return StorageError("no-bucket", f"bucket {bucket!r} does not exist at {endpoint}")
    if "dispatch failure" in text or "connection refused" in text.lower() or "timed out" in text:
        return StorageError("unreachable", f"cannot reach {endpoint} (is AWS_ENDPOINT_URL right and the "
                                           f"server up?): {icechunk_message(e)}")
    return None


@contextmanager
def _storage_errors(url: str) -> Iterator[None]:
    """icechunk errors inside the block that say the store cannot be used -> StorageError."""
    try:
        yield
    except icechunk.IcechunkError as e:
        err = storage_error(url, e)
        if err is None:
            raise
        raise err from None


def _check_reachable(endpoint: str) -> None:
    """Raise StorageError("unreachable") unless a TCP connection to ``endpoint`` opens within
    :data:`ENDPOINT_CONNECT_TIMEOUT_S` (checked once per process and endpoint)."""
    if endpoint in _reachable:
        return
    from urllib.parse import urlsplit

    parts = urlsplit(endpoint)
    if not parts.hostname:
        raise StorageError("unreachable", f"AWS_ENDPOINT_URL {endpoint!r} is not a URL (expected http://HOST:PORT)")
    port = parts.port or (443 if parts.scheme == "https" else 80)
    try:
        socket.create_connection((parts.hostname, port), timeout=ENDPOINT_CONNECT_TIMEOUT_S).close()
    except OSError as e:
        reason = e.strerror or str(e) or type(e).__name__
        raise StorageError("unreachable", f"cannot reach {endpoint} (AWS_ENDPOINT_URL): {reason}") from None
    _reachable.add(endpoint)

_quieted = False


def _quiet_local_storage_warning() -> None:
    """icechunk warns on every local storage that it is unsafe for concurrent commits; our
    commit lock is the answer to that, so the warning is silenced (once, and only when the
    user did not choose icechunk's log filter with ICECHUNK_LOG)."""
    global _quieted
    if not _quieted and "ICECHUNK_LOG" not in os.environ:
        icechunk.set_logs_filter("warn,icechunk::storage::object_store=error")
    _quieted = True


def _local_path(url: str) -> Path | None:
    """The directory of a local URL, or None for a remote one."""
    if url.startswith("file://"):
        return Path(os.path.abspath(os.path.expanduser(url[len("file://"):])))
    if "://" in url:
        return None
    return Path(os.path.abspath(os.path.expanduser(url)))


def open_storage(url: str) -> icechunk.Storage:
    """icechunk storage for ``url``: a local path (or ``file://PATH``), or
    ``s3://BUCKET[/PREFIX]`` (credentials from the environment; ``AWS_ENDPOINT_URL`` for an
    S3-compatible store). No I/O: see :func:`_reached_storage`. Raises ValueError for another
    scheme."""
    path = _local_path(url)
    if path is not None:
        _quiet_local_storage_warning()
        return icechunk.local_filesystem_storage(str(path))
    scheme, _, rest = url.partition("://")
    if scheme != "s3":
        raise ValueError(f"unsupported storage scheme {scheme!r} in {url!r} (use a local path, file:// or s3://)")
    bucket, _, prefix = rest.partition("/")
    if not bucket:
        raise ValueError(f"no bucket in {url!r} (expected s3://BUCKET/PREFIX)")
    endpoint = _endpoint()
    region = os.environ.get("AWS_REGION") or os.environ.get("AWS_DEFAULT_REGION") or None
    if endpoint is not None:
        region = region or DEFAULT_ENDPOINT_REGION
    return icechunk.s3_storage(
        bucket=bucket,
        prefix=prefix.strip("/") or None,
        region=region,
        from_env=True,
        endpoint_url=endpoint,
        allow_http=bool(endpoint and endpoint.startswith("http://")),
        force_path_style=bool(endpoint),
    )


def _reached_storage(url: str) -> icechunk.Storage:
    """:func:`open_storage` of ``url``, after checking that an ``AWS_ENDPOINT_URL`` it uses
    accepts a TCP connection (else :class:`StorageError`, in seconds rather than after the
    S3 client's minute of retries)."""
    endpoint = _endpoint()
    if endpoint is not None and url.startswith("s3://"):
        _check_reachable(endpoint)
    return open_storage(url)


def icechunk_message(e: BaseException) -> str:
    """The one-line gist of an icechunk error (its text is a multi-line report)."""
    for line in str(e).splitlines():
        line = re.sub(r"^[\s|`>-]*(x\s+)?", "", line).strip()
        if line:
            return line
    return type(e).__name__


def check_tag_name(name: str) -> str:
    """A tag name as a user may give it: 1..:data:`MAX_TAG_CHARS` characters, printable (no
    control character, newline or tab), no surrounding space, no ``/``, not ``latest`` and not
    shaped like a snapshot id (a tag must never shadow another way to name a version).
    Raises ValueError saying what is wrong; returns ``name``."""
    if not isinstance(name, str) or not name:
        raise ValueError("tag name is empty")
    if len(name) > MAX_TAG_CHARS:
        raise ValueError(f"tag name has {len(name)} characters (at most {MAX_TAG_CHARS})")
    bad = next((c for c in name if not c.isprintable()), None)
    if bad is not None:
        raise ValueError(f"tag name {name!r} holds the control character {bad!r}")
    if name != name.strip() or "/" in name:
        raise ValueError(f"invalid tag name {name!r} (no surrounding space, no '/')")
    if name == "latest" or SNAPSHOT_ID_RE.match(name.upper()):
        raise ValueError(f"tag name {name!r} would shadow {'the branch tip' if name == 'latest' else 'a snapshot id'}")
    return name


def _iso(t: datetime) -> str:
    return t.astimezone(timezone.utc).isoformat(timespec="seconds")


class MapRepository:
    """A map repository at ``url`` (see the module docstring).

    Use :meth:`open`, :meth:`create` or :meth:`open_or_create`; ``.repo`` is the
    :class:`icechunk.Repository` for anything not wrapped here.
    """

    def __init__(self, url: str, repo: icechunk.Repository):
        self.url = url
        self.repo = repo
        self._local = _local_path(url)
        self._lock = threading.RLock()
        self._depth = 0
        self._lock_file = None

    # --- opening -------------------------------------------------------------------------

    @classmethod
    def exists(cls, url: str) -> bool:
        path = _local_path(url)
        if path is not None and not path.is_dir():
            return False  # (icechunk's exists() would create the directory)
        with _storage_errors(url):
            return icechunk.Repository.exists(_reached_storage(url))

    @classmethod
    def open(cls, url: str) -> "MapRepository":
        """Open an existing repository. Raises ValueError "no map repository at URL", or
        :class:`StorageError` (a ValueError too) when the store cannot be used."""
        if not cls.exists(url):
            raise ValueError(f"no map repository at {url}")
        with _storage_errors(url):
            return cls(url, icechunk.Repository.open(_reached_storage(url)))

    @classmethod
    def create(cls, url: str) -> "MapRepository":
        """Create a new, empty repository (branch ``main`` with icechunk's initial snapshot).
        Raises ValueError when one exists already."""
        if cls.exists(url):
            raise ValueError(f"a map repository exists already at {url}")
        path = _local_path(url)
        if path is not None:
            path.mkdir(parents=True, exist_ok=True)
        with _storage_errors(url):
            return cls(url, icechunk.Repository.create(_reached_storage(url)))

    @classmethod
    def open_or_create(cls, url: str) -> "MapRepository":
        return cls.open(url) if cls.exists(url) else cls.create(url)

    # --- the commit lock -----------------------------------------------------------------

    @contextmanager
    def commit_lock(self, timeout_s: float | None = None) -> Iterator[None]:
        """Hold the repository's commit lock (reentrant within this object).

        Local storage: an exclusive ``fcntl.flock`` on ``<repo dir>/.mosaicmap.lock``;
        another holder (process, or another MapRepository object) makes this wait, with a
        log message, forever or up to ``timeout_s`` seconds (then TimeoutError).

        S3: a no-op. Two processes committing on one branch at once: icechunk's conflict
        detection (conditional writes of the branch reference) lets one through and raises
        ``icechunk.ConflictError`` in the other, whose commit is then not visible at all.
        """
        if self._local is None:
            yield
            return
        if not self._lock.acquire(timeout=-1 if timeout_s is None else timeout_s):
            raise TimeoutError(f"{self.url}: commit lock not acquired within {timeout_s} s")
        try:
            if self._depth == 0:
                self._lock_file = self._flock(timeout_s)
            self._depth += 1
            try:
                yield
            finally:
                self._depth -= 1
                if self._depth == 0:
                    f, self._lock_file = self._lock_file, None
                    fcntl.flock(f, fcntl.LOCK_UN)
                    f.close()
        finally:
            self._lock.release()

    def _flock(self, timeout_s: float | None):
        f = open(self._local / LOCK_NAME, "a")
        try:
            try:
                fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return f
            except BlockingIOError:
                pass
            log.info("%s: another process holds the commit lock; waiting", self.url)
            if timeout_s is None:
                fcntl.flock(f, fcntl.LOCK_EX)
                return f
            deadline = time.monotonic() + timeout_s
            while True:
                try:
                    fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    return f
                except BlockingIOError:
                    if time.monotonic() >= deadline:
                        raise TimeoutError(f"{self.url}: commit lock not acquired within {timeout_s} s") from None
                    time.sleep(0.05)
        except BaseException:
            f.close()
            raise

    # --- sessions ------------------------------------------------------------------------

    def readonly(self, version: str | None = None, branch: str = "main") -> icechunk.Session:
        """A read-only session at ``version`` (see :meth:`resolve`); ``session.store`` is
        the zarr store. Raises ValueError naming an unknown version."""
        return self.repo.readonly_session(snapshot_id=self.resolve(version, branch))

    def writable(self, branch: str = "main") -> icechunk.Session:
        """A writable session on the tip of ``branch``; commit it with :meth:`commit`."""
        return self.repo.writable_session(branch)

    def commit(self, session: icechunk.Session, message: str, metadata: dict | None = None) -> str:
        """Commit a writable session under the commit lock; returns the new snapshot id.
        Raises icechunk.ConflictError when the branch moved since the session began."""
        with self.commit_lock():
            return session.commit(message, metadata=metadata)

    # --- versions ------------------------------------------------------------------------

    def branches(self) -> dict[str, str]:
        """Branch name -> tip snapshot id."""
        return {b: self.repo.lookup_branch(b) for b in sorted(self.repo.list_branches())}

    def tags(self) -> dict[str, str]:
        """Tag name -> snapshot id."""
        return {t: self.repo.lookup_tag(t) for t in sorted(self.repo.list_tags())}

    def _snapshot_exists(self, sid: str) -> bool:
        try:
            # icechunk decodes the base32 leniently (the last character's spare bits are
            # dropped), so compare what it found with what was asked.
            return self.repo.lookup_snapshot(sid).id == sid
        except (icechunk.IcechunkError, ValueError):
            return False

    def resolve(self, version: str | None = None, branch: str = "main") -> str:
        """The snapshot id of ``version``: None/"latest" = tip of ``branch``, else a tag, a
        snapshot id, a branch name, or a unique snapshot id prefix (>= 6 characters).
        Raises ValueError naming an unknown version (or branch)."""
        if version is None or version == "latest":
            if branch not in self.repo.list_branches():
                raise ValueError(f"unknown branch {branch!r}")
            return self.repo.lookup_branch(branch)
        v = str(version)
        if v in self.repo.list_tags():
            return self.repo.lookup_tag(v)
        if SNAPSHOT_ID_RE.match(v.upper()) and self._snapshot_exists(v.upper()):
            return v.upper()
        if v in self.repo.list_branches():
            return self.repo.lookup_branch(v)
        if len(v) >= MIN_PREFIX:
            found = {s for s in self._known_snapshots() if s.startswith(v.upper())}
            if len(found) == 1:
                return found.pop()
            if len(found) > 1:
                raise ValueError(f"ambiguous version {v!r}: prefix of {len(found)} snapshot ids")
        raise ValueError(f"unknown version {v!r} (not a tag, snapshot id or branch)")

    def _known_snapshots(self) -> set[str]:
        ids: set[str] = set()
        for b in self.repo.list_branches():
            ids.update(si.id for si in self.repo.ancestry(branch=b))
        for t in self.repo.list_tags():
            ids.update(si.id for si in self.repo.ancestry(tag=t))
        return ids

    def log(self, branch: str = "main") -> list[dict]:
        """The commits of ``branch``, newest first: ``id``, ``parent_id``, ``written_at``
        (ISO 8601 UTC), ``message``, ``metadata`` (the commit metadata dict), ``tags``
        (names pointing at the snapshot, sorted)."""
        if branch not in self.repo.list_branches():
            raise ValueError(f"unknown branch {branch!r}")
        by_snapshot: dict[str, list[str]] = {}
        for name, sid in self.tags().items():
            by_snapshot.setdefault(sid, []).append(name)
        return [
            {
                "id": si.id,
                "parent_id": si.parent_id,
                "written_at": _iso(si.written_at),
                "message": si.message,
                "metadata": dict(si.metadata or {}),
                "tags": sorted(by_snapshot.get(si.id, [])),
            }
            for si in self.repo.ancestry(branch=branch)
        ]

    def check_new_tag(self, name: str, *, branches: tuple[str, ...] = ()) -> str:
        """``name`` as a new tag: :func:`check_tag_name`, not an existing tag (tags are
        immutable) and not the name of a branch (of the repository, or in ``branches``: one
        about to be created). Raises ValueError saying which; returns ``name``."""
        check_tag_name(name)
        if name in self.repo.list_tags():
            raise ValueError(f"tag {name!r} exists already (at {self.repo.lookup_tag(name)})")
        if name in self.repo.list_branches() or name in branches:
            raise ValueError(f"tag name {name!r} is the name of a branch (a tag would shadow it)")
        return name

    def tag(self, snapshot_or_version: str, name: str) -> str:
        """Tag ``snapshot_or_version`` (anything :meth:`resolve` takes) as ``name``; returns
        the snapshot id. Raises ValueError when the name is invalid, the tag exists (tags are
        immutable) or it names a branch (:meth:`check_new_tag`)."""
        self.check_new_tag(name)
        sid = self.resolve(snapshot_or_version)
        self.repo.create_tag(name, sid)
        return sid

    def gc(self, older_than: datetime, *, expire: bool = False, dry_run: bool = False) -> dict:
        """Free what no branch or tag reaches, with icechunk's own expiry and garbage collection,
        under the commit lock.

        1. With ``expire``, icechunk's expiry: snapshots created before ``older_than`` drop out
           of the branches' and tags' histories. No branch or tag is deleted, so every tagged
           version and branch tip stays readable, but the history (``mosaicmap log``) then
           starts at ``older_than``; the untagged snapshots before it become unreachable.
        2. Garbage collection: snapshots, manifests, chunks and transaction logs written before
           ``older_than`` that no branch or tag reaches (a commit whose branch was reset, a
           publish that lost a race, what the expiry dropped) are deleted.

        With ``dry_run`` nothing changes: the untagged snapshots expiry would drop are counted
        and the collection is icechunk's dry run (which cannot count what the expiry would free).
        Returns ``{"expired_snapshots", "snapshots_deleted", "manifests_deleted",
        "chunks_deleted", "attributes_deleted", "transaction_logs_deleted", "bytes_deleted",
        "dry_run"}``."""
        if older_than.tzinfo is None:
            older_than = older_than.replace(tzinfo=timezone.utc)
        with self.commit_lock():
            if not expire:
                expired = 0
            elif dry_run:
                expired = len(self._expirable(older_than))
            else:
                refs = set(self.branches().values()) | set(self.tags().values())
                expired = len(set(self.repo.expire_snapshots(older_than)) - refs)
            summary = self.repo.garbage_collect(older_than, dry_run=dry_run)
        out = {"expired_snapshots": expired, "dry_run": dry_run}
        for k in ("snapshots_deleted", "manifests_deleted", "chunks_deleted", "attributes_deleted",
                  "transaction_logs_deleted", "bytes_deleted"):
            out[k] = int(getattr(summary, k))
        return out

    def _expirable(self, older_than: datetime) -> set[str]:
        """Snapshots in some branch's or tag's history, created before ``older_than``, that no
        branch or tag points at (what :meth:`gc`'s expiry takes; the oldest one of each history,
        the repository's root, excluded)."""
        refs = set(self.branches().values()) | set(self.tags().values())
        out: set[str] = set()
        for sid in refs:
            history = list(self.repo.ancestry(snapshot_id=sid))
            for si in history[:-1]:
                if si.id not in refs and si.written_at < older_than:
                    out.add(si.id)
        return out

    def next_tag(self, fmt: str = "v{date}-{n}", today: date | datetime | None = None) -> str:
        """The tag a publish gets: ``fmt`` with ``{date}`` = YYYYMMDD (UTC; ``today`` to
        override) and ``{n}`` = the smallest number >= 1 making the name new."""
        if today is None:
            today = datetime.now(timezone.utc)
        day = today.strftime("%Y%m%d")
        taken = self.repo.list_tags()
        if "{n}" not in fmt:
            name = fmt.format(date=day)
            if name in taken:
                raise ValueError(f"tag {name!r} exists already and the tag format {fmt!r} has no {{n}}")
            return name
        n = 1
        while fmt.format(date=day, n=n) in taken:
            n += 1
        return fmt.format(date=day, n=n)

    def rollback(self, tag_or_version: str, branch: str = "main") -> str:
        """Move ``branch`` back (or forward) to ``tag_or_version``, under the commit lock.

        Nothing is lost: the current tip is first tagged ``rollback-from-YYYYMMDDTHHMMSS``
        (UTC), and that tag name is returned. Raises ValueError for an unknown version or
        branch, or when the branch is already there.
        """
        with self.commit_lock():
            target = self.resolve(tag_or_version, branch)
            if branch not in self.repo.list_branches():
                raise ValueError(f"unknown branch {branch!r}")
            tip = self.repo.lookup_branch(branch)
            if target == tip:
                raise ValueError(f"branch {branch!r} is already at {tag_or_version!r} ({tip})")
            stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S")
            name, n, taken = f"rollback-from-{stamp}", 1, self.repo.list_tags()
            while name in taken:
                n += 1
                name = f"rollback-from-{stamp}-{n}"
            self.repo.create_tag(name, tip)
            self.repo.reset_branch(branch, target, from_snapshot_id=tip)
            log.info("%s: branch %s moved from %s to %s (old tip tagged %s)", self.url, branch, tip, target, name)
            return name

    # --- differences ---------------------------------------------------------------------

    def diff(self, from_version: str, to_version: str, branch: str = "main") -> icechunk.Diff:
        """icechunk's Diff between two versions (``from`` must be an ancestor of ``to``)."""
        a, b = self.resolve(from_version, branch), self.resolve(to_version, branch)
        try:
            return self.repo.diff(from_snapshot_id=a, to_snapshot_id=b)
        except icechunk.IcechunkError as e:
            raise ValueError(f"cannot diff {from_version!r} -> {to_version!r}: {icechunk_message(e)}") from None

    def changed_chunks(self, from_version: str, to_version: str, branch: str = "main") -> dict[str, set[tuple[int, ...]]]:
        """Stored chunks written between two versions: array path (``"floor/0"``, no
        leading slash) -> set of chunk grid indices.

        For a sharded array (the intensity levels) an index is a *shard* index: icechunk
        stores, and diffs, one object per shard; a shard is listed when any of its chunks
        was written (even with unchanged bytes). Arrays created in between list every chunk
        written to them. ``from_version`` must be an ancestor of ``to_version``.
        """
        d = self.diff(from_version, to_version, branch)
        return {path.lstrip("/"): {tuple(int(i) for i in idx) for idx in idxs}
                for path, idxs in d.updated_chunks.items()}
