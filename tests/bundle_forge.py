"""Test helpers: a small signed map site, and an attacker's tools on bundles (rewrite
members, recompute every hash, the manifest and the seal, without the private key)."""

from __future__ import annotations

import hashlib
import json
import struct
import zipfile
from pathlib import Path
from typing import Callable


from mapstore.bundle import MANIFEST, SEAL_LEN, SEAL_PREFIX, SIGNATURE, content_sha256, manifest_bytes, member_key
from mapstore.grid import MapGrid
from pipeline.config import load_config
from pipeline.testing.synthmap import Patch, periodic_texture, publish_repainted
from conftest import invoke

PX = 0.0025
GRID = MapGrid(0.0, 1.0, PX, 400, 400)  # 1 x 1 m, 64-px tiles
PATCH = Patch(0.3, 0.3, 0.45, 0.45, delta=40.0)


def make_site(root: Path) -> dict:
    """A map with two versions, a key pair, signed and unsigned bundles of v1, a signed
    bundle of v2 and a signed delta v1 -> v2."""
    cfg = load_config(None)
    cfg["map"].update({"chunk_px": 64, "shard_px": 256, "layer_cell_px": 16})
    url = str(root / "map")
    tex = periodic_texture(7, 256)
    publish_repainted(url, GRID, tex, PATCH, cfg=cfg)
    key = root / "owner.key"
    site = {"root": root, "url": url, "key": key, "pub": root / "owner.key.pub",
            "signed": root / "v1.zip", "unsigned": root / "v1-unsigned.zip", "signed2": root / "v2.zip",
            "delta": root / "v1-v2.zip"}
    for args in (("keys", "new", key),
                 ("export", url, site["signed"], "--version", "v1", "--sign", key, "--quiet"),
                 ("export", url, site["unsigned"], "--version", "v1", "--quiet"),
                 ("export", url, site["signed2"], "--version", "v2", "--sign", key, "--quiet"),
                 ("export", url, site["delta"], "--version", "v2", "--since", "v1", "--sign", key, "--quiet")):
        r = invoke(*args)
        assert r.exit_code == 0, r.output
    return site


def read_members(path: Path) -> list[tuple[str, bytes]]:
    """Every member (name, bytes) in zip order."""
    with zipfile.ZipFile(path) as z:
        return [(zi.filename, z.read(zi)) for zi in z.infolist()]


def write_sealed(path: Path, members: list[tuple[str, bytes]]) -> None:
    """Write ``members`` (any names, this order) as a stored zip with a valid seal."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED) as z:
        for name, data in members:
            zi = zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0))
            z.writestr(zi, data)
        z.comment = SEAL_PREFIX + b"0" * 64
    data = bytearray(path.read_bytes())
    data[-64:] = hashlib.sha256(bytes(data[:-SEAL_LEN])).hexdigest().encode()
    path.write_bytes(bytes(data))


def forge(src: Path, dst: Path, edit: Callable[[dict[str, bytes]], dict[str, bytes]], *,
          keep_signature: bool = True, manifest_edit: Callable[[dict], None] | None = None) -> None:
    """What an attacker without the private key can do: change members (``edit`` maps the
    data members {name: bytes} to new ones), recompute every member hash, the manifest's
    content hash and the seal, keep (or drop) the old signature."""
    old = dict(read_members(src))
    manifest = json.loads(old.pop(MANIFEST))
    sig = old.pop(SIGNATURE, None)
    data = edit(dict(old))
    manifest["members"] = {n: {"sha256": hashlib.sha256(b).hexdigest(), "bytes": len(b)} for n, b in data.items()}
    manifest["content_sha256"] = content_sha256(manifest["members"])
    if manifest.get("kind") == "delta":
        manifest["changed"] = sorted(data, key=_key)
    if manifest_edit is not None:
        manifest_edit(manifest)
    members = sorted(data.items(), key=lambda kv: _key(kv[0])) + [(MANIFEST, manifest_bytes(manifest))]
    if keep_signature and sig is not None:
        members.append((SIGNATURE, sig))
    write_sealed(dst, members)


def _key(name: str):
    try:
        return (0, member_key(name))
    except Exception:  # noqa: BLE001 (odd names sort last)
        return (1, name)


def move_origin(members: dict[str, bytes], dx_m: float = 0.5) -> dict[str, bytes]:
    """The floor's grid origin moved by ``dx_m`` metres (every zarr.json holding it)."""
    out = dict(members)
    for name, data in members.items():
        if name.endswith("zarr.json") and b"x0_m" in data:
            meta = json.loads(data)
            _shift(meta, dx_m)
            out[name] = json.dumps(meta).encode()
    return out


def _shift(obj, dx: float) -> None:
    if isinstance(obj, dict):
        for k, v in obj.items():
            if k == "x0_m" and isinstance(v, (int, float)):
                obj[k] = v + dx
            elif k == "origin" and isinstance(v, list) and v and isinstance(v[0], (int, float)):
                v[0] += dx
            else:
                _shift(v, dx)
    elif isinstance(obj, list):
        for v in obj:
            _shift(v, dx)


def zstd_bomb(n_bytes: int, declared: int | None = -1) -> bytes:
    """A real zstd frame decoding to ``n_bytes`` zero bytes in RLE blocks (32 kB for 1 GB).
    ``declared``: the decoded size its header declares (-1: the truth, None: none)."""
    if declared == -1:
        declared = n_bytes
    if declared is None:
        head = b"\x28\xb5\x2f\xfd" + bytes([0x00, 0x58])  # no content size, window descriptor (8 MiB)
    else:
        head = b"\x28\xb5\x2f\xfd" + bytes([(3 << 6) | (1 << 5)]) + struct.pack("<Q", declared)
    blocks, left = [], n_bytes
    block = 1 << 17
    while left > 0:
        size = min(block, left)
        left -= size
        blocks.append(struct.pack("<I", (1 if left == 0 else 0) | (1 << 1) | (size << 3))[:3] + b"\0")
    return head + b"".join(blocks)
