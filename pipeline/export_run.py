"""What ``mosaicmap export``, ``verify`` and ``apply-delta`` run (the commands,
:mod:`pipeline.cli.export`, are their options; each calls one function here and prints
its summary).

:func:`export_map` writes a bundle (:mod:`mapstore.bundle`: one sealed zip file with a zarr
v3 map extract and a manifest) of a region or a corridor of a map version, at chosen levels
and layers, with the chosen route panoramas (cut to the selection) (:mod:`mapstore.export`);
with ``since`` a delta holding only the tiles changed since an older version; with ``fmt
= "ome-zarr"`` a plain OME-Zarr directory for viewers (:class:`mapstore.export.OmeZarrSink`:
``OUT/map.zarr`` the zarr hierarchy, ``OUT/manifest.json`` beside it; the report's ``open``
names the images to open). With ``sign_key`` bundles and deltas are signed
(:mod:`mapstore.signing`). A bundle holding intensity level 0 also carries the tracker's
relocalization index (``floor/reloc/features``, unless ``reloc_index=False`` or ``[export]
reloc_index = false``): :func:`pipeline.reloc_export.reloc_index_array`.

:func:`verify_file` checks a bundle's seal, manifest and every checksum (with ``keys`` its
signature too); :func:`apply_delta_file` patches an old bundle with a delta into the new one
(what the vehicle side runs; with ``keys`` both must be signed by a trusted key).

Each returns the command's JSON report (a dict; sizes in bytes, times in seconds, bounds in
metres of the map frame) and raises :class:`pipeline.errors.BadInput` (exit code 2) naming
the option or file at fault, in the command's words.
"""

from __future__ import annotations

import csv
import time
from functools import partial
from pathlib import Path
from typing import Sequence

import numpy as np

from pipeline.errors import BadInput
from pipeline.map_version import open_version
from pipeline.progress import progress
from pipeline.reloc_export import reloc_index_array

__all__ = ["read_corridor_csv", "export_map", "export_summary", "verify_file", "verify_problem", "verify_summary",
           "apply_delta_file", "apply_delta_summary", "size_text", "FORMATS"]

SHORT_ID = 8
FORMATS = ("bundle", "ome-zarr")


# --- inputs -------------------------------------------------------------------------------


def read_corridor_csv(path: Path) -> np.ndarray:
    """A guidepath polyline: a CSV whose header names columns ``x`` and ``y`` (metres, world
    frame; a drive-log-style ``t,x,y,theta`` file works too) -> (N, 2). Raises BadInput
    naming the file and line."""
    from pipeline.drivelog import parse_number

    if not path.is_file():
        raise BadInput(path, "file not found")
    pts = []
    try:
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.reader(f)
            header = next(reader, None)
            if header is None:
                raise BadInput(path, "file is empty (expected a header with columns x,y)")
            names = [h.strip() for h in header]
            if "x" not in names or "y" not in names:
                raise BadInput(f"{path}:1", f"header needs columns x and y (metres), got {','.join(names)}")
            ix, iy = names.index("x"), names.index("y")
            for fields in reader:
                lineno = reader.line_num
                if not fields or all(not v.strip() for v in fields):
                    continue
                if len(fields) != len(names):
                    raise BadInput(f"{path}:{lineno}", f"expected {len(names)} fields, got {len(fields)}")
                pts.append((parse_number(path, lineno, "x", fields[ix]), parse_number(path, lineno, "y", fields[iy])))
    except UnicodeDecodeError:
        raise BadInput(path, "not a UTF-8 text file") from None
    except csv.Error as e:
        raise BadInput(path, f"unparsable CSV: {e}") from None
    if len(pts) < 2:
        raise BadInput(path, f"has {len(pts)} point(s); a corridor needs at least 2")
    return np.asarray(pts, float)


def size_text(n: int) -> str:
    """A byte count as people read it: ``1.23 MB`` (powers of 1000)."""
    for unit, f in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= f:
            return f"{n / f:.2f} {unit}"
    return f"{n} B"


# --- keys ---------------------------------------------------------------------------------


def _private_key(path: Path):
    from mapstore.signing import SignatureError, load_private_key

    try:
        return load_private_key(path)
    except SignatureError as e:
        raise BadInput("--sign", str(e)) from None


def _public_keys(items: Sequence[str | Path], option: str = "--key") -> tuple:
    from mapstore.signing import SignatureError, load_public_keys

    try:
        return load_public_keys(items)
    except SignatureError as e:
        raise BadInput(option, str(e)) from None


def _sign(private, result_doc: bytes | None, manifest: bytes) -> bytes:
    from mapstore.signing import signature_document

    return signature_document(manifest, private, result=result_doc)


def _key_id(private) -> str:
    from cryptography.hazmat.primitives import serialization

    from mapstore.signing import key_id

    return key_id(private.public_key().public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw))


def _now() -> str:
    from datetime import datetime, timezone

    return datetime.now(timezone.utc).isoformat(timespec="seconds")


# --- export -------------------------------------------------------------------------------


def _base_version(mrepo, repo: str, since: str, sid: str, branch: str):
    """(snapshot id, zarr root) of the ``since`` version; it must be an ancestor of ``sid``."""
    import zarr

    try:
        base_sid = mrepo.resolve(since, branch)
    except ValueError as e:
        raise BadInput("--since", str(e)) from None
    if base_sid not in {si.id for si in mrepo.repo.ancestry(snapshot_id=sid)}:
        raise BadInput("--since", f"version {since} ({base_sid}) is not an ancestor of the exported version ({sid})")
    root = zarr.open_group(mrepo.repo.readonly_session(snapshot_id=base_sid).store, mode="r")
    if "floor" not in root and "routes" not in root:
        raise BadInput("--since", f"version {since} ({base_sid}) holds no map")
    return base_sid, root


def _reloc_report(ext, manifest: dict, path: str) -> dict:
    """The report's ``reloc_index`` entry: features, tiles (index chunks) and bytes the
    written bundle (or delta) carries, seconds spent computing features."""
    st = ext.derived_stats[path]
    names = [n for n in manifest["members"] if n.startswith(path + "/c/")]
    return {"path": path, "features": sum(st["counts"].get(n, 0) for n in names), "tiles": len(names),
            "bytes": sum(manifest["members"][n]["bytes"] for n in names), "tiles_computed": st["tiles"],
            "seconds": st["seconds"]}


def _routes_report(manifest: dict) -> list[dict]:
    """The report's ``routes`` entry: per route held, the manifest's entry plus ``bytes``
    and ``chunks`` (route chunk members the written bundle or delta carries)."""
    out = []
    for r in manifest.get("routes", []):
        prefix = f"routes/{r['id']}/"
        names = [n for n in manifest["members"] if n.startswith(prefix) and not n.endswith("zarr.json")]
        out.append({**r, "chunks": len(names),
                    "bytes": sum(manifest["members"][n]["bytes"] for n in manifest["members"] if n.startswith(prefix))})
    return out


def _check_format(*, fmt: str, sign_key: Path | None) -> None:
    """The output format, and signing only a bundle (BadInput naming the option)."""
    if fmt not in FORMATS:
        raise BadInput("--format", f"expected one of {', '.join(FORMATS)}, got {fmt!r}")
    if sign_key is not None and fmt != "bundle":
        raise BadInput("--sign", "signs bundles and deltas: not with --format ome-zarr")


def _check_selection_options(*, fmt: str, region, corridor: Path | None, width_m: float | None,
                             since: str | None) -> None:
    """The combinations of selection options an export refuses (BadInput naming the option)."""
    if region is not None and corridor is not None:
        raise BadInput("--region", "give --region or --corridor, not both")
    if width_m is not None and corridor is None:
        raise BadInput("--width", "applies to --corridor only")
    if since is not None and fmt != "bundle":
        raise BadInput("--since", "a delta is a bundle: not with --format ome-zarr")


def export_map(repo: str, out: Path, *, cfg: dict, version: str | None = None, branch: str = "main",
               region: Sequence[float] | None = None, corridor: Path | None = None, width_m: float | None = None,
               levels: Sequence[int] | None = None, layers: Sequence[str] | None = None,
               routes: str | None = None, since: str | None = None, fmt: str = "bundle",
               sign_key: Path | None = None, reloc_index: bool | None = None, quiet: bool = False) -> dict:
    """Export a region or corridor of ``version`` of the map in ``repo`` to ``out``.

    Args:
        repo: the map repository's URL (directory, ``file://``, ``s3://``).
        out: the bundle or delta file, or (``fmt="ome-zarr"``) the directory to write (replaced).
        cfg: the effective configuration (:func:`pipeline.config.load_config`); its ``[export]``
            table gives every default below, ``[tracker.reloc]`` the relocalization index.
        version, branch: the map version to export (default the branch tip).
        region: the world box ``(x0, y0, x1, y1)`` in metres (opposite corners), or
        corridor: a guidepath CSV (:func:`read_corridor_csv`) and ``width_m`` its width in
            metres (default ``[export] corridor_width_m``); neither: the whole map.
        levels: pyramid levels of the intensity (None: ``[export] levels``; empty: all).
        layers: layer names (None: ``[export] layers``).
        routes: route panoramas: ``"all"``, ``"none"`` or comma-separated ids (None:
            ``[export] routes``).
        since: an ancestor version: write a delta holding the tiles changed since it.
        fmt: ``"bundle"`` or ``"ome-zarr"``.
        sign_key: the map owner's private key file: sign the bundle or delta.
        reloc_index: store the relocalization index (None: ``[export] reloc_index`` when
            intensity level 0 is exported to a bundle).
        quiet: no progress bars or lines.

    Returns the report: ``kind``, ``format``, ``path``, ``bytes``, ``members``, ``tiles``,
    ``tiles_by_array``, ``seconds``, ``map_id``, ``version``, ``bounds_m``, ``levels``,
    ``layers``, ``selection``, ``content_sha256``, ``reloc_index``, ``routes``,
    ``signed_by``; ``open`` (OME-Zarr: image name -> path); a delta's ``base``, ``changed``,
    ``changed_tiles``, ``removed``, ``candidate_tiles``, ``selected_tiles``,
    ``changed_fraction``. BadInput naming the option or file at fault.
    """
    from mapstore.export import INTENSITY, Extract, SelectionError, make_selection
    from mapstore.routes import list_routes

    _check_format(fmt=fmt, sign_key=sign_key)
    private = _private_key(sign_key) if sign_key is not None else None
    ecfg = cfg["export"]
    t0 = time.perf_counter()
    _check_selection_options(fmt=fmt, region=region, corridor=corridor, width_m=width_m, since=since)
    box = [float(v) for v in region] if region is not None else None
    path = read_corridor_csv(corridor) if corridor is not None else None
    if corridor is not None and width_m is None:
        width_m = float(ecfg["corridor_width_m"])
    level_list = [int(k) for k in (ecfg["levels"] if levels is None else levels)]
    layer_list = list(ecfg["layers"] if layers is None else layers)
    mrepo, sid, root, info = open_version(repo, version, branch, routes_only_ok=True)
    where = {"region": "--region", "corridor": str(corridor), "width": "--width", "levels": "--levels",
             "layers": "--layers", "routes": "--routes",
             "selection": "--region" if box else str(corridor) if corridor else repo}
    try:
        sel = make_selection(info, region=box, corridor=path, width_m=width_m, levels=level_list or None,
                             layers=layer_list, routes=routes if routes is not None else ecfg["routes"],
                             route_ids=list_routes(root), route_margin_m=float(ecfg["route_margin_m"]))
    except SelectionError as e:
        raise BadInput(where[e.field], e.what) from None
    if fmt == "ome-zarr" and INTENSITY not in sel.layers:
        raise BadInput("--layers", "an OME-Zarr export needs the intensity layer (its multiscales)")
    tags = sorted(t for t, s in mrepo.tags().items() if s == sid)
    has0 = 0 in sel.levels
    if reloc_index and not has0:
        raise BadInput("--reloc-index", "the relocalization index is computed from intensity level 0, which this "
                                        "export leaves out (see --levels, --layers)")
    if reloc_index is None:
        reloc_index = ecfg["reloc_index"] and has0 and fmt == "bundle"
    derived = [reloc_index_array(cfg["tracker"]["reloc"], info.spec.chunk_px)] if reloc_index else []
    chunk_rows = ecfg["route_rows_per_chunk"]
    if isinstance(chunk_rows, bool) or not isinstance(chunk_rows, int) or chunk_rows < 0:
        raise BadInput("config[export.route_rows_per_chunk]", f"must be an integer >= 0 (0 = the map's chunks), "
                                                              f"got {chunk_rows!r}")

    def extract(version_root=root) -> Extract:
        """The selection's extract of a version (default the exported one)."""
        return Extract(version_root, sel, int(ecfg["zstd_level"]), derived, route_chunk_rows=chunk_rows)

    ext = extract()
    try:
        manifest, nbytes = _write(ext, extract, out, fmt=fmt, since=since, private=private, mrepo=mrepo, repo=repo,
                                  sid=sid, branch=branch, tags=tags, quiet=quiet)
    except SelectionError as e:
        raise BadInput(where[e.field], e.what) from None
    return _export_report(manifest, ext, sel, derived, out=out, fmt=fmt, nbytes=nbytes,
                          seconds=time.perf_counter() - t0, private=private)


def _write(ext, extract, out: Path, *, fmt: str, since: str | None, private, mrepo, repo: str, sid: str,
           branch: str, tags: list[str], quiet: bool) -> tuple[dict, int]:
    """Write the OME-Zarr directory, the delta or the bundle; (manifest, bytes written)."""
    from mapstore.bundle import BundleWriter
    from mapstore.export import export_delta, export_extract

    bar = partial(progress, quiet=quiet)
    if fmt == "ome-zarr":
        from mapstore.export import OmeZarrSink
        from pipeline.fsutil import atomic_dir

        with atomic_dir(out, replace=True) as tmp:
            manifest = export_extract(ext, OmeZarrSink(tmp), snapshot=sid, tags=tags, progress=bar)
        return manifest, sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    if since is not None:
        base_sid, base_root = _base_version(mrepo, repo, since, sid, branch)
        base = extract(base_root)
        changed = mrepo.changed_chunks(base_sid, sid, branch)
        created, sign = _now(), None
        if private is not None:
            from mapstore.bundle import manifest_bytes
            from mapstore.export import HashingSink
            from mapstore.signing import signature_document

            result = export_extract(extract(), HashingSink(), snapshot=sid, tags=tags, created=created, progress=bar)
            result.pop("stats")
            result_doc = signature_document(manifest_bytes(result), private)
            sign = partial(_sign, private, result_doc)
        manifest = export_delta(ext, base, changed, BundleWriter(out, sign=sign), snapshot=sid, tags=tags,
                                base_snapshot=base_sid, created=created, progress=bar)
        return manifest, out.stat().st_size
    sign = None if private is None else partial(_sign, private, None)
    manifest = export_extract(ext, BundleWriter(out, sign=sign), snapshot=sid, tags=tags, progress=bar)
    return manifest, out.stat().st_size


def _export_report(manifest: dict, ext, sel, derived: list, *, out: Path, fmt: str, nbytes: int, seconds: float,
                   private) -> dict:
    """The export's report (see :func:`export_map`)."""
    stats = manifest["stats"]
    rep = {
        "kind": manifest["kind"], "format": fmt, "path": str(out), "bytes": nbytes,
        "members": len(manifest["members"]) + 1, "tiles": stats["tiles"], "tiles_by_array": stats["tiles_by_array"],
        "seconds": seconds, "map_id": manifest["map_id"], "version": manifest["version"],
        "bounds_m": manifest["bounds_m"], "levels": list(sel.levels), "layers": list(sel.layers),
        "selection": manifest["selection"], "content_sha256": manifest["content_sha256"],
        "reloc_index": _reloc_report(ext, manifest, derived[0].path) if derived else None,
        "routes": _routes_report(manifest),
        "signed_by": None if private is None else _key_id(private),
    }
    if "ome_zarr" in manifest:
        rep["open"] = {name: str(out / rel) for name, rel in manifest["ome_zarr"]["images"].items()}
    if manifest["kind"] == "delta":
        rep.update({"base": manifest["base"], "changed": len(manifest["changed"]), "changed_tiles": stats["tiles"],
                    "removed": stats["removed"], "candidate_tiles": stats["candidates"],
                    "selected_tiles": stats["selected_tiles"],
                    "changed_fraction": stats["tiles"] / stats["selected_tiles"] if stats["selected_tiles"] else 0.0})
    return rep


def export_summary(rep: dict) -> str:
    """What ``mosaicmap export`` prints of its report: one line (and, for an OME-Zarr
    directory, a line per image to open)."""
    x0, y0, x1, y1 = rep["bounds_m"]
    v = rep["version"]
    what = {"bundle": "bundle", "ome-zarr": "OME-Zarr directory"}[rep["format"]]
    head = (f"{'delta' if rep['kind'] == 'delta' else what} {rep['path']}: {rep['members']} members "
            f"({rep['tiles']} tiles), {size_text(rep['bytes'])}; version {v['number']} ({v['snapshot'][:SHORT_ID]})")
    if rep["kind"] == "delta":
        b = rep["base"]
        head += (f" since version {b['number']} ({b['snapshot'][:SHORT_ID]}): {rep['changed_tiles']} changed tiles "
                 f"of {rep['selected_tiles']} selected ({100 * rep['changed_fraction']:.2f} %), "
                 f"{rep['removed']} removed")
    if rep.get("signed_by"):
        head += f"; signed by key {rep['signed_by']}"
    levels = ",".join(map(str, rep["levels"])) or "none"
    ri = rep.get("reloc_index")
    reloc = (f"; reloc index {ri['features']} features in {ri['tiles']} tiles, {size_text(ri['bytes'])} "
             f"({ri['seconds']:.1f} s)" if ri else "; no reloc index")
    held = rep.get("routes") or []
    routes = ("; routes " + ", ".join(f"{r['id']} ({r['rows']} rows from s {r['s0_m']:.2f} m"
                                      f"{', cut' if r['cropped'] else ''})" for r in held)) if held else ""
    text = (f"{head}; bounds x {x0:.3f}..{x1:.3f} m, y {y0:.3f}..{y1:.3f} m; levels {levels}; "
            f"layers {','.join(rep['layers'])}{reloc}{routes}; {rep['seconds']:.1f} s")
    if rep.get("open"):  # the OME-Zarr images, one line each: what to give a viewer
        text += "\nopen in an OME-Zarr viewer (napari, neuroglancer):" + "".join(
            f"\n  {name}: {path}" for name, path in rep["open"].items())
    return text


# --- verify, apply-delta ------------------------------------------------------------------


def verify_file(bundle: Path, *, keys: Sequence[str | Path] = ()) -> dict:
    """Check ``bundle`` (or a delta) completely: its seal, manifest, every member's name,
    checksum and size bounds, and with ``keys`` (trusted public key files) its signature.

    Returns the report: ``path``, ``ok``, ``problems`` (one line each; empty when ok),
    ``bytes``, ``signature_checked``, ``seconds``; when ok also ``kind``, ``members``,
    ``map_id``, ``version``, ``content_sha256`` (and a delta's ``base``). A bad bundle is
    no exception here (its report says why; :func:`verify_problem` is the one line to
    report); BadInput for a missing file or an unreadable key."""
    from mapstore.bundle import BundleError, read_manifest, verify_bundle

    t0 = time.perf_counter()
    trusted = _public_keys(keys) if keys else None
    if not bundle.is_file():
        raise BadInput(bundle, "file not found")
    problems = verify_bundle(bundle, keys=trusted)
    rep: dict = {"path": str(bundle), "ok": not problems, "problems": problems, "bytes": bundle.stat().st_size,
                 "signature_checked": trusted is not None}
    if not problems:
        try:
            m = read_manifest(bundle)
        except BundleError as e:
            raise BadInput(e.part, e.what) from None
        rep.update({"kind": m["kind"], "members": len(m["members"]) + 1, "map_id": m["map_id"],
                    "version": m["version"], "content_sha256": m["content_sha256"]})
        if m["kind"] == "delta":
            rep["base"] = m["base"]
    rep["seconds"] = time.perf_counter() - t0
    return rep


def verify_problem(rep: dict) -> str | None:
    """The one line a failed verification reports (its first problem and how many more),
    None when the bundle is good."""
    problems = rep["problems"]
    if not problems:
        return None
    more = f" (and {len(problems) - 1} more problem(s))" if len(problems) > 1 else ""
    return problems[0] + more


def verify_summary(rep: dict) -> str:
    """What ``mosaicmap verify`` prints of a good bundle's report."""
    v = rep["version"]
    extra = f", base version {rep['base']['number']}" if rep["kind"] == "delta" else ""
    return (f"{rep['path']}: OK: {rep['kind']} bundle of map {rep['map_id'][:SHORT_ID]}, version {v['number']} "
            f"({v['snapshot'][:SHORT_ID]}){extra}; {rep['members']} members, {size_text(rep['bytes'])}; seal and "
            f"every checksum verified"
            + ("; signature verified" if rep["signature_checked"] else "; signature not checked (no --key)"))


def apply_delta_file(base: Path, delta: Path, out: Path, *, keys: Sequence[str | Path] = ()) -> dict:
    """Patch bundle ``base`` with ``delta`` into the new bundle ``out`` (both inputs and the
    result are verified; a delta made for another base is refused). With ``keys`` (trusted
    public key files) both inputs must be signed by one of them, and ``out`` carries the map
    owner's signature of the patched bundle (which a signed delta holds).

    Returns the report: ``path``, ``base``, ``delta``, ``bytes``, ``delta_bytes``,
    ``delta_ratio``, ``members``, ``version``, ``content_sha256``, ``seconds``. BadInput
    naming the bad file or part."""
    from mapstore.bundle import BundleError, apply_delta

    t0 = time.perf_counter()
    trusted = _public_keys(keys) if keys else None
    for p in (base, delta):
        if not p.is_file():
            raise BadInput(p, "file not found")
    try:
        m = apply_delta(base, delta, out, keys=trusted)
    except BundleError as e:
        raise BadInput(e.part, e.what) from None
    nbytes, dbytes = out.stat().st_size, delta.stat().st_size
    return {"path": str(out), "base": str(base), "delta": str(delta), "bytes": nbytes, "delta_bytes": dbytes,
            "delta_ratio": dbytes / nbytes, "members": len(m["members"]) + 1, "version": m["version"],
            "content_sha256": m["content_sha256"], "seconds": time.perf_counter() - t0}


def apply_delta_summary(rep: dict) -> str:
    """What ``mosaicmap apply-delta`` prints of its report."""
    v = rep["version"]
    return (f"{rep['path']}: version {v['number']} ({v['snapshot'][:SHORT_ID]}) = {Path(rep['base']).name} + "
            f"{Path(rep['delta']).name}; {rep['members']} members, {size_text(rep['bytes'])} (delta "
            f"{size_text(rep['delta_bytes'])} = {100 * rep['delta_ratio']:.2f} %); verified")
