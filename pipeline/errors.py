"""Exceptions that carry mosaicmap's exit-code contract.

0 success, 1 failure of the job, 2 bad input or usage. A :class:`BadInput` message is one
line naming the file (and line or field) and what is wrong.
"""

from __future__ import annotations

import errno
import os
import re
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator


class MosaicmapError(Exception):
    """Base class; ``exit_code`` is what the CLI exits with."""

    exit_code = 1


class BadInput(MosaicmapError):
    """Bad input or usage: exit code 2.

    Args:
        where: the culprit: a file, optionally with ``:line`` or ``[field]``.
        what: what is wrong with it.
    """

    exit_code = 2

    def __init__(self, where: str | Path, what: str):
        self.where = str(where)
        self.what = what
        super().__init__(f"{self.where}: {what}")


class JobFailed(MosaicmapError):
    """The job ran on valid input but could not produce its result: exit code 1."""

    exit_code = 1


class WriteFailed(JobFailed):
    """A write the job needs failed (disk full, permission denied, name too long, ...): exit
    code 1, one line naming the path, what was being written and the system's reason."""

    def __init__(self, path: str | Path, what: str, reason: str):
        self.path, self.what, self.reason = str(path), what, reason
        super().__init__(f"{self.path}: cannot write {what}: {reason}")


# Errno values that mean "the storage refused the write", not a bug: reported as one line.
STORAGE_ERRNOS = frozenset(
    getattr(errno, name) for name in ("ENOSPC", "EDQUOT", "EACCES", "EPERM", "EROFS", "ENAMETOOLONG",
                                      "EFBIG", "EIO", "EMFILE", "ENFILE", "EXDEV", "ENOTDIR", "EISDIR")
    if hasattr(errno, name)
)
# Errors of the Rust storage layer (icechunk, object_store) carry the OS error as "(os error 28)".
_OS_ERROR_RE = re.compile(r"\(os error (\d+)\)")


def os_errno(e: BaseException) -> int | None:
    """The OS error number behind ``e``: an :class:`OSError`'s ``errno``, or the ``(os error N)``
    an icechunk / object_store error message carries; None otherwise."""
    if isinstance(e, OSError) and e.errno is not None:
        return e.errno
    m = _OS_ERROR_RE.search(str(e))
    return int(m.group(1)) if m else None


@contextmanager
def writing(what: str, path: str | Path) -> Iterator[None]:
    """Turn a storage failure (:data:`STORAGE_ERRNOS`: disk full, permission, name too long, ...)
    inside the block into :class:`WriteFailed` naming the file (the OSError's, else ``path``)
    and ``what`` was being written ("the work directory", "the map repository")."""
    try:
        yield
    except MosaicmapError:
        raise
    except Exception as e:
        n = os_errno(e)
        if n not in STORAGE_ERRNOS:
            raise
        where = getattr(e, "filename", None) or path
        raise WriteFailed(where, what, f"{os.strerror(n)} (errno {errno.errorcode.get(n, n)})") from e


_NP_SCALAR_RE = re.compile(r"np\.(?:float|int|uint|bool_?)\d*\(([^()]*)\)")


def one_line(message: str) -> str:
    """``message`` made safe for one terminal line: numpy scalar reprs shown as plain numbers
    (``np.float64(2.4)`` -> ``2.4``), newlines and other control characters escaped (``\\n``,
    ``\\x1b``) so that nothing in an input file can break the line or drive the terminal."""
    message = _NP_SCALAR_RE.sub(r"\1", message)
    out = []
    for c in message:
        if c.isprintable() or c == " ":
            out.append(c)
        else:
            out.append(c.encode("unicode_escape").decode("ascii"))
    return "".join(out)
