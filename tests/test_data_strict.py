"""Recorded data read strictly: sample times checked at load and against the graph's blocks, explicit
resampling, strict CSV and NPZ parsing, and the streaming CSV reader."""

import csv
import math

import numpy as np
import pytest

import rcotorch as rt
from rcotorch.data.recording import CSV_CHUNK_ROWS


def _write(tmp_path, text, name="d.csv"):
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


@pytest.mark.parametrize("dt", [0, 0.0, math.nan, math.inf, -0.01, True, "0.01x"])
def test_load_refuses_a_bad_sample_time_naming_file_and_value(tmp_path, dt):
    path = _write(tmp_path, "w,y\n1,2\n3,4\n")
    with pytest.raises(rt.DataError) as e:
        rt.load(path, dt=dt)
    assert str(path) in str(e.value) and repr(dt) in str(e.value)


def test_recording_and_block_refuse_a_bad_sample_time():
    with pytest.raises(rt.DataError, match="recording: the sample time dt must be .* got 0"):
        rt.Recording(np.ones((3, 1)), ["w"], dt=0)
    with pytest.raises(rt.DataError, match="block 'data': .* got nan"):
        rt.Recorded(np.ones((3, 1)), {"w": 0}, dt=math.nan)
    rec = rt.Recording(np.ones((3, 1)), ["w"], dt=0.01)
    with pytest.raises(rt.DataError, match=r"block 'data': dt=0.001 differs from the sample time 0.01"):
        rt.Recorded(rec, {"w": "w"}, dt=0.001)
    assert rt.Recorded(rec, {"w": "w"}, dt=0.01 * (1 + 1e-12)).dt == 0.01       # equal to rounding


def _sdof_data(tmp_path, dt, n=200):
    k = np.arange(n)
    path = _write(tmp_path, "w,y\n" + "".join(f"{math.sin(0.1 * i)!r},{math.cos(0.1 * i)!r}\n" for i in k))
    return rt.load(path, dt=dt)


def test_recording_at_another_sample_time_than_the_known_model_is_refused_at_build(tmp_path, sdof_known):
    for dt in (0.001, 0.01 * (1 + 1e-6)):
        rec = _sdof_data(tmp_path, dt)
        with pytest.raises(rt.DataError) as e:
            rt.refinement(sdof_known(0.01), rt.RCOEstimator({"y0": 1}, nc=1), nu=5,
                          data=rt.Recorded(rec, {"w": "w", "y": "y"}))
        msg = str(e.value)
        assert "'data'" in msg and "'known'" in msg and repr(dt) in msg and " 0.01 s" in msg and rec.path in msg
    # The right sample time, and a recording without one, build.
    g = rt.refinement(sdof_known(0.01), rt.RCOEstimator({"y0": 1}, nc=1), nu=5,
                      data=rt.Recorded(_sdof_data(tmp_path, 0.01 * (1 + 1e-12)), {"w": "w", "y": "y"}))
    assert g.max_steps == 200
    rt.refinement(sdof_known(0.01), rt.RCOEstimator({"y0": 1}, nc=1), nu=5,
                  data=rt.Recorded(np.ones((50, 2)), {"w": 0, "y": 1}))


def test_a_plain_graph_checks_every_block_with_a_sample_time(zoh_first_order):
    src = rt.Recorded(np.ones((20, 1)), {"out": 0}, name="src", dt=0.1)
    rt.Graph([src, zoh_first_order(0.1)], ["src.out -> lti.in"])
    src = rt.Recorded(np.ones((20, 1)), {"out": 0}, name="src", dt=0.2)
    with pytest.raises(rt.DataError, match=r"block 'src' plays recorded data sampled every 0.2 s, but block 'lti' "
                                           r"has the sample time 0.1 s.*resample=0.1"):
        rt.Graph([src, zoh_first_order(0.1)], ["src.out -> lti.in"])


def test_resample_interpolates_a_sine_onto_the_models_grid(sdof_known):
    f = 3.0                                                    # Hz
    t = np.arange(2001) * 1e-3                                 # 2 s at 1 kHz
    rec = rt.Recording(np.c_[np.sin(2 * np.pi * f * t), np.cos(2 * np.pi * f * t)], ["w", "y"], dt=1e-3)
    down = rt.Recorded(rec, {"w": "w", "y": "y"}, resample=0.01)
    assert down.dt == 0.01 and down.length == 201
    coarse = np.arange(201) * 0.01
    np.testing.assert_allclose(down.values[0, :, 0].numpy(), np.sin(2 * np.pi * f * coarse), rtol=0, atol=1e-12)
    # Between samples: 1 kHz -> 1/0.0035 s and 100 Hz -> 1 kHz, within the linear interpolation error
    # h^2 / 8 max|x''| of the coarser grid.
    for src_dt, step in ((1e-3, 3.5e-3), (1e-2, 1e-3)):
        ts = np.arange(int(2 / src_dt) + 1) * src_dt
        blk = rt.Recorded(rt.Recording(np.sin(2 * np.pi * f * ts)[:, None], ["w"], dt=src_dt), {"w": "w"},
                          resample=step)
        tn = np.arange(blk.length) * step
        assert tn[-1] <= ts[-1] + 1e-12 and tn[-1] + step > ts[-1]
        bound = src_dt ** 2 / 8 * (2 * np.pi * f) ** 2
        err = np.abs(blk.values[0, :, 0].numpy() - np.sin(2 * np.pi * f * tn)).max()
        assert err <= bound and err > bound / 10
    # The resampled block builds with the known model at its sample time.
    g = rt.refinement(sdof_known(0.01), rt.RCOEstimator({"y0": 1}, nc=1), nu=5, data=down)
    g.run(200)
    with pytest.raises(rt.DataError, match="resample=0.01 needs the recording's sample time"):
        rt.Recorded(np.ones((10, 1)), {"w": 0}, resample=0.01)
    with pytest.raises(rt.DataError, match="resample: the sample time dt must be"):
        rt.Recorded(rec, {"w": "w"}, resample=-1)


def test_resample_keeps_gaps_invalid():
    values = np.arange(10.0)[:, None]
    valid = np.ones((10, 1), bool)
    valid[4] = False
    blk = rt.Recorded(rt.Recording(values, ["w"], dt=1.0, valid=valid), {"w": "w"}, resample=0.5)
    # t = 3.5, 4, 4.5 touch the missing sample at t = 4; 3 and 5 do not.
    assert blk.length == 19 and blk.valid_mask[0, :, 0].tolist()[5:12] == [1, 1, 0, 0, 0, 1, 1]
    assert blk.values[0, :, 0].tolist()[5:12] == [2.5, 3.0, 3.0, 3.0, 3.0, 5.0, 5.5]   # held, then interpolated


def test_csv_byte_order_mark_is_dropped(tmp_path):
    path = tmp_path / "bom.csv"
    path.write_bytes(b"\xef\xbb\xbftime [s],w\r\n0,1\r\n1,2\r\n")
    rec = rt.load(path)
    assert rec.columns == ["time", "w"] and rec.units == {"time": "s"}
    np.testing.assert_array_equal(rec.values, [[0, 1], [1, 2]])


@pytest.mark.parametrize("header,match", [
    ("a,b,a", r"names the column 'a' twice \(columns 0 and 2"),
    ("x,y,x [m]", r"header columns 0 and 2 \(0-based\), 'x' and 'x \[m\]', both name the column 'x'"),
    ("x [m],y,x", r"names the column 'x' twice|both name the column 'x'"),
])
def test_csv_duplicate_or_ambiguous_column_names_are_refused(tmp_path, header, match):
    path = _write(tmp_path, header + "\n1,2,3\n")
    with pytest.raises(rt.DataError, match=match) as e:
        rt.load(path)
    assert str(path) in str(e.value)


def test_columns_asked_for_twice_are_refused(tmp_path):
    path = _write(tmp_path, "a,b\n1,2\n")
    with pytest.raises(rt.DataError, match=r"asks for the column\(s\) \['a'\] more than once"):
        rt.load(path, columns=["a", 0])
    with pytest.raises(rt.DataError, match="names no column"):
        rt.load(path, columns=[])


@pytest.mark.parametrize("field", ["1_000", "١٢", "0x10", "1,5", "1.5.2", "1d3", "--1"])
def test_csv_numbers_other_than_decimal_forms_are_refused(tmp_path, field):
    path = tmp_path / "n.csv"
    with open(path, "w", newline="", encoding="utf-8") as f:
        csv.writer(f).writerows([["a", "b"], ["1", "2"], ["3", field]])
    with pytest.raises(rt.DataError) as e:
        rt.load(path)
    msg = str(e.value)
    assert str(path) in msg and "row 1 (0-based data row), column 'b'" in msg and repr(field) in msg


def test_csv_usual_decimal_forms_and_nonfinite_policy(tmp_path):
    path = _write(tmp_path, "a\n1e-3\n-0.5\n+2\n.5\n5.\n 7 \nNaN\n-inf\n")
    rec = rt.load(path, on_nonfinite="skip")
    np.testing.assert_array_equal(rec.values[:6, 0], [1e-3, -0.5, 2, 0.5, 5, 7])
    assert np.isnan(rec.values[6, 0]) and rec.values[7, 0] == -np.inf
    assert rec.valid[:, 0].tolist() == [True] * 6 + [False] * 2
    with pytest.raises(rt.DataError, match="row 6 .*column 'a': value is missing"):
        rt.load(path)


def test_csv_that_is_not_utf8_is_refused_naming_file_and_row(tmp_path):
    path = tmp_path / "latin1.csv"
    path.write_bytes("w,y\n1,2\n\n3,4\n5,6 \xb5m\n".encode("latin-1"))
    with pytest.raises(rt.DataError) as e:
        rt.load(path)
    msg = str(e.value)
    assert str(path) in msg and "not UTF-8" in msg and "row 2 (0-based data row)" in msg and "\\xb5" in msg
    path.write_bytes("\ufeffw,y\n1,2\n".encode("utf-16"))
    with pytest.raises(rt.DataError, match="not UTF-8 text \\(the header"):
        rt.load(path)


def test_npz_complex_object_and_empty_arrays_are_refused(tmp_path):
    x = np.arange(4.0)
    np.savez(tmp_path / "c.npz", x=x, z=x + 1j * x)
    with pytest.raises(rt.DataError, match=r"c.npz: array 'z' is complex"):
        rt.load(tmp_path / "c.npz")
    np.savez(tmp_path / "o.npz", x=x, o=np.array([1.0, "a", None, 2], dtype=object))
    with pytest.raises(rt.DataError, match=r"o.npz: array 'o' holds Python objects"):
        rt.load(tmp_path / "o.npz")
    np.savez(tmp_path / "s.npz", x=x, s=np.array(["1", "2", "3", "4"]))
    with pytest.raises(rt.DataError, match=r"s.npz: array 's' has dtype <U1, not numbers"):
        rt.load(tmp_path / "s.npz")
    np.savez(tmp_path / "e.npz", x=np.array([]), y=np.array([]))
    with pytest.raises(rt.DataError, match=r"e.npz: array 'x' is empty \(shape \(0,\)\)"):
        rt.load(tmp_path / "e.npz")
    np.savez(tmp_path / "m.npz", data=np.zeros((0, 3)))
    with pytest.raises(rt.DataError, match=r"array 'data' is empty"):
        rt.load(tmp_path / "m.npz")
    with pytest.raises(rt.DataError, match=r"shape \(0, 2\)"):
        rt.Recorded(np.zeros((0, 2)), {"w": 0})


def test_files_that_are_not_npz_are_refused(tmp_path):
    import pickle
    (tmp_path / "p.npz").write_bytes(pickle.dumps({"x": [1.0, 2.0]}))
    (tmp_path / "t.npz").write_text("x,y\n1,2\n")
    np.save(tmp_path / "a.npy", np.arange(3.0))
    (tmp_path / "a.npy").rename(tmp_path / "a.npz")
    for name in ("p.npz", "t.npz", "a.npz"):
        with pytest.raises(rt.DataError, match=f"{name}: not an .npz file"):
            rt.load(tmp_path / name)


def test_streaming_csv_read_equals_the_values_of_a_plain_parse(tmp_path):
    """Several batches of rows, blank lines, trailing commas, quoted fields, CRLF: the same values as Python's
    float() of each field, only the asked-for columns stored."""
    rng = np.random.default_rng(5)
    n = 2 * CSV_CHUNK_ROWS + 17
    data = rng.standard_normal((n, 4)) * 10.0 ** rng.integers(-5, 5, (n, 4))
    path = tmp_path / "big.csv"
    with open(path, "w", newline="", encoding="utf-8") as f:
        f.write("a,b [V],c,d,\r\n")
        for i, row in enumerate(data):
            f.write(",".join(f'"{float(v)!r}"' if i % 7 == 0 else repr(float(v)) for v in row) + ",\r\n")
            if i % 1000 == 0:
                f.write("\r\n")
    rec = rt.load(path, columns=["d", "b"])
    assert rec.columns == ["d", "b"] and rec.units == {"b": "V"} and rec.values.shape == (n, 2)
    np.testing.assert_array_equal(rec.values, data[:, [3, 1]])
    np.testing.assert_array_equal(rt.load(path).values, data)
    np.testing.assert_array_equal(rt.load(path, columns=[2], rows=(n - 5, n)).values, data[-5:, [2]])
