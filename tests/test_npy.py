"""Tests of flyvpr._npy: headers are checked before anything is allocated."""

import io
import tracemalloc
import warnings
import zipfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from flyvpr._npy import ArrayFileError, load_npy, npy_header, read_npz_member
from flyvpr._validation import InsufficientMemoryError


def _header_only(path, shape, descr="<f4", payload=b"\x00" * 16):
    with open(path, "wb") as fh:
        header = {"descr": descr, "fortran_order": False, "shape": shape}
        np.lib.format.write_array_header_1_0(fh, header)
        fh.write(payload)
    return path


def test_roundtrip_and_expectations(tmp_path):
    a = np.arange(12, dtype=np.int16).reshape(3, 4)
    np.save(tmp_path / "a.npy", a)
    np.testing.assert_array_equal(load_npy(tmp_path / "a.npy", dtype="int16", shape=(3, None)), a)
    assert npy_header(tmp_path / "a.npy") == ((3, 4), False, np.dtype("int16"))
    with pytest.raises(ArrayFileError, match="expected dtype float32"):
        load_npy(tmp_path / "a.npy", dtype="float32")
    with pytest.raises(ArrayFileError, match=r"expected shape \(4, \*\)"):
        load_npy(tmp_path / "a.npy", shape=(4, None))
    f = np.asfortranarray(np.arange(6.0).reshape(2, 3))
    np.save(tmp_path / "f.npy", f)
    np.testing.assert_array_equal(load_npy(tmp_path / "f.npy"), f)


def test_header_claiming_a_huge_array_costs_nothing(tmp_path):
    path = _header_only(tmp_path / "huge.npy", (10**6, 10**6), "|b1")
    tracemalloc.start()
    try:
        with pytest.raises(ArrayFileError, match=r"huge\.npy.*holds 16 bytes"):
            load_npy(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1 << 20  # refused from the header: nothing near 10**12 bytes was allocated


def test_honest_but_too_large_array_refused_by_memory(tmp_path, monkeypatch):
    np.save(tmp_path / "a.npy", np.zeros(1000, np.float64))
    monkeypatch.setenv("FLYVPR_MAX_MEMORY", "4k")
    with pytest.raises(InsufficientMemoryError, match=r"a\.npy.*8 kB.*4.1 kB"):
        load_npy(tmp_path / "a.npy")


def test_truncated_and_pickled(tmp_path):
    np.save(tmp_path / "a.npy", np.arange(100.0))
    data = (tmp_path / "a.npy").read_bytes()
    (tmp_path / "a.npy").write_bytes(data[:-8])
    with pytest.raises(ArrayFileError, match="truncated"):
        load_npy(tmp_path / "a.npy")
    np.save(tmp_path / "o.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(ArrayFileError, match="pickle"):
        load_npy(tmp_path / "o.npy")


def _npz(members, compression=zipfile.ZIP_STORED):
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression) as zf:
        for name, arr in members.items():
            with zf.open(name + ".npy", "w") as fh:
                np.lib.format.write_array(fh, arr)
    buf.seek(0)
    return zipfile.ZipFile(buf)


def test_npz_members(tmp_path):
    zf = _npz({"a": np.arange(5, dtype=np.uint8)})
    np.testing.assert_array_equal(read_npz_member(zf, "a", "f.npz"), np.arange(5))
    with pytest.raises(ArrayFileError, match="missing entry 'b'"):
        read_npz_member(zf, "b", "f.npz")
    compressed = _npz({"a": np.zeros(10)}, zipfile.ZIP_DEFLATED)
    with pytest.raises(ArrayFileError, match="compressed"):
        read_npz_member(compressed, "a", "f.npz")


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=st.binary(max_size=300))
def test_random_bytes_never_escape_as_anything_but_a_clear_error(tmp_path, data):
    path = tmp_path / "r.npy"
    path.write_bytes(data)
    try:
        load_npy(path)
    except ArrayFileError as exc:
        assert "r.npy" in str(exc)


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=st.binary(min_size=1, max_size=200), at=st.integers(0, 200))
def test_random_header_bytes(tmp_path, data, at):
    path = tmp_path / "a.npy"
    np.save(path, np.arange(10.0))
    raw = bytearray(path.read_bytes())
    raw[at : at + len(data)] = data  # overwrite part of the header (and maybe data)
    path.write_bytes(bytes(raw))
    try:
        out = load_npy(path)
    except ArrayFileError as exc:
        assert "a.npy" in str(exc)
    else:
        assert out.nbytes <= len(raw)


def test_a_header_with_stray_escapes_is_refused_without_python_warnings(tmp_path):
    path = tmp_path / "a.npy"
    np.save(path, np.arange(10.0))
    raw = path.read_bytes()
    start = raw.index(b"{")
    bad = raw[:start] + b"{'descr': '\\=<f8'" + raw[start + 17 :]
    path.write_bytes(bad)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(ArrayFileError, match="a.npy"):
            load_npy(path)
    assert [str(w.message) for w in caught] == []
