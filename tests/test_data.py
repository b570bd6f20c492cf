"""Loading recorded data (CSV, NPZ), its checks, playback with gaps, and a Figure-1 run on data with a gap."""


import re

import numpy as np
import pytest
import torch

import rcotorch as rt


def _write(tmp_path, text, name="d.csv"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_csv_header_with_trailing_comma(tmp_path):
    path = _write(tmp_path, "a,b,\n1,2,\n3,4.5,\n-1e-3,6,\n")
    rec = rt.load(path, dt=0.5)
    assert rec.columns == ["a", "b"]
    np.testing.assert_array_equal(rec.values, [[1, 2], [3, 4.5], [-1e-3, 6]])
    assert rec.valid is None and rec.dt == 0.5 and rec.first_row == 0 and rec.path == str(path)
    np.testing.assert_array_equal(rec.column("b"), [2, 4.5, 6])


def test_csv_quoted_header_and_spaces(tmp_path):
    rec = rt.load(_write(tmp_path, '"V1","V2"\n 1.0 , 2.0\n'))
    assert rec.columns == ["V1", "V2"]
    np.testing.assert_array_equal(rec.values, [[1.0, 2.0]])


def test_csv_empty_field_is_an_error_naming_file_row_column(tmp_path):
    path = _write(tmp_path, "a,b\n1,2\n3,4\n5,\n7,8\n")
    with pytest.raises(rt.DataError) as e:
        rt.load(path)
    msg = str(e.value)
    assert str(path) in msg and "row 2" in msg and "'b'" in msg


def test_csv_nonfinite_skip_marks_invalid_and_recorded_holds(tmp_path):
    path = _write(tmp_path, "a,b\n1,2\n3,\n5,nan\n7,8\n")
    rec = rt.load(path, on_nonfinite="skip")
    np.testing.assert_array_equal(rec.valid, [[True, True], [True, False], [True, False], [True, True]])
    blk = rt.Recorded(rec, {"w": "a", "y": "b"})
    assert blk.outputs == {"w": 1, "y": 1, "valid": 1}
    blk.reset(2)
    outs = [blk.step() for _ in range(4)]
    assert [o["y"][0, 0].item() for o in outs] == [2.0, 2.0, 2.0, 8.0]     # last valid value held
    assert [o["w"][0, 0].item() for o in outs] == [1.0, 3.0, 5.0, 7.0]
    assert [o["valid"][0, 0].item() for o in outs] == [1.0, 0.0, 0.0, 1.0]
    assert outs[1]["y"].shape == (2, 1)
    with pytest.raises(rt.DataError, match="past the end"):
        blk.step()
    # Without on_nonfinite='skip' a Recorded block refuses non-finite samples.
    with pytest.raises(rt.DataError, match="non-finite"):
        rt.Recorded(np.array([[1.0, np.inf]]), {"w": 0, "y": 1})
    with pytest.raises(rt.DataError, match="on_nonfinite"):
        rt.load(path, on_nonfinite="ignore")


def test_a_recording_prints_what_it_holds_in_one_line(tmp_path):
    path = _write(tmp_path, "force [N],b\n1,2\n3,\n5,nan\n7,8\n")
    rec = rt.load(path, on_nonfinite="skip", dt=0.01)
    assert repr(rec.rows(1, 4)) == (f"Recording({str(path)!r}, 3 rows (file rows 1..3), columns force [N], b, "
                                    f"dt=0.01 s, 2 samples missing)")
    members = rt.Recording(np.zeros((3, 10, 2)), ["a", "b"])
    assert repr(members) == "Recording(10 rows x 3 members, columns a, b, dt unknown)"


def test_csv_bad_number_names_row_and_column(tmp_path):
    path = _write(tmp_path, "a,b\n1,2\n3,x4\n")
    with pytest.raises(rt.DataError) as e:
        rt.load(path)
    msg = str(e.value)
    assert str(path) in msg and "row 1" in msg and "'b'" in msg and "'x4'" in msg


def test_csv_wrong_field_count_and_empty(tmp_path):
    with pytest.raises(rt.DataError, match="row 1.*3 fields"):
        rt.load(_write(tmp_path, "a,b\n1,2\n3,4,5\n"))
    with pytest.raises(rt.DataError, match="empty"):
        rt.load(_write(tmp_path, "", "e.csv"))
    with pytest.raises(rt.DataError, match="no data rows"):
        rt.load(_write(tmp_path, "a,b\n", "h.csv"))


def test_column_selection_by_name_and_index(tmp_path):
    path = _write(tmp_path, "a,b,c\n1,2,3\n4,5,6\n")
    rec = rt.load(path, columns=["c", "a"])
    assert rec.columns == ["c", "a"]
    np.testing.assert_array_equal(rec.values, [[3, 1], [6, 4]])
    rec = rt.load(path, columns=[1])
    assert rec.columns == ["b"]
    np.testing.assert_array_equal(rec.values, [[2], [5]])
    with pytest.raises(rt.DataError, match="no column 'd'"):
        rt.load(path, columns=["d"])
    with pytest.raises(rt.DataError, match="column index 3 out of range"):
        rt.load(path, columns=[3])
    # Recorded picks columns by name or index too.
    blk = rt.Recorded(rt.load(path), {"w": "c", "y": 0, "v": ["a", "b"]})
    blk.reset(1)
    out = blk.step()
    assert out["w"].item() == 3.0 and out["y"].item() == 1.0 and out["v"].tolist() == [[1.0, 2.0]]


def test_rows_split(tmp_path):
    path = _write(tmp_path, "a,b\n" + "".join(f"{i},{10 * i}\n" for i in range(10)))
    rec = rt.load(path, rows=(3, 7))
    np.testing.assert_array_equal(rec.values[:, 0], [3, 4, 5, 6])
    assert rec.first_row == 3
    sub = rec.rows(4, 6)
    np.testing.assert_array_equal(sub.values[:, 1], [40, 50])
    assert sub.first_row == 4
    with pytest.raises(rt.DataError, match="outside"):
        rec.rows(2, 5)
    with pytest.raises(rt.DataError, match="outside"):
        rt.load(path, rows=(5, 11))
    # Rows in errors are rows of the file, not of the split.
    bad = _write(tmp_path, "a,b\n1,2\n3,4\n5,\n7,8\n", "bad.csv")
    with pytest.raises(rt.DataError, match="row 2"):
        rt.load(bad, rows=(1, 4))


def test_missing_and_unsupported_file(tmp_path):
    with pytest.raises(rt.DataError, match="no such file"):
        rt.load(tmp_path / "nope.csv")
    with pytest.raises(rt.DataError, match="unsupported"):
        rt.load(_write(tmp_path, "a\n1\n", "d.txt"))


def test_npz_dict_of_vectors_and_single_matrix(tmp_path):
    x, y = np.arange(5.0), np.arange(5.0) ** 2
    np.savez(tmp_path / "v.npz", x=x, y=y)
    rec = rt.load(tmp_path / "v.npz")
    assert rec.columns == ["x", "y"]
    np.testing.assert_array_equal(rec.values, np.c_[x, y])
    M = np.random.default_rng(0).standard_normal((6, 3))
    np.savez(tmp_path / "m.npz", data=M)
    rec = rt.load(tmp_path / "m.npz", columns=[2, 0])
    assert rec.columns == ["data[2]", "data[0]"]
    np.testing.assert_array_equal(rec.values, M[:, [2, 0]])
    np.savez(tmp_path / "bad.npz", x=x, y=y[:3])
    with pytest.raises(rt.DataError, match="different lengths"):
        rt.load(tmp_path / "bad.npz")
    np.savez(tmp_path / "bad2.npz", x=x, m=M)
    with pytest.raises(rt.DataError, match="'m' has shape"):
        rt.load(tmp_path / "bad2.npz")


def test_silverbox_file(silverbox_csv):
    rec = rt.load(silverbox_csv)
    assert rec.columns == ["V1", "V2"]
    assert rec.values.shape == (131072, 2)
    assert rec.valid is None
    np.testing.assert_array_equal(rec.values[0], [0.0057756, 0.0093978])


def test_figure1_on_data_skips_update_at_gap(tmp_path, sdof_known):
    rng = np.random.default_rng(4)
    T, gap = 60, 30
    w, y = rng.standard_normal(T), rng.standard_normal(T)
    lines = [f"{a:.17g},{b:.17g}" if k != gap else f"{a:.17g}," for k, (a, b) in enumerate(zip(w, y))]
    path = _write(tmp_path, "w,y\n" + "\n".join(lines) + "\n")
    rec = rt.load(path, on_nonfinite="skip", dt=0.1)
    data = rt.Recorded(rec, {"w": "w", "y": "y"}, name="data")
    est = rt.RCOEstimator({"y0": 1}, nc=2, p0=100.0)
    g = rt.refinement(sdof_known(0.1), est, data=data, nu=5, batch_size=2)
    assert g.sources[("identified", "valid")] == ("data", "valid")
    assert g.max_steps == T
    g.run(gap)
    theta, P = est.theta.clone(), est.P.clone()
    sig = g.step()                                              # the sample at the gap
    assert sig[("data", "valid")].flatten().tolist() == [0.0, 0.0]
    assert sig[("data", "y")].flatten().tolist() == [y[gap - 1]] * 2
    assert torch.equal(est.theta, theta) and torch.equal(est.P, P)
    g.step()                                                    # the next, valid sample updates again
    assert not torch.equal(est.theta, theta)
    assert bool(est.alive.all())
    with pytest.raises(rt.ConfigError, match="recorded data gives 60 samples"):
        g.run(T)


def test_row_numbers_agree_with_blank_lines(tmp_path):
    text = "a,b\n1,2\n\n3,{}\n5,6\n"
    assert rt.load(_write(tmp_path, text.format("4"), "ok.csv"), rows=(1, 2)).values.tolist() == [[3.0, 4.0]]
    with pytest.raises(rt.DataError, match="row 1 "):
        rt.load(_write(tmp_path, text.format(""), "gap.csv"))
    with pytest.raises(rt.DataError, match="row 1 "):                   # the same line, a bad number
        rt.load(_write(tmp_path, text.format("x"), "bad.csv"))


def test_recorded_per_member_data():
    T = 5
    data = np.stack([np.c_[np.arange(T), 10 + np.arange(T)], np.c_[-np.arange(T), 20 + np.arange(T)]])
    blk = rt.Recorded(data, {"w": 0, "y": 1}, dt=0.2)
    assert blk.max_steps == T and blk.dt == 0.2
    with pytest.raises(rt.DimensionError, match="2 members"):
        blk.reset(3)
    blk.reset(2)
    blk.step()
    out = blk.step()
    assert out["w"].flatten().tolist() == [1.0, -1.0] and out["y"].flatten().tolist() == [11.0, 21.0]


def test_the_measured_outputs_unit_comes_from_the_recording(tmp_path, sdof_known):
    """A recording whose header gives the measured column's unit labels y, z and the fits in a run of a graph
    built in Python (its figures and summary), unless the user names another."""
    from rcotorch.run.refine import GraphScenario
    rng = np.random.default_rng(5)
    rows = "\n".join(f"{a:.17g},{b:.17g}" for a, b in rng.standard_normal((40, 2)))
    rec = rt.load(_write(tmp_path, "force [N],velocity [m/s]\n" + rows + "\n"), dt=0.1)
    data = rt.Recorded(rec, {"w": "force", "y": "velocity"}, name="data")
    assert data.units == {"w": "N", "y": "m/s"}
    g = rt.refinement(sdof_known(0.1), rt.RCOEstimator({"y0": 1}, nc=1, p0=100.0), data=data, nu=5)
    assert GraphScenario(g).unit("y") == "m/s"
    assert GraphScenario(g, units={"y": "mm/s"}).unit("y") == "mm/s"
    mixed = rt.Recorded(rec, {"w": ["force", "velocity"], "y": "velocity"})
    assert mixed.units == {"y": "m/s"}                          # a port whose columns differ in unit has none


def _row_by_row(path, columns):
    """The row-by-row CSV parser's result, as ``_read_csv`` returns it."""
    import csv

    from rcotorch.data import recording as R
    with open(path, newline="", encoding="utf-8-sig") as f:
        return R._parse_csv(path, csv.reader(f), columns, R._record_bound(path))


@pytest.mark.parametrize("columns", [None, ["b"], ["c [V]", "a"]])
def test_a_plain_csv_read_in_one_pass_equals_the_row_by_row_parse(tmp_path, columns):
    """Plain numbers (17 significant digits, exponents, signs), a trailing comma on every row, CRLF line ends, a
    byte-order mark, a time column not asked for, units in the header, blank lines at the end: the one-pass
    reader gives the same names, units, values (bit for bit) and time columns as the row-by-row parser."""
    from rcotorch.data import recording as R
    rng = np.random.default_rng(3)
    v = rng.standard_normal((500, 3)) * 10.0 ** rng.integers(-12, 12, (500, 3))
    lines = ["time [ms],a,b,c [V],"] + [f"{k * 0.5},{float(x)!r},{y:+.17e},{z:.6g}," for k, (x, y, z) in enumerate(v)]
    path = tmp_path / "plain.csv"
    path.write_bytes(b"\xef\xbb\xbf" + "\r\n".join(lines).encode() + b"\r\n\r\n\n")
    cols = None if columns is None else [c.split(" [")[0] for c in columns]
    fast, slow = R._read_plain_csv(path, cols), _row_by_row(path, cols)
    assert fast is not None
    assert fast[:3] == slow[:3] and np.array_equal(fast[3], slow[3])
    assert [t[:2] for t in fast[4]] == [t[:2] for t in slow[4]]
    assert all(np.array_equal(a[2], b[2]) for a, b in zip(fast[4], slow[4]))
    rec = rt.load(path, columns=cols)
    assert np.array_equal(rec.values, slow[3])


@pytest.mark.parametrize("body", ["1,2\n3,nan\n", "1,2\n\n3,4\n", "1,2\n3,\n", "1,2\n3,4,5\n", '1,2\n"3",4\n',
                                  "1,2\n3_0,4\n", "1,2\n3,4;5\n", "1,2\n3,4\u00a0\n"])
def test_csv_text_other_than_plain_numbers_is_left_to_the_row_by_row_parser(tmp_path, body):
    """nan, a blank line inside, an empty field, an extra field, a quote, an underscore, another separator, text
    that is not ASCII: the one-pass reader declines, and ``load`` reads or refuses the file as before."""
    from rcotorch.data import recording as R
    path = tmp_path / "odd.csv"
    path.write_text("a,b\n" + body, encoding="utf-8")
    assert R._read_plain_csv(path, None) is None
    try:
        expected = _row_by_row(path, None)
    except rt.DataError as e:
        with pytest.raises(rt.DataError, match=re.escape(str(e))):
            rt.load(path, on_nonfinite="skip")
        return
    assert np.array_equal(rt.load(path, on_nonfinite="skip").values, expected[3], equal_nan=True)


def test_a_plain_csv_larger_than_the_one_pass_limit_is_read_row_by_row(tmp_path, monkeypatch):
    """The one-pass reader holds the file's text several times over: above ``PLAIN_CSV_BYTES`` it declines, so
    that a large file is read in batches, with the same values."""
    from rcotorch.data import recording as R
    path = tmp_path / "big.csv"
    path.write_text("a,b\n" + "".join(f"{k},{k * 0.25}\n" for k in range(2000)))
    assert R._read_plain_csv(path, None) is not None
    monkeypatch.setattr(R, "PLAIN_CSV_BYTES", path.stat().st_size - 1)
    assert R._read_plain_csv(path, None) is None
    assert np.array_equal(rt.load(path).values, np.c_[np.arange(2000.0), np.arange(2000.0) * 0.25])
