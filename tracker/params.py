"""Settings dataclasses from configuration tables (``configs/tracker.toml``), one way for all."""

from __future__ import annotations

from dataclasses import fields
from typing import TypeVar

__all__ = ["params_from_dict"]

T = TypeVar("T")


def params_from_dict(cls: type[T], d: dict, what: str) -> T:
    """``cls(**d)`` for a frozen settings dataclass: TOML lists become tuples; an unknown
    key raises ValueError naming it (``what``: e.g. "tracker parameter")."""
    names = {f.name for f in fields(cls)}
    unknown = set(d) - names
    if unknown:
        raise ValueError(f"unknown {what}(s): {', '.join(sorted(unknown))}")
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})
