"""links.csv: what register writes and optimize reads back (pipeline.links), and the
streamed atomic text writer under it (pipeline.fsutil)."""

from __future__ import annotations

import copy
import math
import pickle
from pathlib import Path

import numpy as np

from pipeline.fsutil import copy_file_atomic, write_text_atomic
from pipeline.links import (ExtraColumns, Link, TableLink, link_arrays, read_link_gains, read_links, table_links,
                            write_links)

EXTRA = ("iterations", "radius_px", "peak_ncc", "rotation", "note", "residual_px")


def _links() -> list[Link]:
    cov = np.array([[1e-10, 2e-12, -3e-12], [2e-12, 4e-10, 5e-11], [-3e-12, 5e-11, 6e-9]])
    texts = [
        # the kinds of values an extra column holds: ints, floats as repr writes them, nan,
        # words, empty; and text that only looks like a number (kept as written)
        {"iterations": 5, "radius_px": 5.35, "peak_ncc": math.nan, "rotation": "measured", "note": "",
         "residual_px": 1.25e-05},
        {"iterations": "007", "radius_px": "1.50", "peak_ncc": "-0", "rotation": "prior", "note": "a, \"b\"",
         "residual_px": "inf"},
    ]
    out = []
    for k, extra in enumerate(texts):
        out.append(Link(k, k + 1, np.array([0.1, -2e-6, 3e-5]) * (k + 1), cov * (k + 1), 0.99, 0.9, 0.8, 1000 + k,
                        "correlation", "accepted" if k == 0 else "rejected", "" if k == 0 else "low NCC: 0.2",
                        dict(extra), gain=1.0 + k / 10))
    return out


def test_read_links_gives_back_what_was_written_and_writes_the_same_bytes(tmp_path: Path):
    links = _links()
    write_links(tmp_path / "a.csv", links, EXTRA)
    back = read_links(tmp_path / "a.csv")
    assert len(back) == len(links)
    for lk, bk in zip(links, back):
        assert (bk.a, bk.b, bk.status, bk.reason, bk.method, bk.inliers) == (lk.a, lk.b, lk.status, lk.reason,
                                                                            lk.method, lk.inliers)
        np.testing.assert_array_equal(bk.rel, lk.rel)
        np.testing.assert_array_equal(bk.cov, lk.cov)
        assert bk.cov.shape == (3, 3) and bk.rel.shape == (3,)
        assert isinstance(bk, TableLink) and bk._tab is back[0]._tab  # rows of one table, not arrays of their own
        assert bk.gain == lk.gain and bk.ncc == lk.ncc
    # numbers come back as numbers, words and number-like text as the text written
    assert back[0].extra["iterations"] == 5 and isinstance(back[0].extra["iterations"], int)
    assert back[0].extra["radius_px"] == 5.35 and back[0].extra["residual_px"] == 1.25e-05
    assert math.isnan(back[0].extra["peak_ncc"])
    assert back[0].extra["rotation"] == "measured" and back[0].extra["note"] == ""
    assert back[1].extra["iterations"] == "007" and back[1].extra["radius_px"] == "1.50"
    assert back[1].extra["peak_ncc"] == "-0" and back[1].extra["residual_px"] == math.inf
    assert back[1].extra["note"] == 'a, "b"'
    write_links(tmp_path / "b.csv", back, EXTRA)
    assert (tmp_path / "b.csv").read_bytes() == (tmp_path / "a.csv").read_bytes()


def test_table_links_are_the_links_as_their_file_gives_them_back(tmp_path: Path):
    links = _links()
    links.append(Link(7, 9, np.array([1.0, 2.0, 0.5]), np.eye(3), 0.5, 0.1, 0.3, 12, "features", "accepted", "",
                      {"iterations": 2, "rotation": "12"}, log_scale=0.01, cov4=np.eye(4) * 2.0))
    held = table_links(links)
    assert table_links([]) == []
    assert all(isinstance(lk, TableLink) and lk._tab is held[0]._tab for lk in held)  # rows of one table
    for lk, h in zip(links, held):
        assert (h.a, h.b, h.inliers, h.method, h.status, h.reason, h.gain, h.ncc, h.uniqueness, h.overlap) == (
            lk.a, lk.b, lk.inliers, lk.method, lk.status, lk.reason, lk.gain, lk.ncc, lk.uniqueness, lk.overlap)
        np.testing.assert_array_equal(h.rel, lk.rel)
        np.testing.assert_array_equal(h.cov, lk.cov)
        assert h.log_scale == lk.log_scale and (h.cov4 is lk.cov4)
        assert set(h.extra) == set(lk.extra)
    # extras that read back as themselves become text; a comma, or a word that spells a
    # number ("12" would read back as 12), keeps the dict as made
    assert isinstance(held[0].extra, ExtraColumns) and held[0].extra["iterations"] == 5
    assert math.isnan(held[0].extra["peak_ncc"]) and held[0].extra["rotation"] == "measured"
    assert held[1].extra is links[1].extra and held[2].extra is links[2].extra
    for extra in (EXTRA, ()):
        write_links(tmp_path / "made.csv", links, extra)
        write_links(tmp_path / "held.csv", held, extra)
        assert (tmp_path / "held.csv").read_bytes() == (tmp_path / "made.csv").read_bytes()
    held[0].status, held[0].reason = "rejected", "outlier"  # (what the revisits' solves do)
    held[0].extra["residual_px"] = 2.5
    assert held[0].status == "rejected" and held[0].extra["residual_px"] == 2.5
    assert links[0].status == "accepted" and links[0].extra["residual_px"] == 1.25e-05  # (the links as made untouched)


def test_a_table_link_reads_and_writes_its_row_and_travels_as_a_plain_link(tmp_path: Path):
    write_links(tmp_path / "a.csv", _links() * 3000, EXTRA)  # (more rows than the table starts with)
    back = read_links(tmp_path / "a.csv")
    assert len(back) == 6000 and len(back[0]._tab.ncc) == 6000
    lk, other = back[0], back[2]
    lk.cov = lk.cov * 4.0  # (what the calibration of the covariances does)
    np.testing.assert_array_equal(lk.cov, _links()[0].cov * 4.0)
    np.testing.assert_array_equal(other.cov, _links()[0].cov)  # the other rows are untouched
    lk.rel[2] = 0.5  # into the row, as into a link's own array
    lk.gain = 2.0
    assert lk.rel[2] == 0.5 and lk.gain == 2.0 and isinstance(lk.ncc, float)
    moved = lk.with_ends(10, 11)  # a renumbering shares the measurement (as replace shares the arrays)
    assert (moved.a, moved.b) == (10, 11) and moved.rel[2] == 0.5 and moved.inliers == lk.inliers == 1000
    moved.cov = np.eye(3)
    np.testing.assert_array_equal(lk.cov, np.eye(3))
    moved.extra["residual_px"] = 3.5  # ... and the extras (as the one dict a renumbered Link shares)
    assert lk.extra["residual_px"] == 3.5 and other.extra["residual_px"] == 1.25e-05
    moved.status = "rejected"  # (but not the status: each link's own)
    assert lk.status == "accepted" and type(lk.a) is int and type(lk.inliers) is int
    assert back[0].b is back[4].b  # one int object per frame
    own = table_links([Link(5, 6, lk.rel, lk.cov, lk.ncc, lk.uniqueness, lk.overlap, 7, "features", extra={"k": 1})])[0]
    own.cov = np.zeros((3, 3))  # a link of its own row
    np.testing.assert_array_equal(lk.cov, np.eye(3))
    assert (own.a, own.inliers, own.rel[2], dict(own.extra)) == (5, 7, 0.5, {"k": 1})
    for plain in (pickle.loads(pickle.dumps(lk)), copy.copy(lk)):
        assert type(plain) is Link and plain.cov.flags.owndata
        assert (plain.a, plain.b, plain.gain, plain.status) == (lk.a, lk.b, 2.0, lk.status)
        np.testing.assert_array_equal(plain.rel, lk.rel)


def test_an_empty_links_file_has_its_header_and_reads_as_no_links(tmp_path: Path):
    write_links(tmp_path / "e.csv", [], EXTRA)
    assert (tmp_path / "e.csv").read_text().count("\n") == 1
    assert read_links(tmp_path / "e.csv") == []


def test_write_text_atomic_takes_pieces_and_leaves_no_temporary(tmp_path: Path):
    path = tmp_path / "sub" / "t.txt"
    write_text_atomic(path, (f"line {i}\n" for i in range(3)))
    assert path.read_text() == "line 0\nline 1\nline 2\n"
    write_text_atomic(path, "whole\n")
    assert path.read_text() == "whole\n"
    assert sorted(p.name for p in path.parent.iterdir()) == ["t.txt"]


def test_copy_file_atomic_copies_the_bytes_and_leaves_no_temporary(tmp_path: Path):
    src = tmp_path / "links.csv"
    src.write_bytes(b"a,b\n" + b"1,2\n" * 100_000)
    copy_file_atomic(src, tmp_path / "out" / "links.csv")
    copy_file_atomic(src, tmp_path / "out" / "links.csv")  # (over an earlier copy)
    assert (tmp_path / "out" / "links.csv").read_bytes() == src.read_bytes()
    assert [p.name for p in (tmp_path / "out").iterdir()] == ["links.csv"]


def test_link_arrays_gathers_a_tables_rows_and_plain_links_alike(tmp_path: Path):
    write_links(tmp_path / "a.csv", _links() * 3, EXTRA)
    back = read_links(tmp_path / "a.csv")
    back[1].cov = back[1].cov * 2.0  # (a row changed in place is what is gathered)
    picked = [back[4], back[1], back[1].with_ends(7, 8)]  # rows out of order, one renumbered
    plain = [copy.copy(lk) for lk in picked]
    for links in (picked, plain, picked[:1] + [copy.copy(picked[1])] + picked[2:]):  # (a mixed list: per link)
        a, b, rel, cov = link_arrays(links)
        assert a.dtype == b.dtype == np.int64 and rel.shape == (3, 3) and cov.shape == (3, 3, 3)
        np.testing.assert_array_equal(a, [0, 1, 7])
        np.testing.assert_array_equal(b, [1, 2, 8])
        np.testing.assert_array_equal(rel, [lk.rel for lk in plain])
        np.testing.assert_array_equal(cov, [lk.cov for lk in plain])
        np.testing.assert_array_equal(cov[1], _links()[1].cov * 2.0)
    a, b, rel, cov = link_arrays([])
    assert a.shape == b.shape == (0,) and rel.size == cov.size == 0


def test_read_link_gains_gives_the_links_ends_gains_and_statuses(tmp_path: Path):
    links = _links()
    links[1].gain = math.nan
    links.append(Link(-1, 3, np.zeros(3), np.eye(3), 0.9, 0.9, 0.5, 10, "correlation", gain=0.8))  # a map link
    write_links(tmp_path / "l.csv", links, EXTRA)
    a, b, gain, accepted = read_link_gains(tmp_path / "l.csv")
    assert a.tolist() == [0, 1, -1] and b.tolist() == [1, 2, 3] and a.dtype == np.int64
    assert gain[0] == 1.0 and math.isnan(gain[1]) and gain[2] == 0.8
    assert accepted.tolist() == [True, False, True]
    write_links(tmp_path / "e.csv", [])
    assert [len(x) for x in read_link_gains(tmp_path / "e.csv")] == [0, 0, 0, 0]


def test_extra_columns_stay_text_until_set_and_read_like_a_dict(tmp_path: Path):
    links = _links()
    write_links(tmp_path / "a.csv", links, EXTRA)
    plain, quoted = read_links(tmp_path / "a.csv")
    # a row of plain fields keeps its text; one with a quoted field (comma, quote) a dict
    assert isinstance(plain.extra, ExtraColumns) and isinstance(quoted.extra, dict)
    assert list(plain.extra) == list(EXTRA) and len(plain.extra) == len(EXTRA)
    assert plain.extra.get("rotation") == "measured" and plain.extra.get("missing", "x") == "x"
    assert plain.extra["iterations"] == 5 and "note" in plain.extra and "missing" not in plain.extra
    assert repr(dict(plain.extra)) == repr({k: plain.extra[k] for k in EXTRA})  # (nan != nan)
    # setting a value (optimize's residuals) turns it into a dict of the same values plus it
    plain.extra["mahalanobis"] = 2.5
    plain.extra["residual_px"] = 0.5
    assert len(plain.extra) == len(EXTRA) + 1 and plain.extra["iterations"] == 5
    assert plain.extra["residual_px"] == 0.5 and plain.extra["mahalanobis"] == 2.5
    del plain.extra["note"]
    assert "note" not in plain.extra
    write_links(tmp_path / "b.csv", [plain], EXTRA + ("mahalanobis",))
    again = read_links(tmp_path / "b.csv")[0]
    assert again.extra["residual_px"] == 0.5 and again.extra["mahalanobis"] == 2.5 and again.extra["note"] == ""
