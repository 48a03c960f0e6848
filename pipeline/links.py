"""Pairwise registration links: the record ``register`` writes and ``optimize`` reads.

Frames are numbered globally over the frames store: the frames of ``log000`` first, then
``log001``..., each log's frames in store order. A link says where frame ``b`` lies in
frame ``a``'s frame: ``rel = ⊖pose_a ⊕ pose_b`` (:func:`mapstore.grid.se2_between`), in
metres and radians, with its covariance and the quality figures it was accepted on.

With ``[optimize] pose_model = "similarity2"`` a link also carries the relative scale:
``log_scale = log(s_b / s_a)`` (one pixel of b spans ``exp(log_scale)`` pixels of a, the
frames' scales ``s`` as in ``poses.csv``) and the 4 x 4 covariance of ``(rel, log_scale)``;
``rel``'s translation is then in frame a's *nominal* metres (a's pixels x the pixel size).
``links.csv`` gets the columns ``dlog_scale, cov_xs, cov_ys, cov_ts, cov_ss`` (after the
standard ones) only when some link has a scale, so rigid links files are unchanged.
"""

from __future__ import annotations

import csv
import sys
from collections.abc import MutableMapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np

from pipeline.fsutil import write_text_atomic

LINK_COLUMNS = (
    "a", "b", "dx", "dy", "dtheta",
    "cov_xx", "cov_xy", "cov_xt", "cov_yy", "cov_yt", "cov_tt",
    "ncc", "uniqueness", "overlap", "inliers", "method", "status", "reason", "gain",
)
SCALE_COLUMNS = ("dlog_scale", "cov_xs", "cov_ys", "cov_ts", "cov_ss")


@dataclass(slots=True)
class Link:
    """One registration between frames ``a`` and ``b`` (global indices).

    Attributes:
        rel: (3,) pose of b in a's frame (metres, metres, radians).
        cov: (3, 3) covariance of ``rel`` (m^2, m*rad, rad^2), from the data.
        ncc: normalized cross-correlation of the aligned overlap, [-1, 1].
        uniqueness: Kelly's (2000) C1 - C2: correlation peak minus the best competing peak.
        overlap: overlap area as a fraction of frame a's valid area.
        inliers: feature inliers (feature path) or pixels in the overlap (correlation path).
        method: "correlation" or "features".
        status: "accepted" or "rejected"; ``reason`` says why a link was rejected.
        gain: mean intensity of b over the overlap divided by a's (exposure ratio b/a),
            for the render's gain compensation.
        log_scale: log(s_b / s_a) (similarity links), None for rigid links.
        cov4: (4, 4) covariance of ``(rel, log_scale)`` (similarity links; ``cov`` is its
            upper-left block), None for rigid links.
    """

    a: int
    b: int
    rel: np.ndarray
    cov: np.ndarray
    ncc: float
    uniqueness: float
    overlap: float
    inliers: int
    method: str
    status: str = "accepted"
    reason: str = ""
    extra: MutableMapping = field(default_factory=dict)
    gain: float = 1.0
    log_scale: float | None = None
    cov4: np.ndarray | None = None

    def scale_row(self) -> list:
        """The values of :data:`SCALE_COLUMNS` (empty strings for a rigid link)."""
        if self.log_scale is None or self.cov4 is None:
            return [""] * len(SCALE_COLUMNS)
        c = self.cov4
        return [float(self.log_scale), c[0, 3], c[1, 3], c[2, 3], c[3, 3]]

    def row(self) -> list:
        c = self.cov
        return [
            self.a, self.b, *map(float, self.rel),
            c[0, 0], c[0, 1], c[0, 2], c[1, 1], c[1, 2], c[2, 2],
            self.ncc, self.uniqueness, self.overlap, self.inliers, self.method, self.status, self.reason,
            self.gain,
        ]

    def with_ends(self, a: int, b: int) -> "Link":
        """This link between frames ``a`` and ``b`` instead (a renumbering): a new link whose
        measurement is this one's (the same arrays, as :func:`dataclasses.replace` gives)."""
        return replace(self, a=a, b=b)


class _LinkTable:
    """A file's links as columns (see :class:`TableLink`): ``rel`` (L, 3), ``cov`` (L, 3, 3),
    ``ncc``, ``uniqueness``, ``overlap``, ``gain`` (L,) float64, ``inliers`` (L,) int64, and
    the extra columns: each row's text as the file spells it (``extra_text``, (L,) bytes,
    UTF-8, fields ``,``-joined, named by ``extra_cols``: name -> position) unless the row's
    extras were set or are not plain text (``extra_set``: row -> its mapping)."""

    __slots__ = ("rel", "cov", "ncc", "uniqueness", "overlap", "gain", "inliers", "extra_cols", "extra_text",
                 "extra_set")
    _COLUMNS = ("rel", "cov", "ncc", "uniqueness", "overlap", "gain", "inliers", "extra_text")

    def __init__(self, n: int, extra_cols: dict[str, int] | None = None, width: int = 1):
        self.rel = np.zeros((n, 3))
        self.cov = np.zeros((n, 3, 3))
        self.ncc = np.zeros(n)
        self.uniqueness = np.zeros(n)
        self.overlap = np.zeros(n)
        self.gain = np.ones(n)
        self.inliers = np.zeros(n, np.int64)
        self.extra_cols: dict[str, int] = {} if extra_cols is None else extra_cols
        self.extra_text = np.zeros(n, f"S{max(width, 1)}")
        self.extra_set: dict[int, MutableMapping] = {}

    def resized(self, n: int) -> "_LinkTable":
        """A table of ``n`` rows holding this one's first rows (copies; new rows zero, gain 1)."""
        out = _LinkTable(n, self.extra_cols, self.extra_text.dtype.itemsize)
        k = min(n, len(self.ncc))
        for name in self._COLUMNS:
            getattr(out, name)[:k] = getattr(self, name)[:k]
        out.extra_set = {r: v for r, v in self.extra_set.items() if r < n}
        return out

    def put_text(self, row: int, text: str) -> None:
        """Store ``row``'s extra columns as their text (widening the column for a longer one)."""
        raw = text.encode()
        width = self.extra_text.dtype.itemsize
        if len(raw) > width:  # (a few widenings per file: the rows of a file spell alike)
            self.extra_text = self.extra_text.astype(f"S{len(raw) + 16}")
        self.extra_text[row] = raw

    def put_extra(self, row: int, extra: MutableMapping) -> None:
        """``row``'s extras are ``extra`` (kept as it is, shared with whoever holds it)."""
        if not (isinstance(extra, ExtraColumns) and extra._tab is self and extra._row == row):
            self.extra_set[row] = extra

    def extra(self, row: int) -> MutableMapping:
        """``row``'s extras: the mapping set for it, else a view of its text."""
        got = self.extra_set.get(row)
        return ExtraColumns(self, row) if got is None else got


def _row_field(name: str, doc: str, kind: type | None) -> property:
    """A :class:`TableLink` field read from and stored into its row of column ``name`` (a
    Python ``kind``, float or int, or with None a view of the row)."""
    def get(self):
        v = getattr(self._tab, name)[self._row]
        return v if kind is None else kind(v)

    def put(self, value) -> None:
        getattr(self._tab, name)[self._row] = value

    return property(get, put, doc=doc)


class TableLink:
    """A :class:`Link` whose numbers and extra columns live in a row of its file's
    :class:`_LinkTable` (:func:`read_links`): it has a :class:`Link`'s fields and methods.
    A link read from a file is 333 bytes held through optimize, the table's row included
    (tracemalloc, the 48,083 links of a 20 x 20 m floor), instead of 923 with ``rel`` and
    ``cov`` as arrays of their own, four float objects and a dict of register's six
    figures, or 555 with the numbers in the row but the figures as a text object per link
    and ``a``, ``b`` and ``inliers`` as int objects of their own.
    Reading ``rel`` or ``cov`` gives a view of the row (writing into it writes the row, as
    into a link's own array); setting them or a number stores into the row. Made by
    :func:`read_links` and :func:`table_links`; pickled or copied, it is a plain :class:`Link`.
    """

    __slots__ = ("_tab", "_row", "a", "b", "method", "status", "reason", "log_scale", "cov4")

    rel = _row_field("rel", "(3,) view of the row: pose of b in a's frame (metres, metres, radians).", None)
    cov = _row_field("cov", "(3, 3) view of the row: covariance of ``rel``.", None)
    ncc = _row_field("ncc", "NCC of the aligned overlap.", float)
    uniqueness = _row_field("uniqueness", "Kelly's C1 - C2.", float)
    overlap = _row_field("overlap", "Overlap area as a fraction of frame a's valid area.", float)
    gain = _row_field("gain", "Exposure ratio b/a.", float)
    inliers = _row_field("inliers", "Feature inliers or pixels in the overlap.", int)
    extra = property(lambda self: self._tab.extra(self._row), lambda self, v: self._tab.put_extra(self._row, v),
                     doc="The link's extra columns (a mapping; see :class:`ExtraColumns`).")
    row = Link.row
    scale_row = Link.scale_row

    @classmethod
    def at(cls, tab: _LinkTable, row: int, a: int, b: int, method: str, status: str, reason: str,
           log_scale: float | None, cov4: np.ndarray | None) -> "TableLink":
        """The link of ``tab``'s row ``row`` (its numbers and extras already stored there)."""
        lk = cls.__new__(cls)
        lk._set(tab, row, a, b, method, status, reason, log_scale, cov4)
        return lk

    def _set(self, tab, row, a, b, method, status, reason, log_scale, cov4) -> None:
        self._tab, self._row = tab, row
        self.a, self.b, self.method, self.status, self.reason = a, b, method, status, reason
        self.log_scale, self.cov4 = log_scale, cov4

    def with_ends(self, a: int, b: int) -> "TableLink":
        """This link between frames ``a`` and ``b`` instead (a renumbering): a new link
        sharing this one's row (its measurement, figures and extras), as
        :meth:`Link.with_ends` shares the arrays."""
        return TableLink.at(self._tab, self._row, a, b, self.method, self.status, self.reason, self.log_scale,
                            self.cov4)

    def __reduce__(self):
        # (arrays and extras of its own: a plain link does not keep the whole table alive)
        own = {"rel": np.array(self.rel), "cov": np.array(self.cov), "extra": dict(self.extra)}
        return (Link, tuple(own.get(f.name, getattr(self, f.name)) for f in fields(Link)))

    def __repr__(self) -> str:
        return (f"TableLink(a={self.a}, b={self.b}, rel={self.rel!r}, status={self.status!r}, "
                f"reason={self.reason!r}, extra={self.extra!r})")


class ExtraColumns(MutableMapping):
    """A table link's extra columns (:class:`TableLink`): ``name -> value`` like the dict a
    new :class:`Link` holds, read from its row's text until a value is set.

    A 40 x 40 m floor has 195,000 links with six extra columns (register's figures), of
    which optimize's solves read only ``rotation``: as dicts of numbers they were ~470
    bytes a link, as a text object per link ~230, as the rows of one bytes column ~50. A
    value is parsed when asked for (:func:`_number_or_text`, as a dict would hold it); the
    first value set (optimize's residuals) gives the row a dict of its own
    (``_LinkTable.extra_set``), which every view of the row then reads.
    """

    __slots__ = ("_tab", "_row")

    def __init__(self, tab: _LinkTable, row: int):
        self._tab, self._row = tab, row

    def _fields(self) -> list[str]:
        return self._tab.extra_text[self._row].decode().split(",")

    def _dict(self) -> MutableMapping:
        tab, row = self._tab, self._row
        got = tab.extra_set.get(row)
        if got is None:
            parts = self._fields()
            got = tab.extra_set[row] = {name: _number_or_text(parts[i]) for name, i in tab.extra_cols.items()}
        return got

    def __getitem__(self, key: str):
        got = self._tab.extra_set.get(self._row)
        if got is not None:
            return got[key]
        return _number_or_text(self._fields()[self._tab.extra_cols[key]])

    def __setitem__(self, key: str, value) -> None:
        self._dict()[key] = value

    def __delitem__(self, key: str) -> None:
        del self._dict()[key]

    def __iter__(self):
        got = self._tab.extra_set.get(self._row)
        return iter(self._tab.extra_cols if got is None else got)

    def __len__(self) -> int:
        got = self._tab.extra_set.get(self._row)
        return len(self._tab.extra_cols if got is None else got)

    def __repr__(self) -> str:
        return f"ExtraColumns({dict(self.items())!r})"


def write_links(path: str | Path, links: list[Link], extra_columns: tuple[str, ...] = ()) -> None:
    """Write links as CSV (full float precision); ``extra_columns`` come from ``Link.extra``."""
    scaled = any(lk.log_scale is not None for lk in links)
    header = ",".join(LINK_COLUMNS + (SCALE_COLUMNS if scaled else ()) + extra_columns) + "\n"

    def lines():  # one at a time: the text of 185,000 links is ~75 MB
        yield header
        for lk in links:
            vals = lk.row() + (lk.scale_row() if scaled else []) + [lk.extra.get(c, "") for c in extra_columns]
            yield ",".join(_fmt(v) for v in vals) + "\n"

    write_text_atomic(path, lines())


def _fmt(v) -> str:
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    s = str(v)
    return '"' + s.replace('"', '""') + '"' if ("," in s or '"' in s) else s


def read_links(path: str | Path) -> list[Link]:
    """The links of a ``links.csv`` written by :func:`write_links`, read row by row.

    A large site has a few hundred thousand links (195,000 on a 40 x 40 m floor): rows are
    not kept as dicts, the numbers go into one table of columns (:class:`TableLink`), the
    words that repeat (method, status) are shared, the extra columns stay text until used
    (:class:`ExtraColumns`), and an extra column's number is given as the int or float it
    spells when it spells it exactly (so :func:`write_links` writes the same text back):
    ~0.6 KB per link instead of ~3 as dicts."""
    out: list[Link] = []
    with open(path, newline="") as f:
        reader = csv.reader(f)
        col = _columns(reader)
        if col is None:
            return out
        extra_cols = [(name, i) for name, i in col.items() if name not in LINK_COLUMNS and name not in SCALE_COLUMNS]
        i_cov = [col[k] for k in ("cov_xx", "cov_xy", "cov_xt", "cov_xy", "cov_yy", "cov_yt",
                                  "cov_xt", "cov_yt", "cov_tt")]
        i_rel = [col[k] for k in ("dx", "dy", "dtheta")]
        i_scale = [col[k] for k in SCALE_COLUMNS] if "dlog_scale" in col else None
        i_gain = col.get("gain")
        i_a, i_b, i_ncc, i_uniq, i_ovl = col["a"], col["b"], col["ncc"], col["uniqueness"], col["overlap"]
        i_inl, i_meth, i_stat, i_reas = col["inliers"], col["method"], col["status"], col["reason"]
        extra_at = {name: k for k, (name, _) in enumerate(extra_cols)}
        extra_idx = [i for _, i in extra_cols]
        tab = _LinkTable(4096, extra_at)
        ends: dict[int, int] = {}  # (one int object per frame, not two per link: 38,000 frames, 195,000 links)
        n = 0
        for r in reader:
            if n == len(tab.ncc):  # (the table grows by half: a file's size says little of its rows)
                tab = tab.resized(n + n // 2)
            fields_ = [r[i] for i in extra_idx]
            text = ",".join(fields_)
            if _plain_row(text, len(fields_)):
                tab.put_text(n, text)
            else:  # (a field holding a comma, quote or line break: its own dict)
                tab.extra_set[n] = {name: _number_or_text(v) for name, v in zip(extra_at, fields_)}
            cov = tab.cov[n]
            cov.flat[:] = [float(r[i]) for i in i_cov]
            tab.rel[n] = [float(r[i]) for i in i_rel]
            tab.ncc[n], tab.uniqueness[n], tab.overlap[n] = float(r[i_ncc]), float(r[i_uniq]), float(r[i_ovl])
            tab.gain[n] = float(r[i_gain] or 1.0) if i_gain is not None else 1.0
            tab.inliers[n] = int(r[i_inl])
            log_scale = cov4 = None
            if i_scale is not None and r[i_scale[0]]:
                ls, cxs, cys, cts, css = (float(r[i]) for i in i_scale)
                log_scale = ls
                cov4 = np.zeros((4, 4))
                cov4[:3, :3] = cov
                cov4[:3, 3] = cov4[3, :3] = [cxs, cys, cts]
                cov4[3, 3] = css
            a, b = int(r[i_a]), int(r[i_b])
            out.append(TableLink.at(tab, n, ends.setdefault(a, a), ends.setdefault(b, b), sys.intern(r[i_meth]),
                                    sys.intern(r[i_stat]), r[i_reas], log_scale, cov4))
            n += 1
    # every link to the final table of exactly n rows (the growing ones go)
    final = tab.resized(n)
    for lk in out:
        lk._tab = final
    return out


def table_links(links: list[Link]) -> list[Link]:
    """``links`` as rows of one new table (:class:`TableLink`), as :func:`read_links` would
    give them back from their file: the same numbers (float64), the same words, and each
    link's extra columns as text (:class:`ExtraColumns`) where that text reads back as the
    very values (ints, floats, words that do not spell a number), else as they are.

    For a stage that holds its links for a long time while making more: register holds a
    40 x 40 m floor's 195,285 links through ~20 minutes of revisits: 1,057 bytes a link as
    made (two arrays, four floats, a dict of six figures), 382 as rows of tables of 64 (a
    register task's; 552 with the figures as a text object per link), measured with
    tracemalloc on 20,000 links; the small objects' arenas that outlive
    the stage stay resident under optimize's solves. Similarity links keep their 4 x 4
    ``cov4`` as it is."""
    n = len(links)
    if n == 0:
        return []
    # (the table's extra columns: the names of the first link that has extras)
    names = next((tuple(lk.extra) for lk in links if type(lk.extra) is dict and lk.extra), ())
    tab = _LinkTable(n, {name: k for k, name in enumerate(names)})
    out: list[Link] = []
    for i, lk in enumerate(links):
        tab.rel[i], tab.cov[i] = lk.rel, lk.cov
        tab.ncc[i], tab.uniqueness[i], tab.overlap[i], tab.gain[i] = lk.ncc, lk.uniqueness, lk.overlap, lk.gain
        tab.inliers[i] = lk.inliers
        extra = lk.extra
        text = _as_text(extra.values()) if type(extra) is dict and tuple(extra) == names and names else None
        if text is not None:
            tab.put_text(i, text)
        elif not (type(extra) is dict and not extra and not names):  # (no extras: the row's empty text says so)
            tab.extra_set[i] = extra
        out.append(TableLink.at(tab, i, lk.a, lk.b, sys.intern(lk.method), sys.intern(lk.status), lk.reason,
                                lk.log_scale, lk.cov4))
    return out


def _as_text(values) -> str | None:
    """The values as one row's text, ``,``-joined as :func:`write_links` writes them, when
    :class:`ExtraColumns` reads each back as the same value (ints, floats, words that do
    not spell a number; no comma, quote or line break); else None."""
    parts = []
    for v in values:
        if type(v) is float or type(v) is int:
            parts.append(_fmt(v))
        elif type(v) is str and type(back := _number_or_text(v)) is str and back == v:
            parts.append(v)
        else:
            return None
    text = ",".join(parts)
    return text if _plain_row(text, len(parts)) else None


def _plain_row(text: str, fields: int) -> bool:
    """Whether ``text``, ``fields`` fields joined by commas, splits back into them: no field
    holds a comma, quote or line break (what :class:`ExtraColumns` keeps as text)."""
    return text.count(",") == fields - 1 and '"' not in text and "\n" not in text and "\r" not in text


def link_arrays(links: list[Link]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``links``' ends and measurements as arrays: (L,) ``a``, (L,) ``b`` (int64), (L, 3)
    ``rel`` (metres, metres, radians) and (L, 3, 3) ``cov`` (copies). Links that are rows of
    one table (:func:`read_links`) are gathered from its columns, without a view object
    per link (the optimizer's residuals over a 40 x 40 m floor's 195,285 links: 0.28
    instead of 0.64 CPU s a pass, ~12 passes); other links through their own arrays, as
    given (the caller checks the shapes)."""
    n = len(links)
    a = np.fromiter((lk.a for lk in links), np.int64, n)
    b = np.fromiter((lk.b for lk in links), np.int64, n)
    tab = getattr(links[0], "_tab", None) if n else None
    if tab is not None and all(getattr(lk, "_tab", None) is tab for lk in links):
        rows = np.fromiter((lk._row for lk in links), np.int64, n)
        return a, b, tab.rel[rows], tab.cov[rows]
    return a, b, np.array([lk.rel for lk in links], dtype=float), np.array([lk.cov for lk in links], dtype=float)


def read_link_gains(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(a, b, gain, accepted)`` of every link of a ``links.csv``: (L,) int64, int64,
    float64 and bool arrays, read row by row without making :class:`Link` objects (what the
    render's gain compensation needs of 185,000 links of a 40 x 40 m floor: 6 MB, not ~200)."""
    with open(path, newline="") as f:
        reader = csv.reader(f)
        col = _columns(reader)
        if col is None:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0), np.zeros(0, bool)
        ia, ib, ist, ig = col["a"], col["b"], col["status"], col.get("gain")
        a, b, gain, accepted = [], [], [], []
        for r in reader:
            a.append(int(r[ia]))
            b.append(int(r[ib]))
            gain.append(float(r[ig] or 1.0) if ig is not None else 1.0)
            accepted.append(r[ist] == "accepted")
    return (np.array(a, np.int64), np.array(b, np.int64), np.array(gain, float), np.array(accepted, bool))


def _columns(reader) -> dict[str, int] | None:
    """``name -> position`` from a links.csv reader's header row (None for an empty file)."""
    header = next(reader, None)
    return None if header is None else {name: i for i, name in enumerate(header)}


def _number_or_text(text: str):
    """``text`` as the int or float whose :func:`_fmt` is ``text`` (24-28 bytes instead of
    ~55 for a str), else the text itself, one str object per distinct word
    (``sys.intern``)."""
    if text[:1] in "-0123456789":
        try:
            v = int(text)
        except ValueError:
            try:
                v = float(text)
            except ValueError:
                return sys.intern(text)
            return v if repr(v) == text else text
        return v if str(v) == text else text
    if text in ("nan", "inf"):
        return float(text)
    return sys.intern(text)


def on_cycles(n: int, a, b) -> np.ndarray:
    """Which edges ``(a[i], b[i])`` of the multigraph on frames ``0..n-1`` lie on a cycle:
    (E,) bool, False for a bridge (an edge whose removal parts its two frames). Two edges
    between the same frames are a cycle. A bridge's measurement is fitted exactly by any
    solution, so its residual says nothing about the links' noise (Tarjan's low-link, an
    iterative depth-first search: O(n + E))."""
    a = np.asarray(a, int).tolist()
    b = np.asarray(b, int).tolist()
    adj: list[list[tuple[int, int]]] = [[] for _ in range(n)]
    for e, (i, j) in enumerate(zip(a, b)):
        adj[i].append((j, e))
        adj[j].append((i, e))
    order = [-1] * n  # discovery time
    low = [0] * n
    bridge = np.zeros(len(a), bool)
    clock = 0
    for root in range(n):
        if order[root] >= 0:
            continue
        order[root] = low[root] = clock
        clock += 1
        stack = [(root, -1, iter(adj[root]))]  # (frame, the edge that reached it, its edges to visit)
        while stack:
            v, via, it = stack[-1]
            for w, e in it:
                if e == via:
                    continue
                if order[w] < 0:
                    order[w] = low[w] = clock
                    clock += 1
                    stack.append((w, e, iter(adj[w])))
                    break
                low[v] = min(low[v], order[w])
            else:
                stack.pop()
                if stack:
                    u = stack[-1][0]
                    low[u] = min(low[u], low[v])
                    if low[v] > order[u]:
                        bridge[via] = True
    return ~bridge


def components(n: int, a, b) -> np.ndarray:
    """Connected components of the graph on frames ``0..n-1`` whose edges are the pairs
    ``(a[i], b[i])`` (e.g. accepted links): (n,) labels, equal for connected frames."""
    parent = np.arange(n)

    def find(i: int) -> int:
        root = i
        while parent[root] != root:
            root = parent[root]
        while parent[i] != root:
            parent[i], i = root, parent[i]
        return root

    for i, j in zip(np.asarray(a, int).tolist(), np.asarray(b, int).tolist()):
        ri, rj = find(i), find(j)
        if ri != rj:
            parent[ri] = rj
    return np.array([find(i) for i in range(n)])
