"""Effective configuration: the defaults in ``configs/*.toml`` overlaid by a user file.

Each default file owns its top-level tables (no two files define the same one). A user
file may override any key that exists in the defaults; an unknown key is a usage error
(exit code 2) naming it, so that a typo never silently falls back to a default. Every table
is then checked against its schema (:mod:`pipeline.schema`: type and range of each key), so
an out-of-range value is refused at load time, naming the file, the table and the key.
"""

from __future__ import annotations

import difflib
import hashlib
import json
import re
import tomllib
from pathlib import Path
from typing import Any, Callable

from mapstore.knobs import ConfigError, table_values
from pipeline.errors import BadInput

# A checkout's (or an editable install's) configs/ beside the packages; an installed wheel
# carries the same files as the package ``mosaicmap_configs``.
CONFIG_DIR = Path(__file__).resolve().parent.parent / "configs"
CONFIG_PACKAGE = "mosaicmap_configs"


def default_files() -> list[tuple[str, bytes]]:
    """``(name, bytes)`` of the default ``*.toml`` files, by name: from ``configs/`` of the
    checkout, else from the installed package (importlib.resources)."""
    if (CONFIG_DIR / "floor.toml").is_file():
        return [(str(p), p.read_bytes()) for p in sorted(CONFIG_DIR.glob("*.toml"))]
    try:
        from importlib.resources import files

        root = files(CONFIG_PACKAGE)
        found = sorted((t for t in root.iterdir() if t.name.endswith(".toml")), key=lambda t: t.name)
        return [(f"{CONFIG_PACKAGE}/{t.name}", t.read_bytes()) for t in found]
    except (ModuleNotFoundError, FileNotFoundError, NotADirectoryError):
        return []


def read_toml(path: str | Path, missing: str = "config file not found") -> dict:
    """Parse a TOML file; a missing or invalid file is :class:`BadInput` naming it."""
    path = Path(path)
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except (FileNotFoundError, IsADirectoryError):
        raise BadInput(path, missing) from None
    except OSError as e:  # permission denied, name too long, ...
        raise BadInput(path, f"cannot read: {e.strerror or e}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise BadInput(path, f"not valid TOML: {e}") from None


def _default_tables() -> tuple[dict, dict[str, str]]:
    """The merged default files and, per top-level table, the file that defines it."""
    files = default_files()
    if not files:
        raise BadInput(CONFIG_DIR, f"no default configuration files (configs/*.toml, or the installed package "
                                   f"{CONFIG_PACKAGE}) found: a broken installation")
    merged: dict = {}
    owner: dict[str, str] = {}
    for name, data in files:
        try:
            tables = tomllib.loads(data.decode("utf-8"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
            raise BadInput(name, f"not valid TOML: {e}") from None
        for table, value in tables.items():
            if table in merged:
                raise BadInput(name, f"table [{table}] is also defined in another default file")
            merged[table] = value
            owner[table] = name
    return merged, owner


def default_config() -> dict:
    """Merge of every ``configs/*.toml`` file shipped with mosaicmap (not checked: see
    :func:`load_config`)."""
    return _default_tables()[0]


def _overlay(base: dict, over: dict, source: Path, given: set[str], prefix: str = "") -> None:
    """Overlay ``over`` onto ``base`` in place, recording the dotted keys set in ``given``; a
    key or table the defaults do not have is :class:`BadInput` naming ``source``. Types and
    ranges are the schema's (:func:`check_config`)."""
    for key, value in over.items():
        name = f"{prefix}{key}"
        table = prefix[:-1] or "(top level)"
        if key not in base:
            kind = "table" if isinstance(value, dict) else "key"
            near = difflib.get_close_matches(key, list(base), n=1)
            hint = f' (did you mean "{near[0]}"?)' if near else ""
            raise BadInput(source, f"[{table}] {key}: unknown {kind}{hint}")
        if isinstance(base[key], dict):
            if not isinstance(value, dict):
                raise BadInput(source, f"[{name}]: must be a table, not a value")
            _overlay(base[key], value, source, given, name + ".")
        else:
            if isinstance(value, dict):
                raise BadInput(source, f"[{table}] {key}: must be a value, not a table")
            base[key] = value
            given.add(name)


def check_config(cfg: dict, where: Callable[[str, str], str]) -> None:
    """Check every table of ``cfg`` against the schema (:data:`pipeline.schema.TABLES`): each
    key known, present, of its type and within its range. Values are normalized in place
    (an integer given for a number becomes a float). A violation is :class:`BadInput` naming
    ``where(table, key)`` (the file the value came from), the table, the key and what is
    allowed."""
    from pipeline.schema import TABLES, check_table

    def walk(node: dict, name: str) -> None:
        if name in TABLES:
            try:
                obj = check_table(name, node)
            except ConfigError as e:
                raise BadInput(where(e.table, e.key), str(e)) from None
            node.update(table_values(obj))
        for key, value in node.items():
            sub = f"{name}.{key}" if name else key
            if isinstance(value, dict):
                walk(value, sub)
            elif name not in TABLES:
                raise BadInput(where(name or key, key), f"[{name or '(top level)'}] {key}: not in a known table")
        if name and name not in TABLES and not any(t.startswith(name + ".") for t in TABLES):
            raise BadInput(where(name, ""), f"[{name}]: unknown table")

    walk(cfg, "")
    for name in TABLES:
        node: Any = cfg
        for part in name.split("."):
            node = node.get(part) if isinstance(node, dict) else None
        if not isinstance(node, dict):
            raise BadInput(where(name, ""), f"[{name}]: missing from the default configuration")


def load_config(user_file: str | Path | None = None) -> dict:
    """The effective configuration: the defaults, overlaid by ``user_file`` when given, each
    table checked against its schema (:mod:`pipeline.schema`): an unknown key, a wrong type or
    a value out of range is :class:`BadInput` (exit code 2) naming the file, the table, the
    key and what is allowed."""
    cfg, owner = _default_tables()
    given: set[str] = set()
    path = None if user_file is None else Path(user_file)
    if path is not None:
        _overlay(cfg, read_toml(path), path, given)

    def where(table: str, key: str) -> str:
        if path is not None and f"{table}.{key}" in given:
            return str(path)
        return owner.get(table.split(".")[0], str(CONFIG_DIR))

    check_config(cfg, where)
    return cfg


def config_hash(section: Any) -> str:
    """A stable SHA-256 over a configuration (sub)tree, for stage manifests."""
    blob = json.dumps(section, sort_keys=True, separators=(",", ":")).encode()
    return hashlib.sha256(blob).hexdigest()


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} as TOML")


_BARE_KEY = re.compile(r"^[A-Za-z0-9_-]+$")


def _toml_key(k: str) -> str:
    return k if _BARE_KEY.match(k) else json.dumps(k)


def dump_toml(cfg: dict, _prefix: str = "") -> str:
    """TOML text of a nested dict of scalars, lists and tables (for ``config show``)."""
    lines = []
    scalars = {k: v for k, v in cfg.items() if not isinstance(v, dict)}
    tables = {k: v for k, v in cfg.items() if isinstance(v, dict)}
    if _prefix and scalars:
        lines.append(f"[{_prefix}]")
    for k, v in scalars.items():
        lines.append(f"{_toml_key(k)} = {_toml_value(v)}")
    if scalars:
        lines.append("")
    for k, v in tables.items():
        lines.append(dump_toml(v, f"{_prefix}.{_toml_key(k)}" if _prefix else _toml_key(k)))
    return "\n".join(lines)
