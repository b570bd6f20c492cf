"""Faults of the input files, each refused by ``rt.load`` with a ``DataError`` naming the file (exit 2 from the
command line, one line on stderr): a sample time the file states (a stored scalar, a time column) that
contradicts the one given or the scenario's, a time column that does not step uniformly, an ``.npz`` array whose
header does not describe its data or that would not fit in memory (a zip bomb), a ``Recording`` whose column
names do not match its values, and values too large for float64 arithmetic to square."""

import math
import zipfile

import numpy as np
import pytest
import scipy.io

import rcotorch as rt
import rcotorch.data.recording as recording
from rcotorch.run.cli import main
from rcotorch.run.runner import Run

SILVERBOX_TS = 2 ** 14 / 1e7
QUICK = ["--quiet", "--no-figures"]


def _csv(tmp_path, header, rows, name="d.csv"):
    path = tmp_path / name
    path.write_text(header + "\n" + "".join(",".join(r) + "\n" for r in rows), encoding="utf-8")
    return path


def _one_line(err: str) -> str:
    assert err.count("\n") == 1 and "Traceback" not in err and "Warning" not in err, err
    return err


# --- the sample time a file states -------------------------------------------------------------------------------
def test_a_stored_sample_time_that_contradicts_dt_is_refused_naming_file_values_and_where(tmp_path):
    npz = tmp_path / "x.npz"
    np.savez(npz, w=np.arange(5.0), y=np.ones(5), Ts=0.01)
    with pytest.raises(rt.DataError) as e:
        rt.load(npz, dt=0.02)
    msg = str(e.value)
    assert str(npz) in msg and "dt=0.02" in msg and "0.01 s" in msg and "scalar 'Ts'" in msg, msg
    assert rt.load(npz).dt == 0.01                                  # no dt given: the file's own
    assert rt.load(npz, dt=0.01).dt == 0.01
    mat = tmp_path / "x.mat"
    scipy.io.savemat(mat, {"w": np.arange(5.0), "sample_time": 0.002})
    with pytest.raises(rt.DataError, match=r"x\.mat: dt=0\.001 contradicts .* 0\.002 s \(its scalar 'sample_time'\)"):
        rt.load(mat, dt=0.001)
    assert rt.load(mat).dt == 0.002
    # Stored in single precision, 0.01 is still 0.01; two names that disagree are a fault of the file.
    np.savez(npz, w=np.arange(5.0), dt=np.float32(0.01))
    assert rt.load(npz).dt == 0.01 and rt.load(npz, dt=0.01).dt == 0.01
    np.savez(npz, w=np.arange(5.0), Ts=0.01, dt=0.001)
    with pytest.raises(rt.DataError, match=r"the file states two sample times, 0\.01 s \(its scalar 'Ts'\) and "
                                           r"0\.001 s \(its scalar 'dt'\)"):
        rt.load(npz)
    np.savez(npz, w=np.arange(5.0), Ts=0.0)
    with pytest.raises(rt.DataError, match=r"x\.npz: the file states the sample time Ts = 0\.0, which is not "
                                           r"positive"):
        rt.load(npz)


@pytest.mark.parametrize("header,scale", [("time [s]", 1.0), ("t", 1.0), ("Time (ms)", 1e3)])
def test_a_time_column_that_steps_1_ms_while_dt_is_0_01_is_refused(tmp_path, header, scale):
    rows = [(f"{k * 1e-3 * scale:.6g}", f"{math.sin(k / 7):.6f}") for k in range(50)]
    path = _csv(tmp_path, f"{header},w", rows)
    with pytest.raises(rt.DataError) as e:
        rt.load(path, dt=0.01)
    msg = str(e.value)
    assert str(path) in msg and "dt=0.01" in msg and "0.001 s" in msg and f"time column {header!r}" in msg, msg
    assert "rows 0 to 49" in msg
    # Read even where only other columns are asked for; without dt the file's own is used.
    with pytest.raises(rt.DataError, match=r"dt=0\.01 contradicts"):
        rt.load(path, columns=["w"], dt=0.01)
    assert rt.load(path, columns=["w"]).dt == 0.001
    assert rt.load(path, columns=["w"], dt=0.001).dt == 0.001


def test_a_non_uniform_time_column_is_refused_naming_the_first_row_whose_step_differs(tmp_path):
    k = [i for i in range(60) if i != 38]                           # row 38 of the file is t = 0.039 s
    path = _csv(tmp_path, "time [s],w,y", [(f"{i * 1e-3:.3f}", "1", "2") for i in k])
    for kwargs in ({}, {"dt": 0.001}, {"columns": ["w"]}):
        with pytest.raises(rt.DataError) as e:
            rt.load(path, **kwargs)
        msg = str(e.value)
        assert str(path) in msg and "row 38 (0-based data row), time column 'time [s]'" in msg, msg
        assert "0.037 s to 0.039 s" in msg
    # Only the rows loaded are checked.
    assert rt.load(path, rows=(0, 38)).dt == 0.001
    # A repeated time, a time going back, a missing time.
    rows = [(f"{i * 0.01:.2f}", "1") for i in range(10)]
    for r, bad in ((4, "0.03"), (7, "0.00"), (5, "")):
        path = _csv(tmp_path, "t,w", rows[:r] + [(bad, "1")] + rows[r + 1:], name=f"bad{r}.csv")
        with pytest.raises(rt.DataError, match=rf"bad{r}\.csv: row {r} \(0-based data row\), time column 't'"):
            rt.load(path)
    path = _csv(tmp_path, "t,w", rows[::-1], name="back.csv")
    with pytest.raises(rt.DataError, match=r"back\.csv: time column 't' does not increase"):
        rt.load(path)


def test_a_time_column_written_with_few_significant_digits_passes(tmp_path):
    n = 2000
    t = np.arange(n) * SILVERBOX_TS
    for fmt in ("{:.4f}", "{:.5g}", "{:.3e}", "{!r}"):
        path = _csv(tmp_path, "time [s],V1,V2", [(fmt.format(float(x)), "0", "1") for x in t], name="few.csv")
        rec = rt.load(path, dt=SILVERBOX_TS)
        assert rec.dt == SILVERBOX_TS
        assert abs(rt.load(path).dt - SILVERBOX_TS) <= 1e-4 * SILVERBOX_TS, fmt        # to the digits written
    # Whole milliseconds written as integers, and a time column stored in single precision.
    path = _csv(tmp_path, "t [ms],w", [(str(i), "0") for i in range(100)], name="ms.csv")
    assert rt.load(path).dt == 0.001
    npz = tmp_path / "f32.npz"
    np.savez(npz, t=(np.arange(100_000) * 1e-3).astype(np.float32), w=np.zeros(100_000))
    assert rt.load(npz, dt=1e-3).dt == 1e-3
    assert rt.load(npz).dt == 1e-3


def test_a_time_column_of_clock_times_is_left_unread(tmp_path):
    path = _csv(tmp_path, "time,w", [(f"12:00:0{i}", "1") for i in range(5)])
    rec = rt.load(path, columns=["w"], dt=0.5)
    assert rec.dt == 0.5 and rec.columns == ["w"]
    with pytest.raises(rt.DataError, match=r"row 0 \(0-based data row\), column 'time': '12:00:00' is not a number"):
        rt.load(path)


def test_the_silverbox_scenario_refuses_a_file_whose_sample_time_contradicts_its_Ts(tmp_path, capsys):
    npz = tmp_path / "x.npz"
    np.savez(npz, V1=np.zeros(200), V2=np.zeros(200), Ts=0.001)
    with pytest.raises(rt.DataError) as e:
        Run("silverbox-cubic-stiffness", out=tmp_path / "run", overrides={"data": str(npz)})
    msg = str(e.value)
    assert msg.startswith("scenario 'silverbox-cubic-stiffness': ") and str(npz) in msg, msg
    assert "0.001 s (its scalar 'Ts')" in msg and "setting Ts is 0.0016384 s" in msg and "--set Ts=0.001" in msg
    assert main(["run", "silverbox-cubic-stiffness", "--set", f"data={npz}", "--out", str(tmp_path / "cli"),
                 *QUICK]) == 2
    err = _one_line(capsys.readouterr().err)
    assert str(npz) in err and "setting Ts is 0.0016384 s" in err
    assert not (tmp_path / "cli").exists()


# --- the size an .npz file declares ------------------------------------------------------------------------------
def _npy_header(shape, descr="<f8") -> bytes:
    """A version 1.0 .npy header declaring ``shape`` (padded to 64 bytes, as numpy writes it)."""
    text = repr({"descr": descr, "fortran_order": False, "shape": tuple(shape)})
    text += " " * (-(10 + len(text) + 1) % 64) + "\n"
    return b"\x93NUMPY\x01\x00" + len(text).to_bytes(2, "little") + text.encode("latin1")


def test_an_npz_header_that_claims_ten_billion_samples_is_refused_before_reading(tmp_path, monkeypatch, capsys):
    path = tmp_path / "liar.npz"
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("w.npy", _npy_header((10 ** 10,)) + np.arange(16.0).tobytes())
        z.writestr("Ts.npy", _npy_header(()) + np.float64(0.01).tobytes())

    def no_reading(*args, **kwargs):
        raise AssertionError("the arrays were read")

    monkeypatch.setattr(np, "load", no_reading)
    with pytest.raises(rt.DataError) as e:
        rt.load(path)
    msg = str(e.value)
    assert str(path) in msg and "array 'w'" in msg and "(10000000000,)" in msg and "float64" in msg, msg
    assert "80 GB" in msg and "128 bytes" in msg and "does not describe" in msg
    assert main(["run", "silverbox-cubic-stiffness", "--set", f"data={path}", "--out", str(tmp_path / "cli"),
                 *QUICK]) == 2
    assert "array 'w' declares shape (10000000000,)" in _one_line(capsys.readouterr().err)
    assert not (tmp_path / "cli").exists()


def test_an_npz_that_inflates_beyond_memory_is_refused_naming_array_and_sizes(tmp_path, monkeypatch):
    path = tmp_path / "bomb.npz"
    np.savez_compressed(path, y=np.zeros(2_000_000), w=np.zeros(2_000_000))    # 32 MB in about 31 kB
    assert path.stat().st_size < 100_000
    monkeypatch.setattr(recording, "available_memory", lambda: (5_000_000, "MemAvailable"))
    with pytest.raises(rt.DataError) as e:
        rt.load(path)
    msg = str(e.value)
    assert str(path) in msg and "array 'y'" in msg and "(2000000,)" in msg and "16 MB uncompressed" in msg, msg
    assert "kB in the file" in msg and "more than the 5 MB of memory available" in msg
    monkeypatch.setattr(recording, "available_memory", lambda: (10 ** 9, "MemAvailable"))
    assert rt.load(path).values.shape == (2_000_000, 2)


def test_the_memory_available_is_known_on_this_machine():
    found = recording.available_memory()
    assert found is None or (isinstance(found[0], int) and found[0] > 0 and found[1])


# --- the arguments of a Recording --------------------------------------------------------------------------------
def test_a_recording_refuses_column_names_that_do_not_match_its_values():
    with pytest.raises(rt.DataError, match=r"recording: 2 column names \['a', 'b'\] for the 3 columns of values of "
                                           r"shape \(10, 3\)"):
        rt.Recording(np.zeros((10, 3)), ["a", "b"])
    with pytest.raises(rt.DataError, match=r"rig\.csv: 4 column names .* for the 3 columns"):
        rt.Recording(np.zeros((2, 10, 3)), ["a", "b", "c", "d"], path="rig.csv")
    with pytest.raises(rt.DataError, match=r"values must be \(rows, columns\) or \(members, rows, columns\), got "
                                           r"shape \(10,\)"):
        rt.Recording(np.zeros(10), ["a"])
    with pytest.raises(rt.DataError, match=r"values must be numbers, got dtype <U1"):
        rt.Recording(np.array([["a"]]), ["a"])
    with pytest.raises(rt.DataError, match=r"column names must be strings, got \['a', 1\]"):
        rt.Recording(np.zeros((3, 2)), ["a", 1])
    with pytest.raises(rt.DataError, match=r"names the column 'a' twice"):
        rt.Recording(np.zeros((3, 2)), ["a", "a"])
    with pytest.raises(rt.DataError, match=r"the sample time dt must be .* got -1"):
        rt.Recording(np.zeros((3, 2)), ["a", "b"], dt=-1)
    for first_row in (-1, 1.5, True, "0"):
        with pytest.raises(rt.DataError, match=rf"first_row must be an integer >= 0, got {first_row!r}"):
            rt.Recording(np.zeros((3, 2)), ["a", "b"], first_row=first_row)
    with pytest.raises(rt.DataError, match=r"valid has shape \(3, 1\), values \(3, 2\)"):
        rt.Recording(np.zeros((3, 2)), ["a", "b"], valid=np.ones((3, 1), bool))
    rec = rt.Recording([[1, 2], [3, 4]], ("a", "b"), first_row=np.int64(3))
    assert rec.values.shape == (2, 2) and rec.columns == ["a", "b"] and rec.first_row == 3
    # A recording with missing samples still derives columns from its complete ones.
    valid = np.array([[True, False]] * 2)
    out = rt.Recording(rec.values, rec.columns, 1.0, valid=valid).derive(d=recording.difference("a"))
    assert out.columns == ["a", "b", "d"] and out.valid.tolist() == [[True, False, True]] * 2


# --- values too large to square ----------------------------------------------------------------------------------
def test_values_whose_square_overflows_are_refused_at_load_in_one_line(tmp_path, capsys):
    rows = [(f"{0.01 * math.sin(i):.6g}", f"{1e200 * math.cos(i) if i >= 3 else 0.1:.6g}") for i in range(400)]
    path = _csv(tmp_path, "V1,V2", rows)
    with pytest.raises(rt.DataError) as e:
        rt.load(path, on_nonfinite="skip")
    msg = str(e.value)
    assert str(path) in msg and "row 3 (0-based data row), column 'V2'" in msg and "-9.89992e+199" in msg, msg
    assert "not a finite measurement that float64 arithmetic can square" in msg and "397 such values" in msg
    assert rt.load(path, columns=["V1"]).values.shape == (400, 1)
    assert main(["run", "silverbox-cubic-stiffness", "--set", f"data={path}", "--out", str(tmp_path / "cli"),
                 *QUICK]) == 2
    err = _one_line(capsys.readouterr().err)
    assert str(path) in err and "column 'V2'" in err and "can square" in err


def test_a_linear_fit_of_data_of_extreme_scale_fails_in_one_line_without_warnings():
    """Measurements of 1e50 (below the load's limit) overflow inside the output-error optimizer: one DataError
    saying the fit failed and the data's scale, no RuntimeWarnings before it."""
    import warnings

    from rcotorch.models.identification import MassSpringDamper
    k = np.arange(3000)
    w = 0.01 * np.sin(0.1 * k)
    y = 1e50 * np.cos(0.37 * k)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(rt.DataError, match=r"output-error fit of the linear model failed .*max \|y\| = 1e\+50"):
            MassSpringDamper.fit(w, y, 0.0016384)
