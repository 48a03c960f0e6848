"""The vehicle bundle: one sealed zip file holding a map extract (a public contract).

A bundle is what a vehicle carries: a region or a corridor of one map version, at chosen
pyramid levels and layers (:mod:`mapstore.export` makes them), or a *delta* holding only
what changed since an older bundle (:func:`apply_delta` turns old bundle + delta into the
new bundle). This module reads, writes, verifies and patches bundles with numpy, zarr and
the standard library only: the tracker imports it on the vehicle, so it must never import
icechunk, click or anything of ``pipeline``.

Why a zarr v3 hierarchy in a zip file (and not a tiled multi-resolution TIFF):

- it is the map's own layout (:mod:`mapstore.layout`: root attributes, ``/floor`` with
  its OME-Zarr 0.5 multiscales and ``mosaicmap`` attributes, levels, layers), so
  :func:`mapstore.layout.read_floor`, zarr and OME tools read a bundle as they read a map,
  and the grid (coordinates) travels with the pixels;
- random access without loading the whole: a member is found through the zip central
  directory and only its bytes are read (members are stored, not deflated: every chunk is
  already zstd-compressed). Any zip reader works (``zarr.storage.ZipStore`` too); the
  vehicle reads through :class:`BundleStore`, which does not parse the whole directory
  when opened: zipfile (under ZipStore) takes ~145 ms to parse the 13 285 entries of a
  40 x 40 m bundle, BundleStore reads the directory's bytes once and finds a member by
  searching them, so opening a bundle and reading a tile stays well under 100 ms;
- mixed dtypes in one file (uint8 levels, uint16/float32/int32 layers), which a TIFF
  pyramid of one sample type cannot hold;
- one zip member per 256-px tile, so per-member SHA-256 checksums map 1:1 to tiles and a
  delta after a small floor change carries only the few tiles that changed.

Inside the zip (member names are zarr v3 keys)::

    zarr.json, floor/zarr.json, ...   zarr metadata (the map layout, unsharded: shard_px ==
                                      chunk_px; only the exported levels and layers, no poses;
                                      attrs mosaicmap.levels_present / layers_present)
    floor/<k>/c/<row>/<col>           one intensity tile of level k (chunk_px^2, zstd)
    floor/layers/<name>/c/<r>/<c>     one layer chunk: the cells of one level-0 tile
    floor/reloc/features/c/<r>/<c>/0/0  the relocalization index of level-0 tile (r, c)
                                      (optional, below)
    routes/<id>/zarr.json, ...        route panoramas (optional, below): the map's own
    routes/<id>/lines/c/<r>/0         /routes layout (:mod:`mapstore.routes`), unsharded,
    routes/<id>/poses/c/<r>/0         one member per chunk of rows (zstd)
    manifest.json                     the manifest (last member, unless signed)
    manifest.sig                      the map owner's Ed25519 signature (optional, after the
                                      manifest; :mod:`mapstore.signing`)

The arrays keep the map's full grid shape, so tile indices are the map's; a tile the
selection does not reach, or holding no data, is simply absent (zarr reads the fill value:
0 = no data, NaN for the float layers). Pixels of a written tile outside the selection hold
the fill value too.

The relocalization index (``floor/reloc/features``; present when the export held level 0
and was not told ``--no-reloc-index``): a uint8 array ``(tile rows, tile cols, F, 40)``,
chunks ``(1, 1, F, 40)`` (one member per level-0 tile, zstd; absent for a tile without
features), attribute ``mosaicmap_reloc`` {format "mosaicmap-orb-records-v1", tile_px,
margin_px, features_per_tile F, fast_threshold, record_bytes, ...}. Each tile holds up to F
ORB features of the bundle's own level-0 pixels (after the selection's mask), found in the
tile with 32 px of context around it: a record is column and row inside the tile (uint16
LE each, 1/64 px), orientation (uint16, 360/65536 degree), flags (1 = a feature), a zero
byte and the 32-byte descriptor; unused slots are zero, features first
(:func:`tracker.reloc.tile_features` defines it; the vehicle computes the same records
from the tiles when a bundle lacks them). It is an ordinary member: verify, deltas and
apply-delta treat it like any tile; a delta carries the index chunks whose bytes changed
(those of changed tiles and of their neighbours within the 32-px context).

Routes (``routes/<id>``; the omnidirectional route panoramas, ORP, of :mod:`mapstore.routes`):
a group per route with its ``mosaicmap_route`` attributes, ``lines`` uint8 (M, A) and
``poses`` float32 (M, 3) (x, y metres, theta radians, world frame), chunked by rows as in
the map (or ``[export] route_rows_per_chunk``), so that ``mapstore.routes.read_route(root,
id)`` reads a route from a bundle exactly as from a map (:meth:`Bundle.read_route`). A
whole-map bundle holds the routes whole; a region or corridor bundle holds each route cut
to the rows from the first to the last whose pose lies in the selection grown by
``route_margin_m`` (its ``s0_m`` is then the path length of the first row kept); a route
without such a row is left out. Route chunks are ordinary members: verify, deltas and
apply-delta treat them like tiles.

Routes only: a map built from omni logs without floor stages holds ``/routes`` and no
``/floor``. Its bundle holds the root ``zarr.json`` and the routes' members only; the
manifest says ``routes_only: true`` (the key is absent from bundles with a floor), with
``grid`` and ``tile_px`` null, ``levels`` and ``layers`` empty, ``selection.levels`` and
``selection.layers`` empty, ``bounds_m`` the selection's box (or the routes' poses' box for
the whole map) and ``version.number`` the routes' highest publish version. Verify, deltas
and apply-delta work on it as on any bundle; :func:`open_bundle` opens it with
``require_floor=False`` (``Bundle.info`` None; the route methods work).

Determinism: members are written in :func:`member_key` order, stored, with fixed
timestamps and attributes, so the same content always gives the same bytes (a delta and a
full export of the same version agree byte for byte).

Manifest (``manifest.json``, canonical JSON: sorted keys, no spaces)::

    format "mosaicmap-bundle", format_version 1, kind "full" | "delta",
    map_id, version {snapshot, tags, number}, created (ISO 8601 UTC),
    selection {kind "all" | "region" | "corridor", region_m [xmin, ymin, xmax, ymax] | null,
               corridor_m [[x, y], ...] | null, width_m | null, levels [...], layers [...],
               routes "all" | [id, ...] (as requested; [] = none), route_margin_m | null},
    bounds_m [xmin, ymin, xmax, ymax] (the selection clipped to the map, metres),
    grid (level-0 MapGrid.to_attrs(); null: routes only), tile_px (null: routes only),
    levels {k: {shape, pixel_size_m, chunks}},
    layers {name: {shape, cell_px, chunks, dtype}},
    derived {path: {kind, shape, chunks, dtype, tile_px, margin_px, ...}} (only when the
            bundle holds per-tile derived arrays: "floor/reloc/features" {kind "reloc_index",
            format, features_per_tile, record_bytes, ...}),
    routes [{id, rows, s0_m, spacing_m, samples_per_degree, length_m, version, row0 (the
            map row of the bundle's row 0), rows_in_map, cropped}] (the routes held; [] none),
    routes_only true (only in a bundle without a floor, see "Routes only"),
    members {name: {sha256, bytes}} for every other member,
    content_sha256 = SHA-256 over name + NUL + raw sha256 of each member in sorted(name) order.

A delta adds: base {snapshot, number} (the bundle it applies to), changed (names of the
members it carries: the tiles, index and route chunks whose bytes changed, and the
zarr.json members whose bytes changed or that the base lacks), base_members {name: sha256 the base
bundle must hold for that member, or null when the base has none}, removed {name: sha256}
(members of the base the new bundle no longer has) and result (the new full bundle's
manifest header: every key but members and content_sha256). Applying it checks the base
against base_members and removed, so a delta made for another bundle is refused.

The seal: the zip archive comment, the last ``SEAL_LEN`` bytes of the file, is
``mosaicmap-bundle-v1 sha256=<64 hex>``: the SHA-256 of every byte before it (the
end-of-central-directory record with the comment's length included). Together with the
per-member hashes it makes a change of any single byte of the file detectable, including
zip headers, timestamps and the manifest's own text. Opening a bundle does not verify it
(cheap); :func:`verify_bundle` reads everything.

Trust: the seal and the hashes detect damage, not forgery (anyone can recompute them). A
signed bundle carries ``manifest.sig`` (:mod:`mapstore.signing`): the map owner's Ed25519
signature over the manifest's bytes, cut into pages so that a vehicle checks the signature
at open (a few kB) and each member against the signed manifest when it first reads it
(:func:`open_bundle` with ``keys``, :class:`ZipIndex`). ``verify_bundle(keys=...)`` and
``apply_delta(keys=...)`` check the signature in full; a signed delta carries the signature
of the bundle apply-delta makes from it.

Bounded reading (:class:`BundleLimits`, every reader): member names are checked
(:func:`check_member_name`: relative, no ``..``, backslash, drive letter or control
character, length cap); zarr.json members are size-capped and must be UTF-8 JSON; a
chunk's stored size is capped by its array's declared chunk size and a zstd chunk must
declare exactly that decoded size before anything is decompressed (a zstd bomb is refused,
not decoded). Violations are BundleErrors naming the member, printed with control
characters escaped (:func:`quote_name`).
"""

from __future__ import annotations

import hashlib
import io
import json
import mmap
import os
import re
import struct
import threading
import zipfile
import zlib
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Callable, Iterable

import numpy as np
import zarr

from mapstore.grid import MapGrid
from mapstore.knobs import from_table, knob
from mapstore.layout import FloorInfo, read_floor
from mapstore.routes import ROUTES_GROUP, RouteRecord, list_routes, read_route
from mapstore.signing import SIGNATURE, PublicKey, SignatureError, SignedManifest

__all__ = [
    "BUNDLE_FORMAT",
    "BUNDLE_FORMAT_VERSION",
    "MANIFEST",
    "SEAL_LEN",
    "SIGNATURE",
    "BundleError",
    "BundleLimits",
    "check_member_name",
    "quote_name",
    "MemberSink",
    "BundleWriter",
    "ZipIndex",
    "BundleStore",
    "Bundle",
    "member_key",
    "content_sha256",
    "manifest_bytes",
    "read_manifest",
    "open_bundle",
    "verify_bundle",
    "zstd_codec",
    "verify_bytes",
    "apply_delta",
]

BUNDLE_FORMAT = "mosaicmap-bundle"
BUNDLE_FORMAT_VERSION = 1
MANIFEST = "manifest.json"
SEAL_PREFIX = b"mosaicmap-bundle-v1 sha256="
SEAL_LEN = len(SEAL_PREFIX) + 64
EOCD_LEN = 22  # end-of-central-directory record without its comment
EOCD_SIG = b"PK\x05\x06"
LOCAL_SIG = b"PK\x03\x04"
LOCAL_HEADER_LEN = 30
ZIP_TIME = (1980, 1, 1, 0, 0, 0)  # the zip epoch: fixed, so the same members give the same bytes
MEMBER_ATTR = 0o100644 << 16  # a regular file, rw-r--r--
_HEX64 = re.compile(rb"^[0-9a-f]{64}$")
_HASH_BLOCK = 1 << 22
HEADER_KEYS = ("format", "format_version", "kind", "map_id", "version", "created", "selection", "bounds_m",
               "grid", "tile_px", "levels", "layers")
DELTA_KEYS = ("base", "changed", "base_members", "removed", "result")
ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
_DRIVE = re.compile(r"^[A-Za-z]:")
_PLAIN_NAME = re.compile(r"[A-Za-z0-9_.\-]+(?:/[A-Za-z0-9_.\-]+)*")


class BundleError(ValueError):
    """A bundle (or delta) that cannot be used: ``part`` names the bad part (a member, the
    manifest, the seal, ...), ``what`` says what is wrong."""

    def __init__(self, part: str, what: str):
        self.part, self.what = part, what
        super().__init__(f"{part}: {what}")


@dataclass(frozen=True)
class BundleLimits:
    """Bounds on what reading a bundle may cost (``[tracker.bundle]`` in configs/tracker.toml
    holds the same defaults; verify, apply-delta and the tracker apply them).

    Attributes:
        max_metadata_bytes: largest zarr.json member (bytes); it must also be UTF-8 JSON.
        max_chunk_bytes: largest chunk, stored or decoded (bytes); a chunk's stored size is
            also capped by its array's declared chunk size (chunk shape x item size, plus
            zstd's worst-case overhead), and a zstd frame must declare a decoded size equal
            to that chunk size before it is decompressed.
        max_name_length: longest member name (characters).
    """

    max_metadata_bytes: int = knob(ge=1, default=1 << 20)
    max_chunk_bytes: int = knob(ge=1, default=64 << 20)
    max_name_length: int = knob(ge=1, default=256)

    @classmethod
    def from_dict(cls, d: dict) -> "BundleLimits":
        """From a (partial) ``[tracker.bundle]`` table (its ``trusted_keys`` are the caller's);
        :class:`mapstore.knobs.ConfigError` (a ValueError) for an unknown key or a limit that
        is not a positive integer."""
        return from_table(cls, {k: v for k, v in d.items() if k != "trusted_keys"}, name="tracker.bundle",
                          partial=True)


DEFAULT_LIMITS = BundleLimits()


def quote_name(name: str) -> str:
    """``name`` as printed in a message: as is when it is plain printable ASCII, else
    quoted with its control and unusual characters escaped (``repr``), so that a damaged
    bundle never prints a raw control character."""
    if name and all(32 < ord(ch) < 127 for ch in name) and "'" not in name and '"' not in name:
        return name
    return repr(name)


def check_member_name(name: str, max_length: int = DEFAULT_LIMITS.max_name_length) -> str | None:
    """What is wrong with a member name (None when it is acceptable): empty, too long, an
    absolute path, a drive letter, a backslash, a control character, or an empty, ``.`` or
    ``..`` component."""
    if isinstance(name, str) and 0 < len(name) <= max_length and _PLAIN_NAME.fullmatch(name) and (
            "." not in name or not any(p in (".", "..") for p in name.split("/"))):
        return None  # the common case, fast: 17 000 names of a large bundle in a few ms
    if not isinstance(name, str) or not name:
        return "empty name"
    if len(name) > max_length:
        return f"name of {len(name)} characters (at most {max_length})"
    if any(ord(ch) < 32 or 127 <= ord(ch) < 160 for ch in name):
        return "name holds a control character"
    if name.startswith("/"):
        return "absolute path"
    if "\\" in name:
        return "name holds a backslash"
    if _DRIVE.match(name):
        return "name starts with a drive letter"
    if any(p in ("", ".", "..") for p in name.split("/")):
        return "name holds an empty, '.' or '..' component"
    return None


# --- canonical forms ----------------------------------------------------------------------


def member_key(name: str) -> tuple:
    """Sort key of a member name: zarr.json metadata first, then data chunks, then the
    manifest; within each, path components compared as integers where they are digits
    (``floor/0/c/2/10`` after ``floor/0/c/2/9``)."""
    rank = 3 if name == SIGNATURE else 2 if name == MANIFEST else 0 if name.endswith("zarr.json") else 1
    return rank, tuple((0, int(p), "") if p.isdigit() else (1, 0, p) for p in name.split("/"))


def content_sha256(members: dict[str, dict]) -> str:
    """SHA-256 over ``name + NUL + raw sha256`` of each member, in sorted name order."""
    h = hashlib.sha256()
    for name in sorted(members):
        h.update(name.encode() + b"\0" + bytes.fromhex(members[name]["sha256"]))
    return h.hexdigest()


def manifest_bytes(manifest: dict) -> bytes:
    """The canonical JSON text of a manifest (sorted keys, no spaces, no NaN)."""
    return json.dumps(manifest, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()


def _zipinfo(name: str) -> zipfile.ZipInfo:
    zi = zipfile.ZipInfo(name, date_time=ZIP_TIME)
    zi.compress_type = zipfile.ZIP_STORED
    zi.create_system = 3
    zi.external_attr = MEMBER_ATTR
    return zi


# --- writing ------------------------------------------------------------------------------


class MemberSink:
    """Receives members in :func:`member_key` order and records their SHA-256 and size;
    :meth:`finish` adds the manifest. Subclasses store the bytes (:class:`BundleWriter`:
    a sealed zip; the OME-Zarr export: plain files)."""

    def __init__(self) -> None:
        self.members: dict[str, dict] = {}
        self._last: tuple | None = None

    def add(self, name: str, data: bytes) -> None:
        """Add member ``name`` (a zarr key) holding ``data``. Raises ValueError when the
        name is out of order or repeated, or is the manifest's."""
        bad = check_member_name(name)
        if bad:
            raise ValueError(f"member {name!r}: {bad}")
        key = member_key(name)
        if name in (MANIFEST, SIGNATURE) or (self._last is not None and key <= self._last):
            raise ValueError(f"member {name!r} out of order (after a member sorting later or equal)")
        self._last = key
        self.members[name] = {"sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)}
        self._store(name, data)

    def manifest(self, header: dict) -> dict:
        """The complete manifest: ``header`` + members + content_sha256."""
        return {**header, "members": self.members, "content_sha256": content_sha256(self.members)}

    def finish(self, header: dict) -> dict:
        """Write the manifest and close; returns the manifest."""
        manifest = self.manifest(header)
        self._close(manifest_bytes(manifest))
        return manifest

    def abort(self) -> None:
        """Drop everything written so far."""

    def _store(self, name: str, data: bytes) -> None:
        raise NotImplementedError

    def _close(self, manifest: bytes) -> None:
        raise NotImplementedError

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.abort()


class BundleWriter(MemberSink):
    """Writes a sealed bundle at ``path``: under a temporary name beside it, renamed into
    place by :meth:`finish` (a half-written bundle never carries the final name).

    ``sign``: given the manifest's bytes, the ``manifest.sig`` member to write after it
    (:func:`mapstore.signing.signature_document`); None: an unsigned bundle."""

    def __init__(self, path: str | Path, *, sign: Callable[[bytes], bytes] | None = None):
        super().__init__()
        self.sign = sign
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = self.path.with_name(f".tmp-{self.path.name}-{os.getpid()}")
        self._zip = zipfile.ZipFile(self.tmp, "w", zipfile.ZIP_STORED, allowZip64=True)

    def _store(self, name: str, data: bytes) -> None:
        self._zip.writestr(_zipinfo(name), data)

    def _close(self, manifest: bytes) -> None:
        self._zip.writestr(_zipinfo(MANIFEST), manifest)
        if self.sign is not None:
            self._zip.writestr(_zipinfo(SIGNATURE), self.sign(manifest))
        self._zip.comment = SEAL_PREFIX + b"0" * 64
        self._zip.close()
        size = self.tmp.stat().st_size
        with open(self.tmp, "r+b") as f:
            digest = _sha256_range(f, size - SEAL_LEN)
            f.seek(size - 64)
            f.write(digest.encode())
            f.flush()
            os.fsync(f.fileno())
        os.replace(self.tmp, self.path)
        _fsync_dir(self.path.parent)

    def abort(self) -> None:
        try:
            self._zip.close()
        finally:
            self.tmp.unlink(missing_ok=True)


def _sha256_range(f, n: int) -> str:
    """SHA-256 of the first ``n`` bytes of the open file ``f``."""
    f.seek(0)
    h = hashlib.sha256()
    left = n
    while left > 0:
        block = f.read(min(_HASH_BLOCK, left))
        if not block:
            break
        h.update(block)
        left -= len(block)
    return h.hexdigest()


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


# --- reading ------------------------------------------------------------------------------


class ZipIndex:
    """Finds and reads the members of a zip file of stored members (a bundle) without
    parsing its whole central directory: the directory's bytes are read once, and a name
    is found by searching them (checked against the entry's signature and name length).
    Zip64 aware. Thread safe. Raises BundleError("zip structure", ...) when the file has no
    readable end record or directory.

    With ``trust`` (a checked :class:`mapstore.signing.SignedManifest`, set by
    :func:`open_bundle` with trusted keys) every member read is checked against the SHA-256
    and size the signed manifest lists (the page listing it is read and checked on first
    use), a member the signed manifest does not list is never read, and one it lists but
    the zip lacks is an error rather than "no data": BundleError("member NAME", ...)."""

    CD_SIG = b"PK\x01\x02"
    CD_HEADER = 46

    def __init__(self, path: str | Path, *, limits: BundleLimits = DEFAULT_LIMITS):
        self.path = Path(path)
        self.limits = limits
        self.trust: SignedManifest | None = None
        self._lock = threading.Lock()
        self._f = open(self.path, "rb")
        try:
            self._cd = self._read_directory()
        except BaseException:
            self._f.close()
            raise
        self._found: dict[str, tuple[int, int] | None] = {}
        self._all: dict[str, tuple[int, int]] | None = None
        self._listed: dict[str, tuple[str, int] | None] = {}

    def _read(self, offset: int, n: int) -> bytes:
        with self._lock:
            self._f.seek(offset)
            return self._f.read(n)

    def _read_directory(self) -> bytes:
        size = os.fstat(self._f.fileno()).st_size
        tail_n = min(size, EOCD_LEN + 0xFFFF)
        tail = self._read(size - tail_n, tail_n)
        at = tail.rfind(EOCD_SIG)
        while at >= 0 and at + EOCD_LEN + struct.unpack("<H", tail[at + 20:at + 22])[0] != tail_n:
            at = tail.rfind(EOCD_SIG, 0, at)
        if at < 0 or at + EOCD_LEN > len(tail):
            raise BundleError("zip structure", "no end-of-central-directory record: truncated or not a zip file")
        _, _, _, _, entries, cd_size, cd_off, _ = struct.unpack("<4s4H2LH", tail[at:at + EOCD_LEN])
        if 0xFFFFFFFF in (cd_size, cd_off) or entries == 0xFFFF:  # zip64: locator before the record
            eocd_pos = size - tail_n + at
            loc = self._read(max(0, eocd_pos - 20), 20)
            if len(loc) != 20 or loc[:4] != b"PK\x06\x07":
                raise BundleError("zip structure", "zip64 locator missing")
            rec = self._read(struct.unpack("<Q", loc[8:16])[0], 56)
            if len(rec) != 56 or rec[:4] != b"PK\x06\x06":
                raise BundleError("zip structure", "zip64 end record missing")
            cd_size, cd_off = struct.unpack("<QQ", rec[40:56])
        if cd_off + cd_size > size:
            raise BundleError("zip structure", "central directory runs past the end of the file: truncated or damaged")
        cd = self._read(cd_off, cd_size)
        if len(cd) != cd_size or (cd_size and cd[:4] != self.CD_SIG):
            raise BundleError("zip structure", "central directory unreadable: truncated or damaged")
        return cd

    def _entry(self, pos: int) -> tuple[str, tuple[int, int], int]:
        """(name, (local header offset, stored size), next entry position) of the entry at ``pos``."""
        cd = self._cd
        if pos + self.CD_HEADER > len(cd):
            raise BundleError("zip structure", "central directory entry truncated")
        (csize, usize, n_name, n_extra, n_comment) = struct.unpack("<2L3H", cd[pos + 20:pos + 34])
        offset = struct.unpack("<L", cd[pos + 42:pos + 46])[0]
        raw = cd[pos + 46:pos + 46 + n_name]
        try:
            name = raw.decode()
        except UnicodeDecodeError:
            raise BundleError(f"member {quote_name(raw.decode('utf-8', 'replace'))}",
                              "name is not UTF-8 (central directory damaged)") from None
        if 0xFFFFFFFF in (csize, usize, offset):
            extra = cd[pos + 46 + n_name:pos + 46 + n_name + n_extra]
            i = 0
            while i + 4 <= len(extra):
                tag, n = struct.unpack("<2H", extra[i:i + 4])
                if tag == 1:
                    vals = list(struct.unpack(f"<{n // 8}Q", extra[i + 4:i + 4 + 8 * (n // 8)]))
                    if usize == 0xFFFFFFFF and vals:
                        usize = vals.pop(0)
                    if csize == 0xFFFFFFFF and vals:
                        csize = vals.pop(0)
                    if offset == 0xFFFFFFFF and vals:
                        offset = vals.pop(0)
                    break
                i += 4 + n
        return name, (offset, csize), pos + 46 + n_name + n_extra + n_comment

    def entries(self) -> dict[str, tuple[int, int]]:
        """Every member: name -> (local header offset, stored size) (parsed once). Raises
        BundleError for a name :func:`check_member_name` refuses."""
        if self._all is None:
            out, pos = {}, 0
            while pos + self.CD_HEADER <= len(self._cd) and self._cd[pos:pos + 4] == self.CD_SIG:
                name, loc, pos = self._entry(pos)
                bad = check_member_name(name, self.limits.max_name_length)
                if bad:
                    raise BundleError(f"member {quote_name(name)}", bad)
                out[name] = loc
            self._all = out
        return self._all

    def listed(self, name: str) -> tuple[str, int] | None:
        """(sha256, bytes) the signed manifest lists for ``name`` (None: not listed, or no trust)."""
        if self.trust is None:
            return None
        if name not in self._listed:
            try:
                self._listed[name] = self.trust.lookup(name, lambda a, b: self._raw(MANIFEST, a, b) or b"")
            except SignatureError as e:
                raise BundleError(f"member {quote_name(name)}", str(e)) from None
        return self._listed[name]

    def expect(self, names: Iterable[str]) -> None:
        """Look up the signed manifest's entries of ``names`` at once, ahead of reading them
        (a reader about to read many members, e.g. every chunk of the relocalization index
        at start-up: each manifest page read, checked and parsed once). No-op without trust."""
        if self.trust is None:
            return
        todo = [n for n in names if n not in self._listed]
        try:
            self._listed.update(self.trust.lookup_many(todo, lambda a, b: self._raw(MANIFEST, a, b) or b""))
        except SignatureError as e:
            raise BundleError(MANIFEST, str(e)) from None

    def find(self, name: str) -> tuple[int, int] | None:
        """(local header offset, stored size) of member ``name``, or None. With ``trust``,
        a member the signed manifest lists but the zip lacks raises BundleError."""
        hit = self._find(name)
        if hit is None and self.trust is not None and name not in (MANIFEST, SIGNATURE) \
                and self.listed(name) is not None:
            raise BundleError(f"member {quote_name(name)}", "missing: listed in the signed manifest, absent from the zip")
        return hit

    def _find(self, name: str) -> tuple[int, int] | None:
        if self._all is not None:
            return self._all.get(name)
        if name in self._found:
            return self._found[name]
        key, hit = name.encode(), None
        last = name in (MANIFEST, SIGNATURE)  # the last entries: searched from the end
        start, end = 0, len(self._cd)
        while True:
            at = self._cd.rfind(key, 0, end) if last else self._cd.find(key, start)
            if at < 0:
                break
            pos = at - self.CD_HEADER
            if (pos >= 0 and self._cd[pos:pos + 4] == self.CD_SIG
                    and struct.unpack("<H", self._cd[pos + 28:pos + 30])[0] == len(key)):
                hit = self._entry(pos)[1]
                break
            start, end = at + 1, at
        self._found[name] = hit
        return hit

    def _raw(self, name: str, start: int = 0, end: int | None = None, *,
             loc: tuple[int, int] | None = None) -> bytes | None:
        """Bytes ``[start, end)`` of member ``name`` as stored (unchecked), or None when absent."""
        loc = loc or self._find(name)
        if loc is None:
            return None
        offset, size = loc
        key = name.encode()
        head = self._read(offset, LOCAL_HEADER_LEN + len(key))
        if len(head) < LOCAL_HEADER_LEN or head[:4] != LOCAL_SIG:
            raise BundleError(f"member {quote_name(name)}", "local header damaged (no signature)")
        method, = struct.unpack("<H", head[8:10])
        n_name, n_extra = struct.unpack("<2H", head[26:30])
        if head[LOCAL_HEADER_LEN:] != key or n_name != len(key):
            raise BundleError(f"member {quote_name(name)}", "local header damaged (it names another member)")
        if method != zipfile.ZIP_STORED:
            raise BundleError(f"member {quote_name(name)}", "not stored (compressed members are not part of the format)")
        data_at = offset + LOCAL_HEADER_LEN + n_name + n_extra
        end = size if end is None else min(end, size)
        start = min(max(0, start), end)
        data = self._read(data_at + start, end - start)
        if len(data) != end - start:
            raise BundleError(f"member {quote_name(name)}", "data runs past the end of the file (truncated)")
        return data

    def read(self, name: str, start: int = 0, end: int | None = None) -> bytes | None:
        """Bytes ``[start, end)`` of member ``name`` (all by default), or None when absent.
        With ``trust`` the whole member is read and checked against the signed manifest
        (BundleError naming it when it is not listed, or its bytes differ)."""
        if self.trust is None or name in (MANIFEST, SIGNATURE):
            return self._raw(name, start, end)  # read_manifest checks the manifest against the signature
        loc = self.find(name)
        if loc is None:
            return None
        want = self._listed.get(name) or self.listed(name)
        if want is None:
            raise BundleError(f"member {quote_name(name)}", "not listed in the signed manifest: not read")
        if loc[1] != want[1]:
            raise BundleError(f"member {quote_name(name)}", f"{loc[1]} bytes, the signed manifest says {want[1]}: "
                                                           "forged or damaged")
        data = self._raw(name, loc=loc)
        if hashlib.sha256(data).hexdigest() != want[0]:
            raise BundleError(f"member {quote_name(name)}", "sha256 differs from the signed manifest: forged or damaged")
        if start or end is not None:
            end = len(data) if end is None else min(end, len(data))
            data = data[min(max(0, start), end):end]
        return data

    def close(self) -> None:
        self._f.close()


class BundleStore(zarr.abc.store.Store):
    """A read-only zarr store over a bundle file, through :class:`ZipIndex` (see the
    module docstring for why not ``zarr.storage.ZipStore``).

    Bounded reading (:class:`BundleLimits`): a ``zarr.json`` member must be at most
    ``max_metadata_bytes`` and UTF-8 JSON; a chunk member ``<array>/c/...`` at most its
    array's declared chunk size (chunk shape x item size, plus zstd's worst-case overhead,
    and at most ``max_chunk_bytes``), and a zstd chunk must declare (in its frame header)
    a decoded size equal to that chunk size, checked before anything is decompressed.
    Codec chains other than ``bytes`` or ``bytes, zstd`` are refused. Each violation is a
    BundleError naming the member."""

    supports_writes = False
    supports_deletes = False
    supports_listing = True

    def __init__(self, path: str | Path, *, limits: BundleLimits = DEFAULT_LIMITS):
        super().__init__(read_only=True)
        self.path = Path(path)
        self.limits = limits
        self.index = ZipIndex(self.path, limits=limits)
        self._arrays: dict[str, tuple[int, bool]] = {}
        self._meta: dict[str, bytes] = {}
        self._is_open = True

    def __eq__(self, other: object) -> bool:
        return isinstance(other, BundleStore) and self.path == other.path

    def __str__(self) -> str:
        return f"bundle://{self.path}"

    def metadata(self, key: str) -> dict | None:
        """The parsed zarr.json member ``key`` (checked: size, UTF-8, JSON object), or None."""
        data = self._metadata_bytes(key)
        return None if data is None else json.loads(data)

    def _metadata_bytes(self, key: str) -> bytes | None:
        """A zarr.json member, checked once (size, UTF-8 JSON, and with trust its signed
        hash) and kept: zarr reads the same metadata several times while opening."""
        if key in self._meta:
            return self._meta[key]
        data = self._metadata_read(key)
        if data is not None:
            self._meta[key] = data
        return data

    def _metadata_read(self, key: str) -> bytes | None:
        loc = self.index.find(key)
        if loc is None:
            return None
        if loc[1] > self.limits.max_metadata_bytes:
            raise BundleError(f"member {quote_name(key)}", f"metadata of {loc[1]} bytes (at most "
                                                           f"{self.limits.max_metadata_bytes})")
        data = self.index.read(key)
        _, problem = metadata_problem(data, self.limits)
        if problem:
            raise BundleError(f"member {quote_name(key)}", problem)
        return data

    def _chunk_spec(self, array: str) -> tuple[int, bool]:
        """(decoded bytes of one chunk, zstd compressed) of the array at path ``array``."""
        spec = self._arrays.get(array)
        if spec is None:
            meta = self.metadata(f"{array}/zarr.json")
            if meta is None:
                raise BundleError(f"member {quote_name(array + '/zarr.json')}",
                                  "missing: a chunk without its array's metadata")
            spec = self._arrays[array] = array_chunk_spec(array, meta, self.limits)
        return spec

    def _chunk(self, key: str) -> bytes | None:
        spec = self._chunk_spec(key.rsplit("/c/", 1)[0])
        loc = self.index.find(key)
        if loc is None:
            return None
        problem = check_chunk(spec, loc[1], None)
        if problem is None:
            data = self.index.read(key)
            problem = check_chunk(spec, len(data), data)
        if problem:
            raise BundleError(f"member {quote_name(key)}", problem)
        return data

    def read_checked(self, key: str) -> bytes | None:
        """Member ``key`` through the bounds above (a zarr.json or a chunk), or None when absent."""
        if key.endswith("zarr.json"):
            return self._metadata_bytes(key)
        if "/c/" in key:
            return self._chunk(key)
        raise BundleError(f"member {quote_name(key)}", "neither zarr metadata nor a chunk: not read")

    def _get(self, key: str, prototype, byte_range) -> "zarr.core.buffer.Buffer | None":
        from zarr.abc.store import OffsetByteRequest, RangeByteRequest, SuffixByteRequest

        if key.endswith("zarr.json") or "/c/" in key:
            data = self.read_checked(key)
            if data is not None and byte_range is not None:
                if isinstance(byte_range, RangeByteRequest):
                    data = data[byte_range.start:byte_range.end]
                elif isinstance(byte_range, OffsetByteRequest):
                    data = data[byte_range.offset:]
                elif isinstance(byte_range, SuffixByteRequest):
                    data = data[max(0, len(data) - byte_range.suffix):]
                else:
                    raise TypeError(f"unexpected byte range {byte_range!r}")
        elif self.index.find(key) is None:
            data = None  # zarr probing keys of other formats (.zgroup, ...)
        else:
            raise BundleError(f"member {quote_name(key)}", "neither zarr metadata nor a chunk: not read")
        return None if data is None else prototype.buffer.from_bytes(data)

    async def get(self, key, prototype, byte_range=None):
        return self._get(key, prototype, byte_range)

    async def get_partial_values(self, prototype, key_ranges):
        return [self._get(key, prototype, br) for key, br in key_ranges]

    async def exists(self, key: str) -> bool:
        return self.index.find(key) is not None

    async def set(self, key, value) -> None:
        self._check_writable()

    async def delete(self, key) -> None:
        self._check_writable()

    async def list(self):
        for key in self.index.entries():
            yield key

    async def list_prefix(self, prefix: str):
        for key in self.index.entries():
            if key.startswith(prefix):
                yield key

    async def list_dir(self, prefix: str):
        prefix = prefix.rstrip("/")
        seen = set()
        for key in self.index.entries():
            if prefix:
                if not key.startswith(prefix + "/"):
                    continue
                key = key[len(prefix) + 1:]
            child = key.split("/")[0]
            if child and child not in seen:
                seen.add(child)
                yield child

    def close(self) -> None:
        super().close()
        self.index.close()


def metadata_problem(data: bytes, limits: BundleLimits = DEFAULT_LIMITS) -> tuple[dict | None, str | None]:
    """(parsed zarr.json, None) or (None, what is wrong: too large, not UTF-8, not JSON)."""
    if len(data) > limits.max_metadata_bytes:
        return None, f"metadata of {len(data)} bytes (at most {limits.max_metadata_bytes})"
    try:
        meta = json.loads(data.decode("utf-8"))
    except UnicodeDecodeError as e:
        return None, f"metadata is not UTF-8 (byte {e.start})"
    except ValueError as e:
        return None, f"metadata is not JSON ({quote_name(str(e))})"
    if not isinstance(meta, dict):
        return None, "metadata is not a JSON object"
    return meta, None


def array_chunk_spec(array: str, meta: dict, limits: BundleLimits = DEFAULT_LIMITS) -> tuple[int, bool]:
    """(decoded bytes of one chunk, zstd compressed) of array ``array`` from its zarr.json
    ``meta``. BundleError naming the metadata when it is unusable, declares codecs other
    than ``bytes`` (+ ``zstd``) or chunks above ``limits.max_chunk_bytes``."""
    where = f"member {quote_name(array + '/zarr.json')}"
    try:
        shape = meta["chunk_grid"]["configuration"]["chunk_shape"]
        if not (isinstance(shape, list) and all(isinstance(v, int) and not isinstance(v, bool) and v > 0
                                                for v in shape)):
            raise ValueError(f"chunk_shape {shape!r}")
        dtype = meta["data_type"]
        if not isinstance(dtype, str):
            raise ValueError(f"data_type {dtype!r}")
        itemsize = np.dtype(dtype).itemsize
        codecs = [c.get("name") if isinstance(c, dict) else c for c in meta.get("codecs", [])]
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise BundleError(where, f"array metadata unusable ({type(e).__name__}: {quote_name(str(e))[:100]})") from None
    n = 1
    for v in shape:
        n *= v
    n *= itemsize
    if codecs not in (["bytes"], ["bytes", "zstd"]):
        raise BundleError(where, f"codecs {quote_name(str(codecs))[:100]}: a bundle holds bytes or bytes + zstd only")
    if n > limits.max_chunk_bytes:
        raise BundleError(where, f"chunks of {n} bytes (at most {limits.max_chunk_bytes})")
    return n, codecs[-1] == "zstd"


def check_chunk(spec: tuple[int, bool], stored: int, data: bytes | None) -> str | None:
    """What is wrong with a chunk of an array of ``spec`` (:func:`array_chunk_spec`):
    ``stored`` bytes, and when ``data`` is given, its zstd frame header (the decoded size
    it declares must be the chunk size: nothing is decompressed to learn it)."""
    n, zstd = spec
    cap = n + n // 128 + 1024 if zstd else n
    if stored > cap:
        return f"chunk of {stored} bytes stored, more than its array's chunk size allows ({cap})"
    if data is None:
        return None
    if zstd:
        size = zstd_content_size(data)
        if size != n:
            what = "declares no decoded size" if size is None else f"declares {size} decoded bytes"
            return f"zstd chunk {what}, its array's chunks hold {n}: refused before decompressing"
    elif len(data) != n:
        return f"chunk of {len(data)} bytes, its array's chunks hold {n}"
    return None


def zstd_content_size(data: bytes) -> int | None:
    """The decoded size a zstd frame declares in its header (RFC 8878, 3.1.1.1), or None
    when it declares none or ``data`` does not start with a zstd frame."""
    if len(data) < 6 or data[:4] != ZSTD_MAGIC:
        return None
    fhd = data[4]
    fcs_flag, single, dict_flag = fhd >> 6, (fhd >> 5) & 1, fhd & 3
    pos = 5 + (0 if single else 1) + (0, 1, 2, 4)[dict_flag]
    n = (1 if single else 0, 2, 4, 8)[fcs_flag]
    if n == 0 or len(data) < pos + n:
        return None
    value = int.from_bytes(data[pos:pos + n], "little")
    return value + 256 if n == 2 else value


def read_manifest(path: str | Path, *, index: ZipIndex | None = None) -> dict:
    """The manifest of a bundle (cheap). Raises BundleError naming the part. Unverified,
    unless ``index`` (an open :class:`ZipIndex` of the bundle) holds a checked signature:
    then the manifest's bytes must be the signed ones."""
    own = index is None
    if own:
        try:
            index = ZipIndex(path)
        except FileNotFoundError:
            raise BundleError("file", "not found") from None
        except OSError as e:
            raise BundleError("file", f"cannot read ({e.strerror})") from None
    try:
        data = index.read(MANIFEST)
    finally:
        if own:
            index.close()
    if data is None:
        raise BundleError(MANIFEST, "missing: not a mosaicmap bundle")
    if index.trust is not None:
        try:
            index.trust.check_manifest(data)
        except SignatureError as e:
            raise BundleError(MANIFEST, str(e)) from None
    return _parse_manifest(data)


def read_signature(index: ZipIndex, keys: Iterable[PublicKey]) -> SignedManifest:
    """The bundle's ``manifest.sig`` checked against ``keys`` (BundleError("manifest.sig",
    ...) when the bundle is unsigned, or signed by no trusted key, or forged)."""
    loc = index._find(SIGNATURE)
    if loc is None:
        raise BundleError(SIGNATURE, "missing: the bundle is not signed (export it with --sign KEY)")
    if loc[1] > (1 << 22):
        raise BundleError(SIGNATURE, f"{loc[1]} bytes: not a signature document")
    try:
        return SignedManifest.check(index._raw(SIGNATURE), keys)
    except SignatureError as e:
        raise BundleError(SIGNATURE, str(e)) from None


def _parse_manifest(data: bytes) -> dict:
    try:
        m = json.loads(data)
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise BundleError(MANIFEST, f"not valid JSON ({e})") from None
    if not isinstance(m, dict) or m.get("format") != BUNDLE_FORMAT:
        raise BundleError(MANIFEST, f"format is not {BUNDLE_FORMAT!r}")
    if m.get("format_version") != BUNDLE_FORMAT_VERSION:
        raise BundleError(MANIFEST, f"unknown format_version {m.get('format_version')!r} "
                                    f"(this reader knows {BUNDLE_FORMAT_VERSION})")
    need = HEADER_KEYS + ("members", "content_sha256") + (DELTA_KEYS if m.get("kind") == "delta" else ())
    missing = [k for k in need if k not in m]
    if missing:
        raise BundleError(MANIFEST, f"lacks key(s) {', '.join(missing)}")
    if m["kind"] not in ("full", "delta"):
        raise BundleError(MANIFEST, f"unknown kind {m['kind']!r}")
    members = m["members"]
    if not isinstance(members, dict) or not all(
            isinstance(v, dict) and isinstance(v.get("sha256"), str) and isinstance(v.get("bytes"), int)
            for v in members.values()):
        raise BundleError(MANIFEST, "members must map names to {sha256, bytes}")
    return m


@dataclass
class Bundle:
    """An open bundle (see :func:`open_bundle`). ``root`` is the zarr group over a
    read-only :class:`BundleStore`; ``info`` the map layout (grid, tile size, version);
    ``levels`` the intensity levels held, ``layers`` the cell layers held (coverage,
    texture, uniqueness, updated).

    Coordinates follow :mod:`mapstore.grid`: pixel (row r, col c) of level k is centred at
    ``level_grid(k).pixel_to_world(c, r)`` (metres, world frame); level-0 tile (r, c)
    covers pixels ``[r * tile_px, (r + 1) * tile_px) x [c * tile_px, (c + 1) * tile_px)``.
    """

    path: Path
    root: zarr.Group
    info: FloorInfo | None
    levels: tuple[int, ...]
    layers: tuple[str, ...]
    store: BundleStore = field(repr=False)
    _plain: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @property
    def has_floor(self) -> bool:
        """False for a bundle of route panoramas only (``info`` None, no levels or layers)."""
        return self.info is not None

    def _floor(self) -> FloorInfo:
        if self.info is None:
            raise BundleError("floor", f"{self.path} holds route panoramas only, no floor map")
        return self.info

    @property
    def grid(self) -> MapGrid:
        """The level-0 grid (the map's)."""
        return self._floor().grid

    @property
    def tile_px(self) -> int:
        """Side of a tile (chunk) in pixels of its level."""
        return self._floor().spec.chunk_px

    @cached_property
    def manifest(self) -> dict:
        """The manifest (read on first use; checked against the signature when the bundle
        was opened with trusted keys, else unverified)."""
        return read_manifest(self.path, index=self.store.index)

    @property
    def signed(self) -> bool:
        """Whether the bundle was opened with its signature checked (every member read is
        then checked against the signed manifest)."""
        return self.store.index.trust is not None

    def level_grid(self, k: int) -> MapGrid:
        return self._floor().level_grid(self._level(k))

    def layer_grid(self, name: str) -> MapGrid:
        return self._floor().layer_grid(self._layer(name))

    def tiles_shape(self, k: int) -> tuple[int, int]:
        """Tiles (rows, cols) of level k."""
        rows, cols = self.level_grid(k).shape
        return -(-rows // self.tile_px), -(-cols // self.tile_px)

    def read(self, level: int, rows: slice = slice(None), cols: slice = slice(None)) -> np.ndarray:
        """uint8 pixels of ``level`` in the window (0 = no data or outside the selection)."""
        with _guard(self.path, f"floor/{self._level(level)}"):
            return self.root[f"floor/{level}"][rows, cols]

    def tile_slices(self, level: int, r: int, c: int) -> tuple[slice, slice]:
        """The pixel window of tile (r, c) of ``level``, clipped at the array's edges."""
        rows, cols = self.level_grid(level).shape
        t = self.tile_px
        if not (0 <= r < -(-rows // t) and 0 <= c < -(-cols // t)):
            raise ValueError(f"tile ({r}, {c}) outside level {level}'s {self.tiles_shape(level)} tiles")
        return slice(r * t, min((r + 1) * t, rows)), slice(c * t, min((c + 1) * t, cols))

    def read_tile(self, level: int, r: int, c: int) -> np.ndarray:
        """uint8 pixels of tile (r, c) of ``level`` (edge tiles are clipped).

        A tile is one chunk: when the level is stored as mosaicmap writes it (uint8 chunks
        of one tile, ``bytes`` + ``zstd`` or ``bytes``, default chunk keys) the chunk is
        read through the store's bounds and trust checks and decoded here (~0.08 ms for a
        256 px tile), not through zarr's array machinery (~0.9 ms a call); any other
        layout goes through zarr."""
        rows, cols = self.tile_slices(level, r, c)
        name = f"floor/{int(level)}/c/{int(r)}/{int(c)}"
        with _guard(self.path, f"member {name}"):
            plain = self._plain_tiles(int(level))
            if plain is None:
                return self.root[f"floor/{int(level)}"][rows, cols]
            h, w = rows.stop - rows.start, cols.stop - cols.start
            data = self.store.read_checked(name)
            if data is None:
                return np.full((h, w), plain[1], np.uint8)
            t = self.tile_px
            if plain[0]:
                out = np.empty(t * t, np.uint8)
                zstd_codec().decode(data, out=out)
            else:
                out = np.frombuffer(data, np.uint8).copy()
            return out.reshape(t, t)[:h, :w]

    def _plain_tiles(self, level: int) -> tuple[bool, int] | None:
        """(zstd compressed, fill value) when ``level``'s array is stored as mosaicmap
        writes it (see :meth:`read_tile`), else None; decided once per level. Its codecs
        and chunk size are the bounded reader's (:func:`array_chunk_spec`)."""
        if level not in self._plain:
            array, t, out = f"floor/{self._level(level)}", self.tile_px, None
            nbytes, zstd = self.store._chunk_spec(array)
            meta = self.store.metadata(f"{array}/zarr.json")
            try:
                if (nbytes == t * t and meta["data_type"] == "uint8" and len(meta["shape"]) == 2
                        and meta["chunk_grid"] == {"name": "regular", "configuration": {"chunk_shape": [t, t]}}
                        and meta["chunk_key_encoding"] in ({"name": "default"},
                                                           {"name": "default", "configuration": {"separator": "/"}})
                        and isinstance(meta["fill_value"], int) and 0 <= meta["fill_value"] <= 255
                        and not meta.get("storage_transformers")):
                    out = (zstd, int(meta["fill_value"]))
            except (KeyError, TypeError, AttributeError):
                out = None  # zarr will say what is wrong with it
            self._plain[level] = out
        return self._plain[level]

    def has_tile(self, level: int, r: int, c: int) -> bool:
        """Whether the bundle holds tile (r, c) of ``level`` (else it reads as no data)."""
        self.tile_slices(level, r, c)
        return self.store.index.find(f"floor/{self._level(level)}/c/{r}/{c}") is not None

    def read_layer(self, name: str, rows: slice = slice(None), cols: slice = slice(None)) -> np.ndarray:
        """Cells of layer ``name`` in the window (fill value where no data)."""
        with _guard(self.path, f"floor/layers/{self._layer(name)}"):
            return self.root[f"floor/layers/{name}"][rows, cols]

    def routes(self) -> list[str]:
        """Sorted ids of the route panoramas the bundle holds ([] when none)."""
        return list_routes(self.root)

    def read_route(self, route_id: str) -> RouteRecord:
        """The route panorama ``route_id`` (:func:`mapstore.routes.read_route`: lines,
        poses in metres / radians, world frame, s0_m of its first row). KeyError when the
        bundle does not hold it."""
        with _guard(self.path, f"routes/{route_id}"):
            return read_route(self.root, route_id)

    def close(self) -> None:
        self.store.close()

    def __enter__(self) -> "Bundle":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _level(self, k: int) -> int:
        if int(k) not in self.levels:
            raise ValueError(f"level {k} is not in the bundle (levels {list(self.levels)})")
        return int(k)

    def _layer(self, name: str) -> str:
        if name not in self.layers:
            raise ValueError(f"layer {name!r} is not in the bundle (layers {list(self.layers)})")
        return name


class _guard:
    """Turns what zarr or a codec raises on a damaged member into a BundleError naming
    ``what`` (an array) of the bundle at ``path``; BundleError and KeyError pass."""

    def __init__(self, path: Path, what: str):
        self.path, self.what = path, what

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None or issubclass(exc_type, (BundleError, KeyError)) or not issubclass(exc_type, Exception):
            return False
        raise BundleError(quote_name(self.what), f"unreadable ({exc_type.__name__}: "
                                                 f"{quote_name(str(exc))[:200]})") from None


def zstd_codec():
    """numcodecs' Zstd codec (zarr's own), made once: what a bundle's zstd chunks are
    decoded with when they are read without zarr (:meth:`Bundle.read_tile`, the tracker's
    relocalization index)."""
    global _ZSTD
    if _ZSTD is None:
        import numcodecs

        _ZSTD = numcodecs.Zstd()
    return _ZSTD


_ZSTD = None


def open_bundle(path: str | Path, *, require_floor: bool = True, keys: Iterable[PublicKey] | None = None,
                limits: BundleLimits = DEFAULT_LIMITS) -> Bundle:
    """Open a bundle for reading (cheap: the zip directory and the zarr metadata; no
    full verification, see :func:`verify_bundle`). Raises BundleError when it is not one.

    ``keys``: trusted public keys. Given (even empty), the bundle's signature
    (``manifest.sig``) must check against one of them, else BundleError("manifest.sig",
    ...); every member read is then checked against the signed manifest (on first read,
    see :class:`ZipIndex`). None: no signature check (development). Reads are bounded by
    ``limits`` either way (:class:`BundleStore`).

    A bundle of route panoramas only (no ``floor``; manifest ``routes_only``) raises
    BundleError("floor", ...) unless ``require_floor`` is False: then ``Bundle.info`` is
    None, ``levels`` and ``layers`` are empty and only the route methods work."""
    path = Path(path)
    if not path.is_file():
        raise BundleError("file", f"{path}: not found")
    try:
        store = BundleStore(path, limits=limits)
    except OSError as e:
        raise BundleError("file", f"{path}: cannot read ({e.strerror})") from None
    try:
        if keys is not None:
            store.index.trust = read_signature(store.index, keys)
        root = zarr.open_group(store, mode="r", zarr_format=3)  # no probing of zarr v2 keys (a scan of the zip directory each)
        if "floor" not in root and ROUTES_GROUP in root:
            if require_floor:
                raise BundleError("floor", f"{path} holds route panoramas only ({', '.join(list_routes(root))}), "
                                           "no floor map")
            return Bundle(path, root, None, (), (), store)
        info = read_floor(root)
        meta = root["floor"].attrs["mosaicmap"]
        levels = tuple(int(k) for k in meta.get("levels_present", range(info.levels)))
        layers = tuple(meta["layers_present"] if "layers_present" in meta else root["floor/layers"].array_keys())
    except BundleError:
        store.close()
        raise
    except Exception as e:  # noqa: BLE001 (untrusted metadata: zarr and read_floor raise many kinds)
        store.close()
        raise BundleError("zarr.json", f"not a mosaicmap map extract ({type(e).__name__}: "
                                       f"{quote_name(str(e))[:200]})") from None
    return Bundle(path, root, info, levels, layers, store)


# --- verifying ----------------------------------------------------------------------------


def _check_seal(mm, size: int) -> tuple[str | None, bool]:
    """(problem or None, whether the seal text was found at the end of the file)."""
    if size < EOCD_LEN + SEAL_LEN:
        return f"truncated: {size} bytes, too short for a sealed bundle", False
    tail = mm[size - SEAL_LEN:size]
    eocd = mm[size - SEAL_LEN - EOCD_LEN:size - SEAL_LEN]
    eocd_ok = eocd[:4] == EOCD_SIG and struct.unpack("<H", eocd[20:22])[0] == SEAL_LEN
    if not (tail.startswith(SEAL_PREFIX) and _HEX64.match(tail[len(SEAL_PREFIX):])):
        if eocd_ok:
            return "seal: damaged (the zip comment is not 'mosaicmap-bundle-v1 sha256=<64 hex>')", False
        if mm.rfind(SEAL_PREFIX, max(0, size - 2 * SEAL_LEN - EOCD_LEN)) >= 0:
            return "truncated: the file ends inside its seal", False
        return "truncated or not a mosaicmap bundle: no seal at the end of the file", False
    if not eocd_ok:
        return "zip structure: end-of-central-directory record damaged", True
    h = hashlib.sha256()
    view = memoryview(mm)
    for i in range(0, size - SEAL_LEN, _HASH_BLOCK):
        h.update(view[i:min(i + _HASH_BLOCK, size - SEAL_LEN)])
    view.release()
    if h.hexdigest() != tail[len(SEAL_PREFIX):].decode():
        return "seal: sha256 mismatch", True
    return None, True


def _member_data(mm, zi: zipfile.ZipInfo) -> tuple[bytes | None, str | None]:
    """The stored bytes of ``zi`` read through its local header (problem when damaged)."""
    off = zi.header_offset
    head = mm[off:off + LOCAL_HEADER_LEN]
    if len(head) < LOCAL_HEADER_LEN or head[:4] != LOCAL_SIG:
        return None, "local header damaged (no signature)"
    (_, _, flags, method, _, _, _, _, _, n_name, n_extra) = struct.unpack("<4s5H3L2H", head)
    name = mm[off + LOCAL_HEADER_LEN:off + LOCAL_HEADER_LEN + n_name]
    if name != zi.filename.encode():
        return None, f"local header damaged (it names {name.decode(errors='replace')!r})"
    if method != zipfile.ZIP_STORED or zi.compress_type != zipfile.ZIP_STORED:
        return None, "not stored (compressed members are not part of the format)"
    start = off + LOCAL_HEADER_LEN + n_name + n_extra
    if start + zi.compress_size > len(mm):
        return None, "data runs past the end of the file"
    data = bytes(mm[start:start + zi.compress_size])
    if zlib.crc32(data) != zi.CRC:
        return data, "CRC-32 mismatch (data or zip header damaged)"
    return data, None


def verify_bundle(path: str | Path, *, keys: Iterable[PublicKey] | None = None,
                  limits: BundleLimits = DEFAULT_LIMITS) -> list[str]:
    """Check a bundle completely; returns the problems found, [] when it is intact.

    Checks the seal (SHA-256 of the file), the zip structure, every member's name
    (:func:`check_member_name`), local header, CRC and SHA-256 against the manifest, the
    member set (none missing, none extra), the manifest's content hash, and the bounds of
    :class:`BundleStore` (zarr.json size, UTF-8 JSON; chunk sizes against their array's
    declared chunk size, zstd frame headers). With ``keys`` (trusted public keys) the
    signature too: ``manifest.sig`` must check against one of them and sign this
    manifest's bytes (and, for a delta, carry the signed result). Each problem names its
    part: ``member floor/0/c/3/4: sha256 mismatch``, ``manifest.json: ...``, ``seal:
    ...``, ``manifest.sig: ...``, ``zip structure: ...``, ``truncated: ...``.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        f = open(path, "rb")
    except OSError as e:
        return [f"file: cannot read ({e.strerror})"]
    with f:
        if size == 0:
            return ["truncated: empty file"]
        with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
            return _verify(mm, keys, limits)


def verify_bytes(data: bytes, *, keys: Iterable[PublicKey] | None = None,
                 limits: BundleLimits = DEFAULT_LIMITS) -> list[str]:
    """:func:`verify_bundle` of a bundle held in memory (e.g. as received)."""
    return _verify(data, keys, limits) if len(data) else ["truncated: empty file"]


def _verify(mm, keys: Iterable[PublicKey] | None = None, limits: BundleLimits = DEFAULT_LIMITS) -> list[str]:
    """Verify the bundle whose bytes are ``mm`` (an mmap or bytes)."""
    try:
        return _verify_parts(mm, keys, limits)
    except BundleError as e:
        return [str(e)]
    except Exception as e:  # noqa: BLE001 (untrusted bytes: never a traceback)
        return [f"zip structure: unreadable ({type(e).__name__}: {quote_name(str(e))[:200]})"]


def _verify_parts(mm, keys, limits: BundleLimits) -> list[str]:
    size = len(mm)
    seal, seal_found = _check_seal(mm, size)
    if seal is not None and not seal_found and not seal.startswith("seal:"):
        return [seal]  # truncated, or not a bundle: nothing behind it can be trusted
    problems: list[str] = []
    try:
        with zipfile.ZipFile(io.BytesIO(mm) if isinstance(mm, bytes) else mm) as z:
            infos = z.infolist()
    except Exception as e:  # noqa: BLE001 (untrusted bytes: zipfile raises many kinds)
        return [f"zip structure: central directory unreadable ({type(e).__name__}: {quote_name(str(e))[:200]})"] \
            + ([seal] if seal else [])
    names = [zi.filename for zi in infos]
    for n in names:
        bad = check_member_name(n, limits.max_name_length)
        if bad:
            problems.append(f"member {quote_name(n)}: {bad}")
    if problems:  # names that could escape a directory or hide: nothing else matters
        return problems + ([seal] if seal else [])
    dupes = sorted({n for n in names if names.count(n) > 1}) if len(set(names)) != len(names) else []
    for n in dupes:
        problems.append(f"member {n}: appears more than once")
    by_name = {zi.filename: zi for zi in infos}
    manifest = manifest_data = None
    if MANIFEST not in by_name:
        problems.append(f"{MANIFEST}: missing")
    else:
        data, bad = _member_data(mm, by_name[MANIFEST])
        if bad:
            problems.append(f"{MANIFEST}: {bad}")
        else:
            try:
                manifest = _parse_manifest(data)
                manifest_data = data
                tail = [zi.filename for zi in infos[-2:]]
                if tail[-1] != MANIFEST and tail != [MANIFEST, SIGNATURE]:
                    problems.append(f"{MANIFEST}: not the last member (nor followed by {SIGNATURE} alone)")
            except BundleError as e:
                problems.append(str(e))
    if manifest is None:
        problems.append("members: not checked (no usable manifest)")
    else:
        listed = manifest["members"]
        bad_listed = [n for n in listed if check_member_name(n, limits.max_name_length)]
        for n in bad_listed:
            problems.append(f"{MANIFEST}: lists member {quote_name(n)}: {check_member_name(n, limits.max_name_length)}")
        specs: dict[str, tuple[int, bool] | None] = {}
        datas: dict[str, bytes] = {}
        for zi in sorted(infos, key=lambda z: member_key(z.filename)):  # zarr.json first
            name = zi.filename
            if name in (MANIFEST, SIGNATURE):
                continue
            if name not in listed:
                problems.append(f"member {name}: not listed in the manifest")
                continue
            data, bad = _member_data(mm, zi)
            if data is None:
                problems.append(f"member {name}: {bad}")
                continue
            ok_sha = hashlib.sha256(data).hexdigest() == listed[name]["sha256"]
            if not ok_sha:
                problems.append(f"member {name}: sha256 mismatch")
            elif bad:
                problems.append(f"member {name}: zip CRC field damaged (the data matches its sha256)")
            if len(data) != listed[name]["bytes"]:
                problems.append(f"member {name}: {len(data)} bytes, the manifest says {listed[name]['bytes']}")
            problems.extend(_bounds_problems(name, data, specs, datas, limits, manifest["kind"] == "delta"))
        for name in sorted(set(listed) - set(by_name), key=member_key):
            problems.append(f"member {quote_name(name)}: missing")
        if content_sha256(listed) != manifest["content_sha256"]:
            problems.append(f"{MANIFEST}: content_sha256 does not match its member list")
        if manifest["kind"] == "delta" and sorted(manifest["changed"]) != sorted(listed):
            problems.append(f"{MANIFEST}: the delta's changed list differs from its members")
    if keys is not None:
        problems.extend(_signature_problems(mm, by_name, manifest, manifest_data, keys))
    if seal is not None:
        if problems:
            problems.append(seal)
        elif seal.startswith("seal: sha256"):
            problems.append("seal: sha256 mismatch while every member checks: the zip structure (local or "
                            "central headers) or the seal itself was modified")
        else:
            problems.append(seal)
    return problems


def _bounds_problems(name: str, data: bytes, specs: dict, datas: dict, limits: BundleLimits,
                     delta: bool = False) -> list[str]:
    """:class:`BundleStore`'s bounds on one member (zarr.json members come first). A delta
    lacks the zarr.json of arrays whose metadata did not change: their chunks are checked
    in the patched bundle (apply-delta verifies it)."""
    if name.endswith("zarr.json"):
        meta, problem = metadata_problem(data, limits)
        datas[name] = meta
        return [f"member {name}: {problem}"] if problem else []
    if "/c/" not in name:
        return [f"member {name}: neither zarr metadata nor a chunk"]
    array = name.rsplit("/c/", 1)[0]
    if array not in specs:
        meta = datas.get(f"{array}/zarr.json")
        if meta is None:
            specs[array] = None
            if delta and f"{array}/zarr.json" not in datas:
                return []
            return [f"member {name}: a chunk without usable array metadata ({array}/zarr.json)"]
        try:
            specs[array] = array_chunk_spec(array, meta, limits)
        except BundleError as e:
            specs[array] = None
            return [str(e)]
    if specs[array] is None:
        return []
    problem = check_chunk(specs[array], len(data), data)
    return [f"member {name}: {problem}"] if problem else []


def _signature_problems(mm, by_name: dict, manifest: dict | None, manifest_data: bytes | None,
                        keys: Iterable[PublicKey]) -> list[str]:
    """The signature's problems for :func:`verify_bundle` with trusted ``keys``."""
    if SIGNATURE not in by_name:
        return [f"{SIGNATURE}: missing: the bundle is not signed (export it with --sign KEY)"]
    data, bad = _member_data(mm, by_name[SIGNATURE])
    if data is None or bad:
        return [f"{SIGNATURE}: {bad}"]
    try:
        signed = SignedManifest.check(data, keys)
        if manifest_data is not None:
            signed.check_manifest(manifest_data)
        if manifest is not None and manifest["kind"] == "delta":
            if signed.result is None:
                return [f"{SIGNATURE}: a signed delta must carry the signature of the bundle it makes"]
            SignedManifest.check(json.dumps(signed.result, sort_keys=True, separators=(",", ":")).encode(), keys)
    except SignatureError as e:
        return [f"{SIGNATURE}: {e}"]
    return []


# --- deltas -------------------------------------------------------------------------------


def apply_delta(base: str | Path, delta: str | Path, out: str | Path, *,
                keys: Iterable[PublicKey] | None = None, limits: BundleLimits = DEFAULT_LIMITS) -> dict:
    """Write the new bundle ``out`` = bundle ``base`` patched with ``delta``; returns its
    manifest.

    Both inputs are verified first (:func:`verify_bundle`, with ``keys`` when given: then
    both must be signed by a trusted key); the delta must have been made for this base:
    same map id, base snapshot and selection, and the base must hold exactly the member
    hashes the delta expects (``base_members``, ``removed``). The result is what a full
    export of the delta's version with the same selection gives, byte for byte; a signed
    delta carries the map owner's signature of that result, which ``out`` gets as its
    ``manifest.sig``. ``out`` is verified after writing (with ``keys`` when given) and
    removed when it does not verify. Raises BundleError naming the file and the mismatch.
    """
    base, delta, out = Path(base), Path(delta), Path(out)
    keys = None if keys is None else tuple(keys)
    for p in (base, delta):
        problems = verify_bundle(p, keys=keys, limits=limits)
        if problems:
            more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
            raise BundleError(str(p), problems[0] + more)
    bm, dm = read_manifest(base), read_manifest(delta)
    if bm["kind"] != "full":
        raise BundleError(str(base), f"is a {bm['kind']} bundle; apply a delta to a full bundle")
    if dm["kind"] != "delta":
        raise BundleError(str(delta), f"is a {dm['kind']} bundle, not a delta")
    _check_base(base, bm, delta, dm)
    result_sig = _result_signature(delta)
    changed = set(dm["changed"])
    result = {n: m for n, m in bm["members"].items() if n not in changed and n not in dm["removed"]}
    result.update({n: dm["members"][n] for n in changed})
    sign = None if result_sig is None else (lambda _manifest: result_sig)
    with zipfile.ZipFile(base) as zb, zipfile.ZipFile(delta) as zd, BundleWriter(out, sign=sign) as w:
        for name in sorted(result, key=member_key):
            w.add(name, (zd if name in changed else zb).read(name))
        manifest = w.finish(dm["result"])
    problems = verify_bundle(out, keys=keys, limits=limits)
    if not problems and result_sig is not None and keys is None:
        problems = _self_signed_problems(out)
    if problems:
        out.unlink(missing_ok=True)
        raise BundleError(str(out), f"the patched bundle does not verify: {problems[0]}")
    if manifest["members"] != result:
        out.unlink(missing_ok=True)
        raise BundleError(str(out), "the patched bundle's members differ from the delta's expectation")
    return manifest


def _result_signature(delta: Path) -> bytes | None:
    """The signature document of the patched bundle a signed delta carries (None: unsigned)."""
    index = ZipIndex(delta)
    try:
        doc = index._raw(SIGNATURE)
    finally:
        index.close()
    if doc is None:
        return None
    try:
        result = json.loads(doc).get("signed", {}).get("result")
    except (ValueError, AttributeError):
        raise BundleError(str(delta), f"{SIGNATURE}: damaged") from None
    if not isinstance(result, dict):
        raise BundleError(str(delta), f"{SIGNATURE}: a signed delta must carry the signature of the bundle it makes")
    return json.dumps(result, sort_keys=True, separators=(",", ":")).encode()


def _self_signed_problems(path: Path) -> list[str]:
    """Without trusted keys: whether the patched bundle's signature document signs its
    manifest bytes (a delta signed for another result would make it fail with keys)."""
    index = ZipIndex(path)
    try:
        doc, manifest = index._raw(SIGNATURE), index._raw(MANIFEST)
    finally:
        index.close()
    signed = json.loads(doc)["signed"]
    if signed.get("manifest_sha256") != hashlib.sha256(manifest).hexdigest():
        return [f"{SIGNATURE}: the delta's signature of its result does not match the patched manifest"]
    return []


def _check_base(base: Path, bm: dict, delta: Path, dm: dict) -> None:
    b = dm["base"]
    if bm["map_id"] != dm["map_id"]:
        raise BundleError(str(delta), f"is for map {dm['map_id']}, the base bundle {base} holds map {bm['map_id']}")
    if bm["version"]["snapshot"] != b["snapshot"]:
        raise BundleError(str(delta), f"base version mismatch: the delta applies to snapshot {b['snapshot']} "
                                      f"(version {b.get('number')}), {base} holds snapshot "
                                      f"{bm['version']['snapshot']} (version {bm['version'].get('number')})")
    if bm["selection"] != dm["result"]["selection"]:
        raise BundleError(str(delta), f"selection mismatch: the delta is for {_describe(dm['result']['selection'])}, "
                                      f"{base} holds {_describe(bm['selection'])}")
    for name, sha in sorted(dm["base_members"].items()):
        have = bm["members"].get(name, {}).get("sha256")
        if have != sha:
            raise BundleError(str(delta), f"base member {name}: the delta expects "
                                          f"{'none' if sha is None else sha[:12]}, {base} holds "
                                          f"{'none' if have is None else have[:12]}")
    for name, sha in sorted(dm["removed"].items()):
        if bm["members"].get(name, {}).get("sha256") != sha:
            raise BundleError(str(delta), f"removed member {name}: not in {base} as the delta expects")


def _describe(sel: dict) -> str:
    kind = sel.get("kind")
    where = {"region": f"region {sel.get('region_m')}", "corridor": f"a corridor of {sel.get('width_m')} m"}.get(
        kind, "the whole map")
    return f"{where}, levels {sel.get('levels')}, layers {sel.get('layers')}"
