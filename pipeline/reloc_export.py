"""The tracker's relocalization index as a derived array of an export.

:func:`reloc_index_array` glues :func:`tracker.reloc.tile_features` (the one feature
definition, shared with the vehicle) into :class:`mapstore.export.TileDerived`, the
export's generic per-tile hook, so that mapstore imports nothing of the tracker
(``mosaicmap export`` stores it in a bundle holding intensity level 0, unless
``--no-reloc-index`` or ``[export] reloc_index = false``).
"""

from __future__ import annotations

from functools import partial

import numpy as np

from pipeline.errors import BadInput


def reloc_index_array(reloc: dict | None, tile_px: int):
    """The relocalization index as a derived per-tile array of an export
    (:class:`mapstore.export.TileDerived`): :func:`tracker.reloc.tile_features` over each
    level-0 tile of ``tile_px`` pixels, with ``reloc`` the ``[tracker.reloc]`` table
    (None: the defaults). Raises BadInput when the table holds an unknown key."""
    from mapstore.export import TileDerived
    from tracker.reloc import INDEX_PATH, MARGIN_PX, RECORD_BYTES, RelocParams, index_attributes, tile_features

    try:
        params = RelocParams.from_dict(dict(reloc or {}))
    except (TypeError, ValueError) as e:
        raise BadInput("[tracker.reloc]", str(e)) from None
    attrs = index_attributes(params, tile_px)
    return TileDerived(
        path=INDEX_PATH, record_shape=(params.features_per_tile, RECORD_BYTES), margin_px=MARGIN_PX,
        compute=partial(tile_features, params=params), count=lambda rec: int(np.count_nonzero(rec[:, 6])),
        attributes={"mosaicmap_reloc": attrs},
        manifest={"kind": "reloc_index", **{k: attrs[k] for k in ("format", "features_per_tile", "record_bytes")}})
