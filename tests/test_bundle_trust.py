"""Signed bundles and bounded reading (mapstore.signing, mapstore.bundle, tracker.bundle_map,
`mosaicmap keys / export --sign / verify --key / apply-delta --key / track --key`): a forged
bundle (every hash and the seal recomputed, no private key) is refused by verify and the
tracker; damaged metadata, zstd bombs and escaping member names end in one line, exit 2."""

from __future__ import annotations

import json
import os
import stat
import zipfile

import numpy as np
import pytest

from bundle_forge import forge, invoke, make_site, move_origin, read_members, write_sealed, zstd_bomb
from mapstore.bundle import (MANIFEST, SIGNATURE, BundleError, BundleLimits, apply_delta, open_bundle,
                             verify_bundle)
from mapstore.signing import load_public_key
from pipeline.config import load_config
from tracker.bundle_map import open_bundle as tracker_open


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    return make_site(tmp_path_factory.mktemp("trust"))


def _one_line(r, *needles):
    text = r.output.strip()
    assert r.exit_code == 2, r.output
    assert "\n" not in text and "Traceback" not in text and "\x1b" not in text, text
    for n in needles:
        assert n in text, text
    return text


def _tile_names(path):
    return [n for n, _ in read_members(path) if n.startswith("floor/0/c/")]


def _swap_level0(members):
    """Every level-0 tile gets another tile's bytes (a wrong map everywhere)."""
    names = sorted(n for n in members if n.startswith("floor/0/c/"))
    out = dict(members)
    for a, b in zip(names, names[1:] + names[:1]):
        out[a] = members[b]
    return out


# --- keys, signing, verify ------------------------------------------------------------------


def test_keys_new_writes_a_private_key_0600_and_refuses_to_overwrite(site, tmp_path):
    mode = stat.S_IMODE(os.stat(site["key"]).st_mode)
    assert mode == 0o600 and site["pub"].read_text().startswith("mosaicmap-ed25519 ")
    assert b"PRIVATE KEY" in site["key"].read_bytes() and b"PRIVATE" not in site["pub"].read_bytes()
    before = site["key"].read_bytes()
    _one_line(invoke("keys", "new", site["key"]), "refusing to overwrite")
    assert site["key"].read_bytes() == before


def test_signed_bundle_verifies_with_its_key_and_not_with_another(site, tmp_path):
    r = invoke("verify", site["signed"], "--key", site["pub"])
    assert r.exit_code == 0 and "signature verified" in r.output, r.output
    assert "signature not checked" in invoke("verify", site["signed"]).output
    assert invoke("keys", "new", tmp_path / "other").exit_code == 0
    _one_line(invoke("verify", site["signed"], "--key", tmp_path / "other.pub"), "manifest.sig", "not a trusted key")
    _one_line(invoke("verify", site["unsigned"], "--key", site["pub"]), "manifest.sig", "not signed")
    names = [n for n, _ in read_members(site["signed"])]
    assert names[-2:] == [MANIFEST, SIGNATURE]


def test_forged_bundle_is_refused_by_verify_key_and_by_track(site, tmp_path, small_log):
    forged = tmp_path / "forged.zip"
    forge(site["signed"], forged, _swap_level0)
    assert verify_bundle(forged) == []  # every hash and the seal check: only the signature can tell
    _one_line(invoke("verify", forged, "--key", site["pub"]), "forged.zip", "manifest.sig", "forged")
    keys = [load_public_key(site["pub"])]
    with pytest.raises(BundleError, match="forged or damaged"):  # at open or at the first tile read
        with tracker_open(forged, keys=keys) as tm:
            for r, c in ((0, 0), (1, 1), (2, 2)):
                tm.bundle.read_tile(0, r, c)
    r = invoke("track", forged, small_log, "--key", site["pub"], "--start", "0.5,0.5,0", "--quiet")
    _one_line(r, "forged.zip", "forged or damaged")


def test_origin_moved_half_a_metre_and_resealed_is_refused(site, tmp_path, small_log):
    moved = tmp_path / "moved.zip"
    forge(site["signed"], moved, move_origin,
          manifest_edit=lambda m: m["grid"].update({k: v + 0.5 for k, v in m["grid"].items() if k == "x0_m"}))
    assert verify_bundle(moved) == []
    with open_bundle(moved) as b:  # unchecked, the forgery reads as a map 0.5 m off
        with open_bundle(site["signed"]) as good:
            assert b.grid.x0 == pytest.approx(good.grid.x0 + 0.5)
    _one_line(invoke("verify", moved, "--key", site["pub"]), "moved.zip", "manifest.sig")
    _one_line(invoke("track", moved, small_log, "--key", site["pub"], "--quiet"), "moved.zip", "forged or damaged")
    with pytest.raises(BundleError):
        tracker_open(moved, keys=[load_public_key(site["pub"])])


def test_track_refuses_unsigned_bundles_unless_insecure(site, small_log, tmp_path):
    r = invoke("track", site["unsigned"], small_log, "--key", site["pub"], "--quiet")
    _one_line(r, "v1-unsigned.zip", "not signed")
    r = invoke("track", site["signed"], small_log, "--quiet")  # no trusted key configured
    _one_line(r, "v1.zip", "no trusted key")
    r = invoke("track", site["unsigned"], small_log, "--insecure", "--quiet", "--frames", "0:3")
    assert r.exit_code == 0, r.output
    assert "warning: --insecure" in r.output
    # a trusted key from the configuration
    cfg = tmp_path / "trust.toml"
    cfg.write_text(f'[tracker.bundle]\ntrusted_keys = ["{site["pub"]}"]\n')
    r = invoke("track", site["signed"], small_log, "--config", cfg, "--quiet", "--frames", "0:3")
    assert r.exit_code == 0 and "warning" not in r.output, r.output


def test_damaged_member_is_refused_at_its_first_read_only(site, tmp_path):
    """Open checks the signature only; a member is checked when first read."""
    data = bytearray(site["signed"].read_bytes())
    name = _tile_names(site["signed"])[5]
    with zipfile.ZipFile(site["signed"]) as z:
        zi = z.getinfo(name)
    at = zi.header_offset + 30 + len(name) + 10
    data[at] ^= 0xFF
    bad = tmp_path / "bad.zip"
    bad.write_bytes(bytes(data))
    keys = [load_public_key(site["pub"])]
    with open_bundle(bad, keys=keys) as b:
        assert b.signed
        r, c = map(int, name.split("/")[-2:])
        b.read_tile(0, 0, 0)
        with pytest.raises(BundleError) as e:
            b.read_tile(0, r, c)
        assert name in str(e.value)
        assert b.manifest["kind"] == "full"  # the manifest itself is intact and signed


def test_expected_members_are_looked_up_in_one_pass_and_still_checked(site, tmp_path):
    """ZipIndex.expect (the tracker's start-up reading the whole relocalization index)
    resolves many signed entries at once: the same entries as one by one, no page parsed
    twice, and a damaged member is still refused at its read."""
    keys = [load_public_key(site["pub"])]
    names = _tile_names(site["signed"])
    with open_bundle(site["signed"], keys=keys) as b:
        idx = b.store.index
        one_by_one = {n: idx.listed(n) for n in names}
    with open_bundle(site["signed"], keys=keys) as b:
        idx = b.store.index
        idx.expect(names + ["floor/0/c/999/999"])
        assert {n: idx._listed[n] for n in names} == one_by_one
        assert idx._listed["floor/0/c/999/999"] is None  # not listed: never read
        pages = len(idx.trust._parsed)
        assert 0 < pages <= len(idx.trust._firsts)
        for n in names:
            assert idx.read(n) is not None
        assert len(idx.trust._parsed) == pages
    data = bytearray(site["signed"].read_bytes())
    with zipfile.ZipFile(site["signed"]) as z:
        zi = z.getinfo(names[3])
    data[zi.header_offset + 30 + len(names[3]) + 10] ^= 0xFF
    bad = tmp_path / "bad.zip"
    bad.write_bytes(bytes(data))
    with open_bundle(bad, keys=keys) as b:
        b.store.index.expect(names)
        with pytest.raises(BundleError) as e:
            b.store.index.read(names[3])
        assert names[3] in str(e.value)


def test_damaged_zarr_json_is_one_line(site, tmp_path, small_log):
    bad = tmp_path / "utf8.zip"
    forge(site["signed"], bad, lambda m: {**m, "floor/zarr.json": m["floor/zarr.json"][:-2] + b"\xff\xfe}"},
          keep_signature=False)
    _one_line(invoke("verify", bad), "utf8.zip", "floor/zarr.json", "not UTF-8")
    _one_line(invoke("track", bad, small_log, "--insecure", "--quiet"), "utf8.zip", "floor/zarr.json", "not UTF-8")
    huge = tmp_path / "huge.zip"
    forge(site["signed"], huge, lambda m: {**m, "floor/zarr.json": m["floor/zarr.json"] + b" " * (2 << 20)},
          keep_signature=False)
    _one_line(invoke("verify", huge), "floor/zarr.json", "metadata of")


def test_zstd_bomb_chunk_is_refused_before_decompressing(site, tmp_path, small_log):
    name = _tile_names(site["signed"])[0]
    for label, bomb in (("1GB", zstd_bomb(1 << 30)), ("lying", zstd_bomb(8 << 20, declared=64 * 64)),
                        ("nosize", zstd_bomb(1 << 24, declared=None))):
        out = tmp_path / f"bomb-{label}.zip"
        forge(site["signed"], out, lambda m: {**m, name: bomb}, keep_signature=False)
        problems = verify_bundle(out)
        if label != "lying":
            assert problems and name in problems[0], problems
            _one_line(invoke("verify", out), name)
        r, c = map(int, name.split("/")[-2:])
        with tracker_open(out, insecure=True) as tm:
            with pytest.raises(BundleError) as e:
                tm.bundle.read_tile(0, r, c)
            assert name in str(e.value)
        signed = tmp_path / f"bomb-{label}-signed.zip"
        forge(site["signed"], signed, lambda m: {**m, name: bomb})
        with pytest.raises(BundleError), tracker_open(signed, keys=[load_public_key(site["pub"])]) as tm:
            tm.bundle.read_tile(0, r, c)


@pytest.mark.parametrize("evil", ["../../evil", "/abs/evil", "floor/../../evil", "C:evil", "floor\\evil",
                                  "floor/0/c/\x1b[31m/0", "x" * 300])
def test_escaping_member_names_are_refused_everywhere(site, tmp_path, small_log, evil):
    bad = tmp_path / "names.zip"
    forge(site["signed"], bad, lambda m: {**m, evil: b"boom"}, keep_signature=False)
    text = _one_line(invoke("verify", bad), "names.zip")
    assert "\x1b" not in text
    problems = verify_bundle(bad)
    assert problems and repr(evil)[1:-1][:20] in problems[0] or evil[:20] in problems[0]
    _one_line(invoke("track", bad, small_log, "--insecure", "--quiet"), "names.zip")
    # apply-delta never writes such a name
    delta = tmp_path / "delta-evil.zip"
    forge(site["delta"], delta, lambda m: {**m, evil: b"boom"}, keep_signature=False)
    out = tmp_path / "out" / "patched.zip"
    _one_line(invoke("apply-delta", site["signed"], delta, out), "delta-evil.zip")
    assert not out.exists() and not (tmp_path / "evil").exists()


# --- deltas ---------------------------------------------------------------------------------


def test_signed_delta_applies_into_a_signed_bundle(site, tmp_path, small_log):
    out = tmp_path / "patched.zip"
    r = invoke("apply-delta", site["signed"], site["delta"], out, "--key", site["pub"])
    assert r.exit_code == 0, r.output
    assert invoke("verify", out, "--key", site["pub"]).exit_code == 0
    a, b = (json.loads(dict(read_members(p))[MANIFEST]) for p in (out, site["signed2"]))
    assert a["content_sha256"] == b["content_sha256"] and a["members"] == b["members"]
    r = invoke("track", out, small_log, "--key", site["pub"], "--quiet", "--frames", "0:3")
    assert r.exit_code == 0, r.output


def test_delta_signature_and_base_are_checked(site, tmp_path):
    keys = [load_public_key(site["pub"])]
    # forged delta: a changed tile, hashes and seal recomputed, the old signature kept
    forged = tmp_path / "forged-delta.zip"
    forge(site["delta"], forged, lambda m: {k: (v[:-1] + bytes([v[-1] ^ 1]) if "/c/" in k else v)
                                            for k, v in m.items()})
    assert verify_bundle(forged) == []
    _one_line(invoke("apply-delta", site["signed"], forged, tmp_path / "x.zip", "--key", site["pub"]),
              "forged-delta.zip", "manifest.sig")
    # the wrong base (v2 instead of v1)
    _one_line(invoke("apply-delta", site["signed2"], site["delta"], tmp_path / "y.zip", "--key", site["pub"]),
              "base version mismatch")
    # an unsigned delta with --key
    unsigned = tmp_path / "unsigned-delta.zip"
    forge(site["delta"], unsigned, lambda m: m, keep_signature=False)
    with pytest.raises(BundleError, match="not signed"):
        apply_delta(site["signed"], unsigned, tmp_path / "z.zip", keys=keys)
    # an unsigned base with --key
    _one_line(invoke("apply-delta", site["unsigned"], site["delta"], tmp_path / "w.zip", "--key", site["pub"]),
              "v1-unsigned.zip", "not signed")
    assert not any((tmp_path / n).exists() for n in ("x.zip", "y.zip", "z.zip", "w.zip"))


def test_bundle_limits_equal_the_configuration():
    table = load_config(None)["tracker"]["bundle"]
    assert BundleLimits.from_dict(table) == BundleLimits()
    assert table["trusted_keys"] == []
    with pytest.raises(ValueError):
        BundleLimits.from_dict({"max_chunk_bytes": 0})


def test_signing_module_imports_no_pipeline_icechunk_or_click():
    from conftest import modules_pulled_in

    assert modules_pulled_in(["mapstore.signing"], ("pipeline", "icechunk", "click", "zarr")) == []
    assert modules_pulled_in(["tracker.bundle_map"], ("pipeline", "icechunk", "click")) == []


@pytest.mark.parametrize("n", [0, 1, 200, 240, 255, 256, 300, 65791, 65792, 614400, 2**33])
def test_zstd_content_size_reads_the_frame_header(n):
    """The decompressed size a zstd frame states, for each width of its size field (1, 2, 4
    and 8 bytes; numcodecs' frames, and headers made by hand per RFC 8878): what bundles and the frames store read before
    decompressing a chunk."""
    from numcodecs import Zstd

    from mapstore.bundle import zstd_content_size

    if n <= 614400:
        assert zstd_content_size(Zstd().encode(np.zeros(n, np.uint8).tobytes())) == n
    magic = b"\x28\xb5\x2f\xfd"
    if n < 256:  # single segment, 1-byte size
        assert zstd_content_size(magic + bytes([0x20]) + bytes([n]) + b"\0" * 3) == n
    if 256 <= n < 65792:  # 2 bytes hold n - 256, after a window descriptor
        assert zstd_content_size(magic + bytes([0x40, 0x50]) + (n - 256).to_bytes(2, "little") + b"\0" * 3) == n
    if n >= 2**32:  # 8 bytes, with a 4-byte dictionary id before them
        assert zstd_content_size(magic + bytes([0xC3, 0x50]) + b"\1\2\3\4" + n.to_bytes(8, "little")) == n
    assert zstd_content_size(b"\0" * 16) is None  # not a zstd frame
    assert zstd_content_size(magic + bytes([0x00, 0x50]) + b"\0" * 8) is None  # size not stated
