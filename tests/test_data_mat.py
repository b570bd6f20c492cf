"""Loading MATLAB .mat files (scipy.io), and units carried with a recording."""


import numpy as np
import pytest
import scipy.io

import rcotorch as rt


def _mat(tmp_path, file_name="d.mat", **variables):
    path = tmp_path / file_name
    scipy.io.savemat(path, variables)
    return path


def test_mat_row_and_column_vectors_scalars_and_strings(tmp_path):
    v1, v2 = np.linspace(0, 1, 7), np.arange(7.0) ** 2
    path = _mat(tmp_path, V1=v1[None, :], V2=v2[:, None], Ts=0.01, info="bench test", i16=np.arange(7, dtype=np.int16))
    rec = rt.load(path, dt=0.01)
    assert rec.columns == ["V1", "V2", "i16"]                 # file order; the scalar and the string are metadata
    np.testing.assert_array_equal(rec.values, np.c_[v1, v2, np.arange(7.0)])
    assert rec.values.dtype == np.float64 and rec.dt == 0.01 and rec.path == str(path) and rec.valid is None
    assert rec.metadata == {"Ts": 0.01, "info": "bench test"}


def test_mat_scalars_are_metadata_kept_through_selections(tmp_path):
    path = _mat(tmp_path, w=np.arange(9.0), y=np.ones(9), Ts=np.array([[0.002]]), gain=np.int32(4), name="rig 2")
    rec = rt.load(path, columns=["y"], rows=(2, 6), dt="Ts")
    assert rec.dt == 0.002 and rec.metadata == {"Ts": 0.002, "gain": 4, "name": "rig 2"}
    assert isinstance(rec.metadata["gain"], int) and rec.rows(3, 5).metadata == rec.metadata
    with pytest.raises(rt.DataError, match=r"dt='fs' names no scalar stored in the file; its scalars are \['Ts', "
                                           r"'gain'\]"):
        rt.load(path, dt="fs")
    with pytest.raises(rt.DataError, match="sample time gain0 = 0.0 is not positive"):
        rt.load(_mat(tmp_path, "z.mat", w=np.ones(3), gain0=0.0), dt="gain0")
    npz = tmp_path / "d.npz"
    np.savez(npz, w=np.arange(4.0), y=np.ones(4), dt=0.5, label="bench")
    rec = rt.load(npz, dt="dt")
    assert rec.columns == ["w", "y"] and rec.dt == 0.5 and rec.metadata == {"dt": 0.5, "label": "bench"}


def test_mat_matrix_channels_samples_along_longer_dimension(tmp_path):
    M = np.random.default_rng(1).standard_normal((50, 3))
    rec = rt.load(_mat(tmp_path, "a.mat", y=M))
    assert rec.columns == ["y[0]", "y[1]", "y[2]"]
    np.testing.assert_array_equal(rec.values, M)
    rec = rt.load(_mat(tmp_path, "b.mat", y=M.T, u=np.ones(50)))   # signals stored as rows
    assert rec.columns == ["y[0]", "y[1]", "y[2]", "u"]
    np.testing.assert_array_equal(rec.values[:, :3], M)


def test_mat_columns_rows_and_nonfinite_by_row_and_column(tmp_path):
    w, y = np.arange(10.0), 10 * np.arange(10.0)
    y[6] = np.nan
    path = _mat(tmp_path, w=w, y=y)
    rec = rt.load(path, columns=["y", "w"], rows=(2, 5), dt=0.5)
    assert rec.columns == ["y", "w"] and rec.first_row == 2
    np.testing.assert_array_equal(rec.values, np.c_[y[2:5], w[2:5]])
    with pytest.raises(rt.DataError) as e:
        rt.load(path)
    assert str(path) in str(e.value) and "row 6" in str(e.value) and "'y'" in str(e.value)
    rec = rt.load(path, on_nonfinite="skip")
    assert rec.valid[:, 1].tolist() == [True] * 6 + [False] + [True] * 3


def test_mat_errors_are_clear(tmp_path):
    with pytest.raises(rt.DataError, match=r"different lengths.*'a': 5.*'b': 4"):
        rt.load(_mat(tmp_path, "len.mat", a=np.ones(5), b=np.ones(4)))
    with pytest.raises(rt.DataError, match=r"no numeric vector.*Ts \(scalar\).*name \(string\)"):
        rt.load(_mat(tmp_path, "none.mat", Ts=0.1, name="x"))
    cube = np.zeros((4, 5, 6))
    path = _mat(tmp_path, "cube.mat", u=np.ones(5), c=cube, s={"gain": 2.0, "sig": np.ones(3)},
                cel=np.array([np.ones(2), "ab"], dtype=object))
    rec = rt.load(path)
    assert rec.columns == ["u"]                                # the rest is not a signal
    with pytest.raises(rt.DataError) as e:
        rt.load(path, columns=["u", "c"])
    msg = str(e.value)
    assert "no column 'c'" in msg and "c (3-D array of shape (4, 5, 6))" in msg and "s (struct)" in msg
    assert "cel (cell)" in msg
    bad = tmp_path / "garbage.mat"
    bad.write_bytes(b"this is not a MATLAB file at all" * 10)
    with pytest.raises(rt.DataError, match="garbage.mat"):
        rt.load(bad)


def test_mat_v4_and_complex(tmp_path):
    path = tmp_path / "v4.mat"
    scipy.io.savemat(path, {"a": np.arange(4.0), "b": np.ones(4)}, format="4")
    np.testing.assert_array_equal(rt.load(path, columns=["b", "a"]).values, np.c_[np.ones(4), np.arange(4.0)])
    path = _mat(tmp_path, "cplx.mat", z=np.ones(4) * 1j, a=np.arange(4.0))
    assert rt.load(path).columns == ["a"]
    with pytest.raises(rt.DataError, match=r"z \(complex\)"):
        rt.load(path, columns=["z"])


def test_silverbox_as_mat_equals_csv(tmp_path, silverbox_csv):
    """The benchmark stores V1, V2 as row vectors in its .mat files; a .mat written that way loads like the CSV."""
    csv = rt.load(silverbox_csv, rows=(40650, 40750))
    path = _mat(tmp_path, V1=csv.column("V1")[None, :], V2=csv.column("V2")[None, :], fs=1e7 / 2 ** 14)
    mat = rt.load(path, columns=["V1", "V2"])
    np.testing.assert_array_equal(mat.values, csv.values)


def test_units_given_parsed_from_csv_header_and_kept_by_splits(tmp_path):
    path = tmp_path / "u.csv"
    path.write_text("time [s],force [N],disp\n0,1,2\n1,3,4\n2,5,6\n")
    rec = rt.load(path)
    assert rec.columns == ["time", "force", "disp"]
    assert rec.units == {"time": "s", "force": "N"} and rec.unit("force") == "N" and rec.unit("disp") is None
    rec = rt.load(path, columns=["disp", "force"], units={"disp": "mm"}, rows=(1, 3))
    assert rec.units == {"force": "N", "disp": "mm"}            # only the kept columns; given units added
    assert rec.rows(2, 3).units == rec.units and rec.unit(0) == "mm"
    assert rt.load(path, units={"force": "kN"}).unit("force") == "kN"   # units= overrides the header
    with pytest.raises(rt.DataError, match=r"units given for unknown column\(s\) \['speed'\]"):
        rt.load(path, units={"speed": "m/s"})
    blk = rt.Recorded(rt.load(path), {"w": "force", "y": "disp"})       # playback by the bare name
    blk.reset(1)
    assert blk.step()["w"].item() == 1.0
    # Splitting would make two names equal: the headers stay as they are.
    path.write_text("x [m],x [mm]\n1,1000\n")
    rec = rt.load(path)
    assert rec.columns == ["x [m]", "x [mm]"] and rec.units == {}


def test_units_on_npz_and_mat(tmp_path):
    np.savez(tmp_path / "v.npz", w=np.ones(3), y=np.zeros(3))
    assert rt.load(tmp_path / "v.npz", units={"w": "V"}).units == {"w": "V"}
    path = _mat(tmp_path, w=np.ones(3), y=np.zeros(3))
    assert rt.load(path, units={"y": "V"}, columns=["y"]).unit("y") == "V"
