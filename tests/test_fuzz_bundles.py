"""Property-based fuzzing of bundles (hypothesis, derandomized, bounded budget): mutated and
forged bundles and deltas through verify, apply-delta and the tracker's open + read path.

Outcome classes asserted for every mutation: a clean refusal (a BundleError, or for the
CLI exit 2, with a one-line message without raw control characters) or acceptance of
content identical to the original; never another exception (a traceback), never a forged
or damaged member used. The budget (examples per mutation kind) is ``FUZZ_BUNDLES_SCALE``
times the CI budget (1 by default: >= 500 bundle mutations in all); bench/fuzz_bundles.py
runs this file with a larger scale."""

from __future__ import annotations

import hashlib
import json
import os
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bundle_forge import forge, invoke, make_site, move_origin, read_members, write_sealed, zstd_bomb
from conftest import write_small_log
from mapstore.bundle import MANIFEST, SIGNATURE, BundleError, apply_delta, verify_bundle, verify_bytes
from mapstore.signing import load_public_key
from tracker.bundle_map import open_bundle as tracker_open

SCALE = max(1, int(os.environ.get("FUZZ_BUNDLES_SCALE", "1")))
COUNTS: dict[str, int] = {}


BUDGET: list[int] = []


def _settings(n: int):
    BUDGET.append(n * SCALE)
    return settings(max_examples=n * SCALE, derandomize=True, deadline=None, database=None,
                    suppress_health_check=list(HealthCheck))


class Site(dict):
    def __repr__(self) -> str:  # hypothesis prints the fixture with a failing example
        return f"Site({self.get('root')})"


@pytest.fixture(scope="module")
def fz(tmp_path_factory):
    root = tmp_path_factory.mktemp("fuzz")
    site = make_site(root)
    keys = [load_public_key(site["pub"])]
    good = _contents(site["signed"], keys)
    patched = root / "patched.zip"
    apply_delta(site["signed"], site["delta"], patched, keys=keys)
    site.update({"keys": keys, "good": good, "bytes": site["signed"].read_bytes(),
                 "members": read_members(site["signed"]), "delta_bytes": site["delta"].read_bytes(),
                 "delta_members": read_members(site["delta"]), "patched_sha": _content_sha(patched),
                 "work": root / "work", "log": write_small_log(root / "log")})
    site["work"].mkdir()
    return Site(site)


def _content_sha(path: Path) -> str:
    with zipfile.ZipFile(path) as z:
        return json.loads(z.read(MANIFEST))["content_sha256"]


def _contents(path: Path, keys) -> dict:
    """What the tracker reads from a bundle: every level-0 tile, the stored index, the grid."""
    with tracker_open(path, keys=keys) as tm:
        b = tm.bundle
        rows, cols = b.tiles_shape(0)
        held = [b.has_tile(0, r, c) for r in range(rows) for c in range(cols)]
        tiles = {"level0": b.read(0), "held": held}  # every level-0 tile, in one read
        idx = tm.stored_index()
        return {"grid": b.grid.to_attrs(), "tiles": tiles,
                "index": None if idx is None else hashlib.sha256(np.ascontiguousarray(idx.descriptors)).hexdigest(),
                "manifest": hashlib.sha256(json.dumps(b.manifest, sort_keys=True).encode()).hexdigest()}


def _clean(msg: str) -> None:
    assert msg and "\n" not in msg and not any(ord(ch) < 32 or ord(ch) == 127 for ch in msg), repr(msg)


def _same(a: dict, b: dict) -> bool:
    if a["grid"] != b["grid"] or a["index"] != b["index"] or a["manifest"] != b["manifest"]:
        return False
    return a["tiles"]["held"] == b["tiles"]["held"] and np.array_equal(a["tiles"]["level0"], b["tiles"]["level0"])


def _through_everything(fz, path: Path, kind: str, *, tracker: bool = True) -> None:
    """verify (with and without the key) and the tracker (trusted, then insecure): refused
    cleanly, or the original content."""
    COUNTS[kind] = COUNTS.get(kind, 0) + 1
    problems = verify_bundle(path, keys=fz["keys"])
    for p in problems:
        _clean(p)
    for p in verify_bundle(path):
        _clean(p)
    if not tracker:
        return
    try:
        got = _contents(path, fz["keys"])
    except BundleError as e:
        _clean(str(e))
    else:
        assert _same(got, fz["good"]), f"{kind}: the tracker used changed content"
        assert problems == [] or all(p.startswith(("seal", "zip structure", "member ")) for p in problems), problems
    try:  # insecure: bounds only; damaged content may read, but never a traceback or a blow-up
        _contents(path, ())
    except BundleError as e:
        _clean(str(e))
    except ValueError as e:  # no level-0 intensity: a clean refusal of its own
        _clean(str(e))


def _write(fz, data: bytes, name: str = "m.zip") -> Path:
    p = fz["work"] / name
    p.write_bytes(data)
    return p


def _forge(fz, edit, *, keep_signature: bool, manifest_edit=None, src: str = "signed") -> Path:
    out = fz["work"] / "forged.zip"
    forge(fz[src], out, edit, keep_signature=keep_signature, manifest_edit=manifest_edit)
    return out


# --- raw byte damage ------------------------------------------------------------------------


@_settings(140)
@given(pos=st.floats(0, 1, exclude_max=True), xor=st.integers(1, 255))
def test_byte_flips(fz, pos, xor):
    data = bytearray(fz["bytes"])
    data[int(pos * len(data))] ^= xor
    path = _write(fz, bytes(data))
    assert verify_bundle(path, keys=fz["keys"]) != []  # the seal sees any flip
    _through_everything(fz, path, "flip")


@_settings(40)
@given(keep=st.floats(0, 1, exclude_max=True))
def test_truncations(fz, keep):
    path = _write(fz, fz["bytes"][:int(keep * len(fz["bytes"]))])
    assert verify_bundle(path) != []
    _through_everything(fz, path, "truncation")


# --- forgeries: every hash and the seal recomputed, no private key --------------------------


def _data_names(fz) -> list[str]:
    return [n for n, _ in fz["members"] if n not in (MANIFEST, SIGNATURE)]


@_settings(70)
@given(which=st.integers(0, 10_000), at=st.floats(0, 1, exclude_max=True), xor=st.integers(1, 255),
       keep=st.booleans())
def test_forged_member_changes(fz, which, at, xor, keep):
    names = _data_names(fz)
    name = names[which % len(names)]

    def edit(m):
        b = bytearray(m[name])
        b[int(at * len(b))] ^= xor
        return {**m, name: bytes(b)}

    path = _forge(fz, edit, keep_signature=keep)
    if keep:
        assert verify_bundle(path, keys=fz["keys"]) != []
    _through_everything(fz, path, "forged member")


@_settings(50)
@given(i=st.integers(0, 10_000), j=st.integers(0, 10_000))
def test_member_swaps(fz, i, j):
    names = _data_names(fz)
    a, b = names[i % len(names)], names[j % len(names)]
    path = _forge(fz, lambda m: {**m, a: m[b], b: m[a]}, keep_signature=True)
    if fz["members"] and dict(fz["members"])[a] != dict(fz["members"])[b]:
        assert verify_bundle(path, keys=fz["keys"]) != []
    _through_everything(fz, path, "swap")


@_settings(20)
@given(dx=st.sampled_from([0.5, -0.5, 0.0025, 100.0, 1e300]), keep=st.booleans())
def test_forged_origin(fz, dx, keep):
    path = _forge(fz, lambda m: move_origin(m, dx), keep_signature=keep)
    assert verify_bundle(path, keys=fz["keys"]) != []
    _through_everything(fz, path, "origin")


NAMES = st.one_of(
    st.sampled_from(["../../evil", "/etc/passwd", "floor/../x", "C:\\x", "C:x", "a\\b", "floor//0", "./x", "",
                     "floor/0/c/\x00/0", "floor/\x1b[2J", "x" * 300, "floor/0/c/0/0\n", "manifest.json",
                     "manifest.sig", "zarr.json/..", "\u202eevil"]),
    st.text(min_size=1, max_size=40))


@_settings(60)
@given(which=st.integers(0, 10_000), new=NAMES, keep=st.booleans())
def test_member_name_changes(fz, which, new, keep):
    names = _data_names(fz)
    name = names[which % len(names)]

    def edit(m):
        out = dict(m)
        out[new] = out.pop(name)
        return out

    try:
        path = _forge(fz, edit, keep_signature=keep)
    except (ValueError, UnicodeEncodeError):  # zipfile itself refuses to write it (NUL, surrogates)
        return
    _through_everything(fz, path, "name")


def _meta_edits():
    values = st.one_of(st.integers(-5, 1 << 40), st.text(max_size=8), st.none(), st.booleans(),
                       st.lists(st.integers(-2, 1 << 33), max_size=4), st.floats(allow_nan=True))
    return st.tuples(st.sampled_from(["chunk_shape", "data_type", "codecs", "shape", "fill_value", "zarr_format",
                                      "node_type", "attributes", "raw", "utf8", "big"]), values)


@_settings(60)
@given(which=st.integers(0, 10_000), edit=_meta_edits(), keep=st.booleans())
def test_metadata_edits(fz, which, edit, keep):
    metas = [n for n in _data_names(fz) if n.endswith("zarr.json")]
    name = metas[which % len(metas)]
    what, value = edit

    def change(m):
        if what == "raw":
            return {**m, name: json.dumps(value).encode()}
        if what == "utf8":
            return {**m, name: m[name][:-1] + b"\xc3\x28}"}
        if what == "big":
            return {**m, name: m[name] + b" " * (1 << 20)}
        meta = json.loads(m[name])
        if what == "chunk_shape" and "chunk_grid" in meta:
            meta["chunk_grid"]["configuration"]["chunk_shape"] = value
        elif what == "codecs":
            meta["codecs"] = value if value is not None else [{"name": "zstd", "configuration": {"level": 0}}]
        else:
            meta[what] = value
        return {**m, name: json.dumps(meta, allow_nan=True).encode()}

    path = _forge(fz, change, keep_signature=keep)
    _through_everything(fz, path, "metadata")


@_settings(40)
@given(which=st.integers(0, 10_000), decoded=st.sampled_from([1 << 30, 1 << 24, 4096, 64 * 64, 64 * 64 + 1]),
       declared=st.sampled_from([-1, None, 0, 64 * 64, 1 << 40]), keep=st.booleans())
def test_chunk_bombs(fz, which, decoded, declared, keep):
    chunks = [n for n in _data_names(fz) if "/c/" in n]
    name = chunks[which % len(chunks)]
    bomb = zstd_bomb(decoded, declared)
    path = _forge(fz, lambda m: {**m, name: bomb}, keep_signature=keep)
    _through_everything(fz, path, "bomb")


# --- deltas through apply-delta -------------------------------------------------------------


@_settings(50)
@given(kind=st.sampled_from(["flip", "forge", "name", "bomb", "truncate"]), at=st.floats(0, 1, exclude_max=True),
       which=st.integers(0, 10_000), new=NAMES)
def test_delta_mutations_through_apply_delta(fz, kind, at, which, new):
    COUNTS["delta"] = COUNTS.get("delta", 0) + 1
    names = [n for n, _ in fz["delta_members"] if n not in (MANIFEST, SIGNATURE)]
    name = names[which % len(names)]
    delta = fz["work"] / "delta.zip"
    try:
        if kind == "flip":
            data = bytearray(fz["delta_bytes"])
            data[int(at * len(data))] ^= 0x5A
            delta.write_bytes(bytes(data))
        elif kind == "truncate":
            delta.write_bytes(fz["delta_bytes"][:int(at * len(fz["delta_bytes"]))])
        elif kind == "forge":
            forge(fz["delta"], delta, lambda m: {**m, name: m[name][::-1]})
        elif kind == "name":
            forge(fz["delta"], delta, lambda m: {**{k: v for k, v in m.items() if k != name}, new: m[name]})
        else:
            forge(fz["delta"], delta, lambda m: {**m, name: zstd_bomb(1 << 30)})
    except (ValueError, UnicodeEncodeError):
        return
    out = fz["work"] / "out" / "patched.zip"
    for keys in (fz["keys"], None):
        try:
            apply_delta(fz["signed"], delta, out, keys=keys)
        except BundleError as e:
            _clean(str(e))
            assert not out.exists()
        else:
            assert _content_sha(out) == fz["patched_sha"], "apply-delta accepted a changed delta"
            out.unlink()
    assert sorted(p.name for p in fz["work"].rglob("*") if p.is_file()) <= sorted(["delta.zip", "m.zip", "forged.zip"])


# --- a few through the command line ----------------------------------------------------------


@_settings(12)
@given(kind=st.sampled_from(["flip", "forge", "origin", "name", "utf8", "bomb"]), at=st.floats(0, 1, exclude_max=True))
def test_cli_refuses_in_one_line(fz, kind, at):
    COUNTS["cli"] = COUNTS.get("cli", 0) + 1
    chunk = next(n for n in _data_names(fz) if "/c/" in n)
    if kind == "flip":
        data = bytearray(fz["bytes"])
        data[int(at * len(data))] ^= 0xFF
        path = _write(fz, bytes(data))
    elif kind == "forge":
        path = _forge(fz, lambda m: {**m, chunk: m[chunk][::-1]}, keep_signature=True)
    elif kind == "origin":
        path = _forge(fz, move_origin, keep_signature=True)
    elif kind == "name":
        path = _forge(fz, lambda m: {**m, "../../evil\x1b[31m": b"x"}, keep_signature=True)
    elif kind == "utf8":
        path = _forge(fz, lambda m: {**m, "floor/zarr.json": b"\xff\xfe{}"}, keep_signature=True)
    else:
        path = _forge(fz, lambda m: {**m, chunk: zstd_bomb(1 << 30)}, keep_signature=True)
    for args in (("verify", path, "--key", fz["pub"]),
                 ("track", path, fz["log"], "--key", fz["pub"], "--start", "0.5,0.5,0", "--quiet"),
                 ("apply-delta", path, fz["delta"], fz["work"] / "out.zip", "--key", fz["pub"])):
        r = invoke(*args)
        text = r.output.strip()
        if kind == "flip" and args[0] == "track" and r.exit_code == 0:
            continue  # the flip hit no member the tracker read (it reads on demand; each read is checked)
        assert r.exit_code == 2, (kind, args[0], r.output)
        assert "Traceback" not in text and len(text.splitlines()) == 1, text
        _clean(text)
        assert str(path) in text or "out.zip" in text


def test_budget_reached():
    """The CI budget: >= 500 bundle mutations configured; run in one process with the
    other tests (not split by xdist), >= 500 actually run (this test runs last)."""
    assert sum(BUDGET) >= 500, BUDGET
    if len(COUNTS) >= 10:
        assert sum(COUNTS.values()) >= 500, COUNTS
