"""Commands: export, verify, apply-delta (vehicle bundles and OME-Zarr extracts).

``export`` writes a bundle (:mod:`mapstore.bundle`: one sealed zip file with a zarr v3 map
extract and a manifest) of a region or a corridor of a map version, at chosen levels and
layers, with the chosen route panoramas (``--routes``; cut to the selection) (:mod:`mapstore.export`); with ``--since`` a delta holding only the tiles changed
since an older version; with ``--format ome-zarr`` a plain OME-Zarr directory for viewers
(:class:`mapstore.export.OmeZarrSink`: ``OUT/map.zarr`` the zarr hierarchy, ``OUT/manifest.json``
beside it; the summary names the images to open).
``verify`` checks a bundle's seal, manifest and every checksum (with ``--key`` its signature
too); ``apply-delta`` patches an old bundle with a delta into the new one (what the vehicle
side runs; with ``--key`` both must be signed by a trusted key). ``keys new`` makes the map
owner's key pair; ``export --sign KEY`` signs bundles and deltas (:mod:`mapstore.signing`).

A bundle holding intensity level 0 also carries the tracker's relocalization index
(``floor/reloc/features``, unless ``--no-reloc-index`` or ``[export] reloc_index = false``):
:func:`pipeline.reloc_export.reloc_index_array`.
"""

from __future__ import annotations

import csv
import time
from functools import partial
from pathlib import Path

import click
import numpy as np

from pipeline.cli.common import config_option, no_config, no_quiet, quiet_option, report_option, setup, write_report
from pipeline.cli.map import _open_version, branch_option, version_option
from pipeline.errors import BadInput
from pipeline.progress import progress
from pipeline.reloc_export import reloc_index_array

SHORT_ID = 8


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


def _parse_region(text: str) -> list[float]:
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise BadInput("--region", f"expected x0,y0,x1,y1 in metres, got {text!r}") from None
    if len(values) != 4:
        raise BadInput("--region", f"expected 4 numbers x0,y0,x1,y1, got {len(values)}")
    return values


def _parse_levels(text: str | None, default: list) -> list[int]:
    if text is None:
        return [int(k) for k in default]
    try:
        return [int(p) for p in text.split(",") if p.strip()]
    except ValueError:
        raise BadInput("--levels", f"expected level numbers like 0,1,2, got {text!r}") from None


def _parse_layers(text: str | None, default: list) -> list[str]:
    if text is None:
        return list(default)
    names = [p.strip() for p in text.split(",") if p.strip()]
    if not names:
        raise BadInput("--layers", "no layer named")
    return names


def _size(n: int) -> str:
    for unit, f in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= f:
            return f"{n / f:.2f} {unit}"
    return f"{n} B"


def _bundle_error(e) -> BadInput:
    return BadInput(e.part, e.what)


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


# --- export -------------------------------------------------------------------------------


@click.command("export")
@click.argument("repo")
@click.argument("out", type=click.Path(path_type=Path))
@version_option
@branch_option
@click.option("--region", default=None, metavar="X0,Y0,X1,Y1",
              help="Export the world box with these opposite corners (metres).")
@click.option("--corridor", type=click.Path(dir_okay=False, path_type=Path), default=None, metavar="PATH.csv",
              help="Export a corridor along this polyline: a CSV with columns x,y in metres "
                   "(a drive log's t,x,y,theta file works too).")
@click.option("--width", type=float, default=None, metavar="METRES",
              help="Corridor width in metres (default [export] corridor_width_m).")
@click.option("--levels", default=None, metavar="0,1,2",
              help="Pyramid levels of the intensity (default [export] levels; empty = all).")
@click.option("--layers", default=None, metavar="intensity,texture",
              help="Layers: intensity, coverage, texture, uniqueness, updated (default [export] layers).")
@click.option("--routes", "routes", default=None, metavar="all|none|ID[,ID...]",
              help="Route panoramas (/routes/<id>) to export: all, none or these ids (default [export] "
                   "routes). With --region or --corridor a route is cut to its rows whose poses lie within "
                   "[export] route_margin_m of the selection; a route without such a row is left out.")
@click.option("--since", default=None, metavar="VERSION",
              help="Write a delta: only the tiles changed since VERSION (an ancestor), to apply with "
                   "`mosaicmap apply-delta` to the bundle of VERSION with the same selection.")
@click.option("--format", "fmt", type=click.Choice(["bundle", "ome-zarr"]), default="bundle", show_default=True,
              help="bundle: one sealed zip file for vehicles; ome-zarr: a plain OME-Zarr directory for "
                   "viewers: open OUT/map.zarr/floor (intensity) or OUT/map.zarr/layers/<name> in napari or "
                   "neuroglancer; OUT/manifest.json lists the files.")
@click.option("--sign", "sign_key", type=click.Path(dir_okay=False, path_type=Path), default=None, metavar="KEY",
              help="Sign the bundle or delta with this private key (`mosaicmap keys new`): vehicles load only "
                   "bundles signed by a key they trust. A signed delta also carries the signature of the bundle "
                   "apply-delta makes from it, which costs a full export's encoding of the new version.")
@click.option("--reloc-index/--no-reloc-index", "reloc_index", default=None,
              help="Store the tracker's relocalization index (ORB features per level-0 tile, "
                   "[tracker.reloc]) in the bundle. Default: [export] reloc_index (true) when intensity "
                   "level 0 is exported; never by default in an OME-Zarr directory.")
@config_option
@report_option
@quiet_option
def export_cmd(repo: str, out: Path, version: str | None, branch: str, region: str | None, corridor: Path | None,
               width: float | None, levels: str | None, layers: str | None, routes: str | None, since: str | None,
               fmt: str, sign_key: Path | None, reloc_index: bool | None, config_file, report, quiet) -> None:
    """Export a region or corridor of a map version in REPO to OUT: a vehicle bundle, a
    delta (--since) or an OME-Zarr directory (--format ome-zarr); --sign KEY signs it."""
    from mapstore.bundle import BundleWriter
    from mapstore.export import INTENSITY, Extract, SelectionError, export_delta, export_extract, make_selection
    from mapstore.routes import list_routes

    cfg = setup(config_file, quiet)
    if sign_key is not None and fmt != "bundle":
        raise BadInput("--sign", "signs bundles and deltas: not with --format ome-zarr")
    private = _private_key(sign_key) if sign_key is not None else None
    ecfg = cfg["export"]
    t0 = time.perf_counter()
    if region is not None and corridor is not None:
        raise BadInput("--region", "give --region or --corridor, not both")
    if width is not None and corridor is None:
        raise BadInput("--width", "applies to --corridor only")
    if since is not None and fmt != "bundle":
        raise BadInput("--since", "a delta is a bundle: not with --format ome-zarr")
    box = _parse_region(region) if region is not None else None
    path = read_corridor_csv(corridor) if corridor is not None else None
    if corridor is not None and width is None:
        width = float(ecfg["corridor_width_m"])
    level_list = _parse_levels(levels, ecfg["levels"])
    layer_list = _parse_layers(layers, ecfg["layers"])
    mrepo, sid, root, info = _open_version(repo, version, branch, routes_only_ok=True)
    where = {"region": "--region", "corridor": str(corridor), "width": "--width", "levels": "--levels",
             "layers": "--layers", "routes": "--routes",
             "selection": "--region" if box else str(corridor) if corridor else repo}
    try:
        sel = make_selection(info, region=box, corridor=path, width_m=width, levels=level_list or None,
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
    ext = Extract(root, sel, int(ecfg["zstd_level"]), derived, route_chunk_rows=chunk_rows)
    bar = partial(progress, quiet=quiet)
    try:
        if fmt == "ome-zarr":
            from mapstore.export import OmeZarrSink
            from pipeline.fsutil import atomic_dir

            with atomic_dir(out, replace=True) as tmp:
                manifest = export_extract(ext, OmeZarrSink(tmp), snapshot=sid, tags=tags, progress=bar)
            nbytes = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
        elif since is not None:
            base_sid, base_root = _base_version(mrepo, repo, since, sid, branch)
            base = Extract(base_root, sel, int(ecfg["zstd_level"]), derived, route_chunk_rows=chunk_rows)
            changed = mrepo.changed_chunks(base_sid, sid, branch)
            created, sign = _now(), None
            if private is not None:
                from mapstore.bundle import manifest_bytes
                from mapstore.export import HashingSink
                from mapstore.signing import signature_document

                full = Extract(root, sel, int(ecfg["zstd_level"]), derived, route_chunk_rows=chunk_rows)
                result = export_extract(full, HashingSink(), snapshot=sid, tags=tags, created=created, progress=bar)
                result.pop("stats")
                result_doc = signature_document(manifest_bytes(result), private)
                sign = partial(_sign, private, result_doc)
            manifest = export_delta(ext, base, changed, BundleWriter(out, sign=sign), snapshot=sid, tags=tags,
                                    base_snapshot=base_sid, created=created, progress=bar)
            nbytes = out.stat().st_size
        else:
            sign = None if private is None else partial(_sign, private, None)
            manifest = export_extract(ext, BundleWriter(out, sign=sign), snapshot=sid, tags=tags, progress=bar)
            nbytes = out.stat().st_size
    except SelectionError as e:
        raise BadInput(where[e.field], e.what) from None
    seconds = time.perf_counter() - t0
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
    write_report(report, rep)
    click.echo(_summary(rep))


def _now() -> str:
    from datetime import datetime, timezone

    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def _private_key(path: Path):
    from mapstore.signing import SignatureError, load_private_key

    try:
        return load_private_key(path)
    except SignatureError as e:
        raise BadInput("--sign", str(e)) from None


def _public_keys(items, option: str = "--key") -> tuple:
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


def _base_version(mrepo, repo: str, since: str, sid: str, branch: str):
    """(snapshot id, zarr root) of the --since version; it must be an ancestor of ``sid``."""
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


def _summary(rep: dict) -> str:
    x0, y0, x1, y1 = rep["bounds_m"]
    v = rep["version"]
    what = {"bundle": "bundle", "ome-zarr": "OME-Zarr directory"}[rep["format"]]
    head = (f"{'delta' if rep['kind'] == 'delta' else what} {rep['path']}: {rep['members']} members "
            f"({rep['tiles']} tiles), {_size(rep['bytes'])}; version {v['number']} ({v['snapshot'][:SHORT_ID]})")
    if rep["kind"] == "delta":
        b = rep["base"]
        head += (f" since version {b['number']} ({b['snapshot'][:SHORT_ID]}): {rep['changed_tiles']} changed tiles "
                 f"of {rep['selected_tiles']} selected ({100 * rep['changed_fraction']:.2f} %), "
                 f"{rep['removed']} removed")
    if rep.get("signed_by"):
        head += f"; signed by key {rep['signed_by']}"
    levels = ",".join(map(str, rep["levels"])) or "none"
    ri = rep.get("reloc_index")
    reloc = (f"; reloc index {ri['features']} features in {ri['tiles']} tiles, {_size(ri['bytes'])} "
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


key_option = click.option(
    "--key", "keys", multiple=True, metavar="PUB",
    help="A trusted public key (KEY.pub of `mosaicmap keys new`; repeatable): the bundle must be signed by one "
         "of them.")


@no_config
@no_quiet
@click.command("verify")
@click.argument("bundle", type=click.Path(path_type=Path))
@key_option
@report_option
def verify_cmd(bundle: Path, keys: tuple[str, ...], report: Path | None) -> None:
    """Check BUNDLE (or a delta) completely: its seal, manifest, every member's name,
    checksum and size bounds, and with --key its signature. Exit code 2 naming the bad
    part when anything is wrong."""
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
            raise _bundle_error(e) from None
        rep.update({"kind": m["kind"], "members": len(m["members"]) + 1, "map_id": m["map_id"],
                    "version": m["version"], "content_sha256": m["content_sha256"]})
        if m["kind"] == "delta":
            rep["base"] = m["base"]
    rep["seconds"] = time.perf_counter() - t0
    write_report(report, rep)
    if problems:
        more = f" (and {len(problems) - 1} more problem(s))" if len(problems) > 1 else ""
        raise BadInput(bundle, problems[0] + more)
    v = rep["version"]
    extra = f", base version {rep['base']['number']}" if rep["kind"] == "delta" else ""
    click.echo(f"{bundle}: OK: {rep['kind']} bundle of map {rep['map_id'][:SHORT_ID]}, version {v['number']} "
               f"({v['snapshot'][:SHORT_ID]}){extra}; {rep['members']} members, {_size(rep['bytes'])}; seal and "
               f"every checksum verified" + ("; signature verified" if trusted else "; signature not checked (no --key)"))


@no_config
@no_quiet
@click.command("apply-delta")
@click.argument("base", type=click.Path(path_type=Path))
@click.argument("delta", type=click.Path(path_type=Path))
@click.argument("out", type=click.Path(path_type=Path))
@key_option
@report_option
def apply_delta_cmd(base: Path, delta: Path, out: Path, keys: tuple[str, ...], report: Path | None) -> None:
    """Patch bundle BASE with DELTA into the new bundle OUT (both inputs and the result
    are verified; a delta made for another base is refused with exit code 2). With --key
    both inputs must be signed by a trusted key, and OUT carries the map owner's
    signature of the patched bundle (which a signed delta holds)."""
    from mapstore.bundle import BundleError, apply_delta

    t0 = time.perf_counter()
    trusted = _public_keys(keys) if keys else None
    for p in (base, delta):
        if not p.is_file():
            raise BadInput(p, "file not found")
    try:
        m = apply_delta(base, delta, out, keys=trusted)
    except BundleError as e:
        raise _bundle_error(e) from None
    nbytes, dbytes = out.stat().st_size, delta.stat().st_size
    rep = {"path": str(out), "base": str(base), "delta": str(delta), "bytes": nbytes, "delta_bytes": dbytes,
           "delta_ratio": dbytes / nbytes, "members": len(m["members"]) + 1, "version": m["version"],
           "content_sha256": m["content_sha256"], "seconds": time.perf_counter() - t0}
    write_report(report, rep)
    v = m["version"]
    click.echo(f"{out}: version {v['number']} ({v['snapshot'][:SHORT_ID]}) = {base.name} + {delta.name}; "
               f"{rep['members']} members, {_size(nbytes)} (delta {_size(dbytes)} = {100 * rep['delta_ratio']:.2f} %); "
               f"verified")
