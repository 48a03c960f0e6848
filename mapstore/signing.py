"""Ed25519 signatures of vehicle bundles: who may publish a map a vehicle trusts.

The map owner holds a private key (:func:`new_key_pair`, ``mosaicmap keys new``); vehicles
hold its public key. A signed bundle carries a member ``manifest.sig`` (after
``manifest.json``): a small JSON document whose ``signed`` part is signed with Ed25519
(RFC 8032, through the ``cryptography`` package) and which binds

- ``manifest_sha256``: the SHA-256 of the manifest's bytes, which hold every other member's
  SHA-256 and size (``mosaicmap verify --key`` checks everything through it);
- ``pages``: the manifest's ``members`` object cut into pages of :data:`PAGE_MEMBERS`
  consecutive entries: each page's first member name, byte range of ``manifest.json`` and
  SHA-256 (``{"first": [...], "ranges": "<hex>"}``). A vehicle checks the signature at open (a few kB, well
  under a millisecond) and, when it first reads a member, the page listing it (a few kB)
  against the signed page hash and then the member's bytes against the page's SHA-256: no
  full read of a large bundle, no 1.5 MB manifest parsed at start-up;
- ``metadata``: the SHA-256 and size of every ``zarr.json`` member (a few dozen), which the
  vehicle reads at open, so that opening needs no page at all.

A signed delta's document adds ``result``: the signature document of the bundle that
``apply-delta`` writes (the exporter computes that bundle's manifest), so the patched
bundle is signed by the map owner too; the vehicle never signs.

The signed message is ``DOMAIN + canonical JSON of signed`` (sorted keys, no spaces).
Standard library + ``cryptography`` only: the tracker imports this module.
"""

from __future__ import annotations

import base64
import binascii
import bisect
import hashlib
import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

__all__ = [
    "SIGNATURE",
    "DOMAIN",
    "PAGE_MEMBERS",
    "PUBLIC_PREFIX",
    "SignatureError",
    "PublicKey",
    "new_key_pair",
    "write_key_pair",
    "load_private_key",
    "load_public_key",
    "load_public_keys",
    "signature_document",
    "SignedManifest",
]

SIGNATURE = "manifest.sig"
DOMAIN = b"mosaicmap-bundle-signature-v1\0"
SIG_FORMAT = "mosaicmap-signature"
SIG_FORMAT_VERSION = 1
PAGE_MEMBERS = 256  # manifest entries per signed page (~28 kB of manifest text)
_RANGE_LEN = 80  # hex digits per page in pages.ranges: start (8), end (8), sha256 (64)
PUBLIC_PREFIX = "mosaicmap-ed25519"
PARSE_AFTER = 16  # lookups in one page after which the page is parsed whole
MAX_SIGNATURE_BYTES = 1 << 22  # the signature document (a 40 x 40 m bundle's: ~6 kB)
_HEX64 = re.compile(r"^[0-9a-f]{64}$")


class SignatureError(ValueError):
    """A key or signature that cannot be used; the message says why (one line)."""


# --- keys ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class PublicKey:
    """A trusted Ed25519 public key: ``raw`` 32 bytes, ``key_id`` (16 hex digits of its
    SHA-256, what a signature names), ``source`` (where it was read, for messages)."""

    raw: bytes
    source: str = ""
    key: Ed25519PublicKey = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "key", Ed25519PublicKey.from_public_bytes(self.raw))

    @property
    def key_id(self) -> str:
        return key_id(self.raw)

    def text(self) -> str:
        """The one-line public key file text: ``mosaicmap-ed25519 <base64>``."""
        return f"{PUBLIC_PREFIX} {base64.b64encode(self.raw).decode()}"


def key_id(raw: bytes) -> str:
    return hashlib.sha256(raw).hexdigest()[:16]


def new_key_pair() -> tuple[bytes, PublicKey]:
    """A fresh key pair: (private key PEM (PKCS#8, unencrypted), public key)."""
    priv = Ed25519PrivateKey.generate()
    pem = priv.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())
    raw = priv.public_key().public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)
    return pem, PublicKey(raw, "new")


def write_key_pair(out: str | Path) -> tuple[Path, Path, PublicKey]:
    """Write a new key pair: the private key at ``out`` (mode 0600) and the public key at
    ``out.pub``. Refuses (FileExistsError) to overwrite either."""
    out = Path(out)
    pub_path = out.with_name(out.name + ".pub")
    for p in (out, pub_path):
        if p.exists() or p.is_symlink():
            raise FileExistsError(str(p))
    pem, pub = new_key_pair()
    out.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(out, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        os.write(fd, pem)
        os.fsync(fd)
    finally:
        os.close(fd)
    os.chmod(out, 0o600)
    with open(pub_path, "x", encoding="ascii") as f:
        f.write(pub.text() + "\n")
    return out, pub_path, pub


def load_private_key(path: str | Path) -> Ed25519PrivateKey:
    """The Ed25519 private key in the PEM file ``path``. SignatureError when it is not one."""
    try:
        data = Path(path).read_bytes()
    except OSError as e:
        raise SignatureError(f"{path}: cannot read the private key ({e.strerror})") from None
    try:
        key = serialization.load_pem_private_key(data, password=None)
    except (ValueError, TypeError) as e:
        raise SignatureError(f"{path}: not an unencrypted PEM private key ({e})") from None
    if not isinstance(key, Ed25519PrivateKey):
        raise SignatureError(f"{path}: not an Ed25519 private key")
    return key


def parse_public_key(text: str, source: str) -> PublicKey:
    """A public key from its text: ``mosaicmap-ed25519 <base64>`` or a PEM public key."""
    text = text.strip()
    if text.startswith(PUBLIC_PREFIX):
        parts = text.split()
        try:
            raw = base64.b64decode(parts[1], validate=True) if len(parts) >= 2 else b""
        except (binascii.Error, ValueError):
            raw = b""
        if len(raw) != 32:
            raise SignatureError(f"{source}: damaged public key (expected '{PUBLIC_PREFIX} <base64 of 32 bytes>')")
        return PublicKey(raw, source)
    if text.startswith("-----BEGIN PUBLIC KEY-----"):
        try:
            key = serialization.load_pem_public_key(text.encode())
        except ValueError as e:
            raise SignatureError(f"{source}: not a PEM public key ({e})") from None
        if not isinstance(key, Ed25519PublicKey):
            raise SignatureError(f"{source}: not an Ed25519 public key")
        return PublicKey(key.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw), source)
    raise SignatureError(f"{source}: not a public key (expected '{PUBLIC_PREFIX} <base64>' or a PEM public key)")


def load_public_key(path_or_text: str | Path) -> PublicKey:
    """A public key from a file (``KEY.pub``) or inline text (``mosaicmap-ed25519 ...``)."""
    s = str(path_or_text)
    if s.startswith(PUBLIC_PREFIX) or s.startswith("-----BEGIN"):
        return parse_public_key(s, "trusted key " + s[:30] + "...")
    try:
        data = Path(s).read_bytes()
    except OSError as e:
        raise SignatureError(f"{s}: cannot read the public key ({e.strerror})") from None
    if len(data) > 1 << 16:
        raise SignatureError(f"{s}: not a public key ({len(data)} bytes)")
    try:
        text = data.decode("ascii")
    except UnicodeDecodeError:
        raise SignatureError(f"{s}: not a public key (not ASCII text)") from None
    return parse_public_key(text, s)


def load_public_keys(items: Iterable[str | Path]) -> tuple[PublicKey, ...]:
    """Public keys from files or inline texts (see :func:`load_public_key`)."""
    return tuple(load_public_key(i) for i in items)


# --- signing ------------------------------------------------------------------------------


def canonical(obj) -> bytes:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()


def _member_pages(manifest: bytes, members: dict, per_page: int) -> dict:
    """The signed pages of the manifest's ``members`` object: ``first`` (each page's first
    member name) and ``ranges``, one hex string holding per page ``start`` and ``end``
    (8 hex digits each: ``manifest[start:end]`` = the page's entries joined by commas) and
    its SHA-256 (64 hex digits). Plain strings and a flat list parse fast at open."""
    names = sorted(members)
    at = manifest.find(b'"members":{')
    if at < 0:
        raise SignatureError("manifest: no members object")
    pos = at + len(b'"members":{')
    firsts, ranges = [], []
    for i in range(0, len(names), per_page):
        chunk = names[i:i + per_page]
        text = b",".join(canonical(n) + b":" + canonical(members[n]) for n in chunk)
        if manifest[pos:pos + len(text)] != text:
            raise SignatureError("manifest: not in canonical form (members are not where expected)")
        firsts.append(chunk[0])
        ranges.append(f"{pos:08x}{pos + len(text):08x}{hashlib.sha256(text).hexdigest()}")
        pos += len(text) + 1
    return {"first": firsts, "ranges": "".join(ranges)}


def signature_document(manifest: bytes, key: Ed25519PrivateKey, *, result: bytes | None = None,
                       per_page: int = PAGE_MEMBERS) -> bytes:
    """The ``manifest.sig`` member of the bundle whose manifest bytes are ``manifest``,
    signed with ``key``. ``result``: for a delta, the signature document of the bundle
    apply-delta writes (embedded, and so signed too)."""
    m = json.loads(manifest)
    raw = key.public_key().public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)
    signed = {"format": SIG_FORMAT, "format_version": SIG_FORMAT_VERSION, "algorithm": "ed25519",
              "key_id": key_id(raw), "manifest_sha256": hashlib.sha256(manifest).hexdigest(),
              "manifest_bytes": len(manifest), "pages": _member_pages(manifest, m["members"], per_page),
              "metadata": {n: [e["sha256"], e["bytes"]] for n, e in m["members"].items() if n.endswith("zarr.json")}}
    if result is not None:
        signed["result"] = json.loads(result)
    sig = key.sign(DOMAIN + canonical(signed))
    return canonical({"signed": signed, "signature": base64.b64encode(sig).decode()})


# --- checking -----------------------------------------------------------------------------


@dataclass
class SignedManifest:
    """A checked signature document: the trusted pages of one bundle's manifest.

    :meth:`check` verifies the document against the trusted keys (cheap: a few kB);
    :meth:`lookup` gives a member's signed ``(sha256 hex, bytes)`` reading only its page
    of the manifest (through ``read_manifest_range(start, end)``), checked against the
    page's signed SHA-256."""

    signed: dict
    key: PublicKey
    _firsts: list[str] = field(default_factory=list, repr=False)
    _ranges: str = field(default="", repr=False)
    _hits: dict[int, int] = field(default_factory=dict, repr=False)
    _parsed: dict[int, dict] = field(default_factory=dict, repr=False)
    _pages: dict[int, bytes] = field(default_factory=dict, repr=False)

    @classmethod
    def check(cls, document: bytes, keys: Iterable[PublicKey]) -> "SignedManifest":
        """The document checked against ``keys``; SignatureError (one line) when it is
        damaged, signed by none of them, or forged.

        The signature is checked over the ``signed`` object's bytes as stored (the
        document is canonical JSON, ``{"signature":...,"signed":{...}}``), and exactly
        those bytes are parsed: nothing is re-serialized at open."""
        keys = tuple(keys)
        if not keys:
            raise SignatureError("no trusted key to check the signature with")
        if len(document) > MAX_SIGNATURE_BYTES:
            raise SignatureError(f"signature document of {len(document)} bytes (at most {MAX_SIGNATURE_BYTES})")
        cut = document.find(b'","signed":{')
        if not document.startswith(b'{"signature":"') or cut < 0 or not document.endswith(b"}"):
            raise SignatureError("damaged: expected {signature, signed}")
        signed_raw = document[cut + 11:-1]
        try:
            sig = base64.b64decode(document[14:cut], validate=True)
        except (binascii.Error, ValueError):
            raise SignatureError("damaged: the signature is not base64") from None
        try:
            signed = json.loads(signed_raw)
        except (ValueError, UnicodeDecodeError) as e:
            raise SignatureError(f"damaged: not JSON ({str(e)[:80]})") from None
        if not isinstance(signed, dict):
            raise SignatureError("damaged: expected {signature, signed}")
        if signed.get("format") != SIG_FORMAT or signed.get("format_version") != SIG_FORMAT_VERSION \
                or signed.get("algorithm") != "ed25519":
            raise SignatureError(f"unknown signature format {str(signed.get('format'))[:40]!r} "
                                 f"version {str(signed.get('format_version'))[:10]!r}")
        kid = signed.get("key_id")
        match = [k for k in keys if k.key_id == kid]
        if not match:
            raise SignatureError(f"signed by key {str(kid)[:16]!r}, which is not a trusted key "
                                 f"(trusted: {', '.join(k.key_id for k in keys)})")
        try:
            match[0].key.verify(sig, DOMAIN + signed_raw)
        except InvalidSignature:
            raise SignatureError(f"signature does not verify with trusted key {kid}: forged or damaged") from None
        except (ValueError, TypeError) as e:
            raise SignatureError(f"damaged signature document ({e})") from None
        out = cls(signed, match[0])
        out._validate()
        return out

    def _validate(self) -> None:
        """Cheap shape checks of the signed document (its pages are checked when used)."""
        s = self.signed
        pages, meta = s.get("pages"), s.get("metadata", {})
        if not (isinstance(s.get("manifest_sha256"), str) and _HEX64.match(s["manifest_sha256"])
                and isinstance(s.get("manifest_bytes"), int) and isinstance(pages, dict) and isinstance(meta, dict)):
            raise SignatureError("signed document lacks manifest_sha256, manifest_bytes or pages")
        firsts, ranges = pages.get("first"), pages.get("ranges")
        if not (isinstance(firsts, list) and isinstance(ranges, str) and len(ranges) == _RANGE_LEN * len(firsts)
                and all(isinstance(f, str) for f in firsts)):
            raise SignatureError("signed document holds malformed pages")
        self._firsts, self._ranges = firsts, ranges

    @property
    def manifest_sha256(self) -> str:
        return self.signed["manifest_sha256"]

    @property
    def result(self) -> dict | None:
        """A delta's embedded signature document of the patched bundle (or None)."""
        return self.signed.get("result")

    def check_manifest(self, manifest: bytes) -> None:
        """SignatureError unless ``manifest`` is the signed manifest's bytes."""
        if len(manifest) != self.signed["manifest_bytes"] or hashlib.sha256(manifest).hexdigest() != self.manifest_sha256:
            raise SignatureError("manifest.json is not the signed manifest (changed after signing: forged or damaged)")

    def lookup(self, name: str, read_manifest_range: Callable[[int, int], bytes]) -> tuple[str, int] | None:
        """(sha256 hex, bytes) the signed manifest lists for member ``name``, or None when it
        does not list it. SignatureError when the page read does not match its signed hash."""
        meta = self.signed.get("metadata", {}).get(name)
        if meta is not None:
            if not (isinstance(meta, list) and len(meta) == 2 and isinstance(meta[0], str) and _HEX64.match(meta[0])
                    and isinstance(meta[1], int)):
                raise SignatureError(f"signed document holds a malformed entry for {name!r}")
            return meta[0], meta[1]
        i = bisect.bisect_right(self._firsts, name) - 1
        if i < 0:
            return None
        text = self._pages.get(i)
        if text is None:
            r = self._ranges[i * _RANGE_LEN:(i + 1) * _RANGE_LEN]
            try:
                start, end, sha = int(r[:8], 16), int(r[8:16], 16), r[16:]
            except ValueError:
                raise SignatureError(f"signed document holds a malformed page {i}") from None
            if not (0 <= start <= end <= self.signed["manifest_bytes"] and _HEX64.match(sha)):
                raise SignatureError(f"signed document holds a malformed page {i}")
            text = read_manifest_range(start, end)
            if hashlib.sha256(text).hexdigest() != sha:
                raise SignatureError(f"manifest.json: members page {i} does not match its signed hash: forged or damaged")
            self._pages[i] = text
        parsed = self._parsed.get(i)
        if parsed is None:
            hits = self._hits[i] = self._hits.get(i, 0) + 1
            if hits > PARSE_AFTER:  # many reads in this page (e.g. the index at start-up): parse it once
                parsed = self._parse_page(i, text)
        if parsed is not None:
            entry = parsed.get(name)
            if entry is None:
                return None
            if not (isinstance(entry, dict) and isinstance(entry.get("sha256"), str)
                    and isinstance(entry.get("bytes"), int)):
                raise SignatureError(f"manifest.json: members page {i} unreadable")
            return entry["sha256"], entry["bytes"]
        key = canonical(name) + b":{"
        at = text.find(key)
        if at < 0 or (at > 0 and text[at - 1:at] != b","):
            return None
        try:
            entry = _raw_entry(text, at + len(key) - 1)
        except ValueError:
            raise SignatureError(f"manifest.json: members page {i} unreadable") from None
        return entry["sha256"], entry["bytes"]


    def _parse_page(self, i: int, text: bytes) -> dict:
        """Page ``i``'s text (already checked against its signed hash), parsed and kept."""
        try:
            parsed = self._parsed[i] = json.loads(b"{" + text + b"}")
        except ValueError:
            raise SignatureError(f"manifest.json: members page {i} unreadable") from None
        return parsed

    def lookup_many(self, names: Iterable[str],
                    read_manifest_range: Callable[[int, int], bytes]) -> dict[str, tuple[str, int] | None]:
        """:meth:`lookup` of many names at once (e.g. every chunk of an array a reader is
        about to read): each page they fall in is read, checked against its signed hash and
        parsed once, then every name is a dictionary lookup."""
        out: dict[str, tuple[str, int] | None] = {}
        meta = self.signed.get("metadata", {})
        for name in names:
            i = bisect.bisect_right(self._firsts, name) - 1
            if name in meta or i < 0:
                out[name] = self.lookup(name, read_manifest_range)
                continue
            if i not in self._parsed:
                self.lookup(self._firsts[i], read_manifest_range)  # reads and checks the page
                self._parse_page(i, self._pages[i])
            entry = self._parsed[i].get(name)
            if entry is not None and not (isinstance(entry, dict) and isinstance(entry.get("sha256"), str)
                                          and isinstance(entry.get("bytes"), int)):
                raise SignatureError(f"manifest.json: members page {i} unreadable")
            out[name] = None if entry is None else (entry["sha256"], entry["bytes"])
        return out


def _raw_entry(text: bytes, at: int) -> dict:
    """The JSON object starting at byte ``at`` of ``text`` (an entry {bytes, sha256})."""
    obj = json.loads(text[at:text.index(b"}", at) + 1])
    if not (isinstance(obj, dict) and isinstance(obj.get("sha256"), str) and isinstance(obj.get("bytes"), int)):
        raise ValueError("not a member entry")
    return obj
