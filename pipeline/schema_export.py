"""Types and ranges of ``[export]`` (``configs/export.toml``, `mosaicmap export`); the values
and what each knob means are in the TOML file only."""

from __future__ import annotations

from dataclasses import dataclass

from mapstore.knobs import knob
from mapstore.layout import LAYERS

__all__ = ["ExportConfig"]


@dataclass(frozen=True)
class ExportConfig:
    """``[export]``: what a bundle holds by default and how it is stored."""

    layers: tuple[str, ...] = knob(choices=("intensity", *LAYERS))
    levels: tuple[int, ...] = knob(ge=0)  # () = every level
    corridor_width_m: float = knob(gt=0.0)
    zstd_level: int = knob(ge=1, le=22)
    reloc_index: bool = knob()
    routes: str = knob()  # "all", "none" or comma-separated route ids (checked against the map)
    route_margin_m: float = knob(ge=0.0)
    route_rows_per_chunk: int = knob(ge=0)  # 0 = the map's chunks
