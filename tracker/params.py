"""Settings dataclasses from configuration tables (``configs/tracker.toml``), one way for all.

The tracker's settings are frozen dataclasses whose fields carry their default, type and range
(:func:`mapstore.knobs.knob`); :func:`params_from_dict` reads one from a (partial) table with
the same strict reader the pipeline's configuration uses (:mod:`mapstore.knobs`).
"""

from __future__ import annotations

from typing import TypeVar

from mapstore.knobs import ConfigError, from_table

__all__ = ["params_from_dict", "ConfigError"]

T = TypeVar("T")


def params_from_dict(cls: type[T], d: dict, table: str) -> T:
    """``cls`` from the ``[table]`` (dotted, e.g. "tracker.floor") of a configuration: keys
    left out keep the dataclass's defaults, TOML lists become tuples; an unknown key, a wrong
    type or a value out of range raises :class:`ConfigError` (a ValueError) naming the table,
    the key and what is allowed."""
    return from_table(cls, d, name=table, partial=True)
