"""Exceptions that carry mosaicmap's exit-code contract.

0 success, 1 failure of the job, 2 bad input or usage. A :class:`BadInput` message is one
line naming the file (and line or field) and what is wrong.
"""

from __future__ import annotations

from pathlib import Path


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
