"""Effective configuration: the defaults in ``configs/*.toml`` overlaid by a user file.

Each default file owns its top-level tables (no two files define the same one). A user
file may override any key that exists in the defaults; an unknown key is a usage error
(exit code 2) naming it, so that a typo never silently falls back to a default.
"""

from __future__ import annotations

import hashlib
import json
import re
import tomllib
from pathlib import Path
from typing import Any

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


def default_config() -> dict:
    """Merge of every ``configs/*.toml`` file shipped with mosaicmap."""
    files = default_files()
    if not files:
        raise BadInput(CONFIG_DIR, f"no default configuration files (configs/*.toml, or the installed package "
                                   f"{CONFIG_PACKAGE}) found: a broken installation")
    merged: dict = {}
    for name, data in files:
        try:
            tables = tomllib.loads(data.decode("utf-8"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
            raise BadInput(name, f"not valid TOML: {e}") from None
        for table, value in tables.items():
            if table in merged:
                raise BadInput(name, f"table [{table}] is also defined in another default file")
            merged[table] = value
    return merged


def _overlay(base: dict, over: dict, source: Path, prefix: str = "") -> None:
    for key, value in over.items():
        name = f"{prefix}{key}"
        if key not in base:
            raise BadInput(source, f"unknown configuration key '{name}'")
        if isinstance(base[key], dict):
            if not isinstance(value, dict):
                raise BadInput(source, f"'{name}' must be a table")
            _overlay(base[key], value, source, name + ".")
        else:
            if isinstance(value, dict):
                raise BadInput(source, f"'{name}' must be a value, not a table")
            if isinstance(base[key], float) and isinstance(value, int) and not isinstance(value, bool):
                value = float(value)
            if type(value) is not type(base[key]):
                raise BadInput(
                    source,
                    f"'{name}' must be of type {type(base[key]).__name__}, got {type(value).__name__}",
                )
            base[key] = value


def load_config(user_file: str | Path | None = None) -> dict:
    """The effective configuration: defaults, overlaid by ``user_file`` when given."""
    cfg = default_config()
    if user_file is not None:
        path = Path(user_file)
        _overlay(cfg, read_toml(path), path)
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
