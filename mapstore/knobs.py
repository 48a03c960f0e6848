"""Typed, ranged configuration tables: one strict reader for every ``[table]`` of ``configs/*.toml``.

A table is a frozen dataclass: each field's annotation is its type (``int``, ``float``, ``bool``,
``str``, ``tuple[float, float]``, ``tuple[int, ...]``, nested tuples) and :func:`knob` gives its
range or choices. :func:`from_table` builds one from a TOML table and refuses, with a
:class:`ConfigError` naming the table, the key and what is allowed, an unknown key, a missing
one, a wrong type or a value out of range. The pipeline's tables carry no defaults (those live
in ``configs/*.toml`` only); the tracker's settings dataclasses keep theirs (the vehicle API)
and may be read from a partial table.

Only the standard library is imported here: ``tracker/`` (which must not import ``pipeline``)
and ``mapstore/bundle.py`` use it as well as ``pipeline/``.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import typing
from collections.abc import Mapping
from dataclasses import MISSING, dataclass, fields
from functools import lru_cache
from typing import Any, TypeVar

__all__ = ["ConfigError", "Rule", "knob", "from_table", "table_values", "rule_of"]

T = TypeVar("T")


class ConfigError(ValueError):
    """A configuration table is wrong: ``table`` (dotted, e.g. "register"), ``key`` and
    ``problem`` (what is wrong and what is allowed); ``str()`` is ``[table] key: problem``."""

    def __init__(self, table: str, key: str, problem: str):
        self.table, self.key, self.problem = table, key, problem
        super().__init__(f"[{table}] {key}: {problem}")


@dataclass(frozen=True)
class Rule:
    """What a knob accepts beyond its type.

    Attributes:
        ge, gt, le, lt: bounds of a number (of every number of a list).
        choices: the strings (or integers) allowed (``fold_case``: strings compared
            case-insensitively).
        url_schemes: also allowed, a string ``SCHEME://ADDRESS`` with one of these schemes
            (the address is whatever follows, without spaces: checked where it is used).
        lengths: the lengths a list may have (None = any).
        ordered: a list's numbers must not decrease (a ``[low, high]`` range).
        decreasing: a list's numbers must strictly decrease.
    """

    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    choices: tuple[str | int, ...] | None = None
    fold_case: bool = False
    url_schemes: tuple[str, ...] = ()
    lengths: tuple[int, ...] | None = None
    ordered: bool = False
    decreasing: bool = False

    def bounds(self) -> str:
        """The numeric range as text ("x >= 0", "0 < x <= 1"), "" when unbounded."""
        lo = f"{_num(self.ge)} <= " if self.ge is not None else f"{_num(self.gt)} < " if self.gt is not None else ""
        hi = f" <= {_num(self.le)}" if self.le is not None else f" < {_num(self.lt)}" if self.lt is not None else ""
        if lo and not hi:  # "x >= 0" reads better than "0 <= x"
            return f"x {'>=' if self.ge is not None else '>'} {lo.split()[0]}"
        return f"{lo}x{hi}" if lo or hi else ""

    def check_number(self, v: float) -> str | None:
        """None when ``v`` is within the bounds, else the allowed range."""
        if ((self.ge is not None and not v >= self.ge) or (self.gt is not None and not v > self.gt)
                or (self.le is not None and not v <= self.le) or (self.lt is not None and not v < self.lt)):
            return self.bounds()
        return None

    def describe_choices(self) -> str:
        opts = [_show(c) for c in self.choices or ()]
        if self.url_schemes:
            opts.append(f"SCHEME://ADDRESS (SCHEME: {', '.join(self.url_schemes)})")
        return "one of " + ", ".join(opts)


def _num(v: float) -> str:
    return repr(int(v)) if float(v).is_integer() and abs(v) < 1e15 else repr(v)


def knob(*, ge: float | None = None, gt: float | None = None, le: float | None = None, lt: float | None = None,
         choices: tuple[str | int, ...] | None = None, fold_case: bool = False, url_schemes: tuple[str, ...] = (),
         lengths: tuple[int, ...] | None = None, ordered: bool = False, decreasing: bool = False,
         default: Any = MISSING) -> Any:
    """A dataclass field carrying its :class:`Rule` (and, for the tracker's settings, a default)."""
    rule = Rule(ge, gt, le, lt, choices, fold_case, url_schemes, lengths, ordered, decreasing)
    return dataclasses.field(default=default, metadata={"knob": rule})


def rule_of(f: dataclasses.Field) -> Rule:
    """A field's :class:`Rule` (an unconstrained one when it has none)."""
    return f.metadata.get("knob", Rule())


@lru_cache(maxsize=None)
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _type_name(tp: Any) -> str:
    if tp is bool:
        return "true or false"
    if tp is int:
        return "an integer"
    if tp is float:
        return "a number"
    if tp is str:
        return "a string"
    args = typing.get_args(tp)
    if len(args) == 2 and args[1] is Ellipsis:
        return f"a list of {_plural(args[0])}"
    return f"a list of {len(args)} {_plural(args[0])}" if len(set(args)) == 1 else "a list"


def _plural(tp: Any) -> str:
    return {bool: "booleans", int: "integers", float: "numbers", str: "strings"}.get(tp, "lists")


def _toml_type(v: Any) -> str:
    if isinstance(v, bool):
        return "a boolean"
    if isinstance(v, int):
        return "an integer"
    if isinstance(v, float):
        return "a number"
    if isinstance(v, str):
        return "a string"
    if isinstance(v, (list, tuple)):
        return "a list"
    if isinstance(v, Mapping):
        return "a table"
    return type(v).__name__


def _coerce(v: Any, tp: Any, rule: Rule) -> Any:
    """``v`` as type ``tp`` (lists as tuples, integers as floats where a number is wanted);
    raises ``_Bad(problem)``."""
    if tp is bool:
        if not isinstance(v, bool):
            raise _Bad(f"must be {_type_name(tp)}, got {_toml_type(v)}")
        return v
    if tp in (int, float):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or (tp is int and not isinstance(v, int)):
            raise _Bad(f"must be {_type_name(tp)}, got {_toml_type(v)} {_show(v)}")
        given = v
        if tp is float:
            v = float(v)
            if not math.isfinite(v):
                raise _Bad(f"must be a finite number, got {v}")
        bad = rule.check_number(v)
        if bad:
            raise _Bad(f"{_show(given)} is out of range; allowed: {bad}")
        if rule.choices is not None and v not in rule.choices:
            raise _Bad(f"{_show(v)} is not allowed; allowed: {rule.describe_choices()}")
        return v
    if tp is str:
        if not isinstance(v, str):
            raise _Bad(f"must be {_type_name(tp)}, got {_toml_type(v)}")
        if rule.choices is not None:
            ok = (v.lower() in {c.lower() for c in rule.choices}) if rule.fold_case else v in rule.choices
            if not ok and not any(_is_url(v, s) for s in rule.url_schemes):
                raise _Bad(f"{_show(v)} is not allowed; allowed: {rule.describe_choices()}")
        return v
    origin = typing.get_origin(tp)
    if origin is tuple:
        if not isinstance(v, (list, tuple)):
            raise _Bad(f"must be {_type_name(tp)}, got {_toml_type(v)}")
        args = typing.get_args(tp)
        variadic = len(args) == 2 and args[1] is Ellipsis
        if not variadic and len(v) != len(args):
            raise _Bad(f"must be {_type_name(tp)}, got {len(v)} values")
        if rule.lengths is not None and len(v) not in rule.lengths:
            raise _Bad(f"must hold {' or '.join(map(str, rule.lengths))} values, got {len(v)}")
        inner = Rule(rule.ge, rule.gt, rule.le, rule.lt, rule.choices, rule.fold_case, rule.url_schemes)
        out = tuple(_coerce(x, args[0] if variadic else a, inner) for x, a in zip(v, args if not variadic else v))
        if rule.ordered and any(b < a for a, b in zip(out, out[1:])):
            raise _Bad(f"{_show(v)} must not decrease ([low, high])")
        if rule.decreasing and any(b >= a for a, b in zip(out, out[1:])):
            raise _Bad(f"{_show(v)} must decrease strictly")
        return out
    raise TypeError(f"knob type {tp!r} is not supported")


def _is_url(v: str, scheme: str) -> bool:
    address = v[len(scheme) + 3:]
    return v.startswith(scheme + "://") and bool(address) and not any(c.isspace() for c in address)


def _show(v: Any) -> str:
    if isinstance(v, str):
        return f'"{v}"'
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_show(x) for x in v) + "]"
    return repr(v)


class _Bad(Exception):
    pass


def from_table(cls: type[T], table: Mapping, *, name: str, partial: bool = False) -> T:
    """The frozen dataclass ``cls`` from a TOML table (``name``: its dotted name, for messages).

    Every key must be a field (unknown keys are refused, with the closest known key as a hint),
    every field without a default must be given (all of them unless ``partial``), and each
    value must have the field's type and satisfy its :func:`knob` rule. Lists become tuples;
    integers become floats where a number is wanted. Raises :class:`ConfigError`."""
    if not isinstance(table, Mapping):
        raise ConfigError(name, "*", f"must be a table, got {_toml_type(table)}")
    hints = _hints(cls)
    by_name = {f.name: f for f in fields(cls)}
    for key in table:
        if key not in by_name:
            near = difflib.get_close_matches(str(key), list(by_name), n=1)
            if near:
                hint = f'did you mean "{near[0]}"?'
            elif len(by_name) <= 12:
                hint = f"known keys: {', '.join(by_name)}"
            else:
                hint = "`mosaicmap config show` lists the known keys"
            raise ConfigError(name, str(key), f"unknown key ({hint})")
    values = {}
    for key, f in by_name.items():
        if key not in table:
            if partial and (f.default is not MISSING or f.default_factory is not MISSING):
                continue
            raise ConfigError(name, key, f"missing ({_type_name(hints[key])} is required)")
        try:
            values[key] = _coerce(table[key], hints[key], rule_of(f))
        except _Bad as e:
            raise ConfigError(name, key, str(e)) from None
    return cls(**values)


def table_values(obj: Any) -> dict:
    """The TOML table of a settings dataclass (tuples as lists), as :func:`from_table` reads it."""

    def plain(v: Any) -> Any:
        return [plain(x) for x in v] if isinstance(v, tuple) else v

    return {f.name: plain(getattr(obj, f.name)) for f in fields(obj)}
