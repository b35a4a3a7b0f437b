"""Tests of the VPR-Bench loader: pickled ground truth is refused unless trusted."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from flyvpr.datasets import load_benchmark, load_vprbench
from flyvpr.datasets.vprbench import parse_vprbench_rows

N_REF, N_QUERY = 5, 4
ROWS = [[0, [0, 1]], [1, [1]], [2, []], [3, [3, 4]]]
EXPECTED = np.array(
    [[1, 1, 0, 0, 0], [0, 1, 0, 0, 0], [0, 0, 0, 0, 0], [0, 0, 0, 1, 1]], dtype=bool
)


def make_folder(root: Path, n_ref=N_REF, n_query=N_QUERY) -> Path:
    for sub, n in (("ref", n_ref), ("query", n_query)):
        (root / sub).mkdir(parents=True)
        for i in range(n):
            Image.fromarray(np.full((4, 4), i, np.uint8)).save(root / sub / f"{i:07d}.jpg")
    return root


def object_rows(rows, two_d=True) -> np.ndarray:
    if two_d:
        arr = np.empty((len(rows), 2), dtype=object)
        for k, (q, refs) in enumerate(rows):
            arr[k, 0], arr[k, 1] = q, refs
    else:
        arr = np.empty(len(rows), dtype=object)
        for k, row in enumerate(rows):
            arr[k] = row
    return arr


def save_pickled(root: Path, rows, two_d=True, name="ground_truth_new.npy") -> Path:
    path = root / name
    np.save(path, object_rows(rows, two_d), allow_pickle=True)
    return path


@pytest.mark.parametrize("two_d", [True, False])
def test_vprbench_pickled_refused_then_trusted(tmp_path, two_d):
    make_folder(tmp_path)
    save_pickled(tmp_path, ROWS, two_d)
    with pytest.raises(ValueError, match="ground_truth_new.npy is a pickled object array") as e:
        load_vprbench(tmp_path)
    msg = str(e.value)
    assert "execute arbitrary code" in msg and "trust_pickle=True" in msg
    assert "--trust-pickle" in msg
    b = load_vprbench(tmp_path, trust_pickle=True)
    assert (b.n_query, b.n_reference) == (N_QUERY, N_REF)
    np.testing.assert_array_equal(b.ground_truth, EXPECTED)
    assert [p.name for p in b.reference.paths] == [f"{i:07d}.jpg" for i in range(N_REF)]
    assert b.protocol()["tolerance"] == {"ground_truth_file": "ground_truth_new.npy"}
    assert b.dataset == "vprbench"


def test_vprbench_refusal_never_unpickles(tmp_path):
    marker = tmp_path / "pwned"

    class Payload:
        def __reduce__(self):
            return (open, (str(marker), "w"))

    make_folder(tmp_path)
    arr = np.empty(1, dtype=object)
    arr[0] = Payload()
    np.save(tmp_path / "ground_truth_new.npy", arr, allow_pickle=True)
    with pytest.raises(ValueError, match="pickled object array"):
        load_vprbench(tmp_path)
    assert not marker.exists()


def test_vprbench_raw_pickle_file_is_refused(tmp_path):
    # Some VPR-Bench conversions write the file with pickle.dump instead of np.save.
    make_folder(tmp_path)
    with open(tmp_path / "ground_truth_new.npy", "wb") as fh:
        pickle.dump(object_rows(ROWS), fh, protocol=2)
    with pytest.raises(ValueError, match="pickled object array"):
        load_vprbench(tmp_path)
    b = load_vprbench(tmp_path, trust_pickle=True)
    np.testing.assert_array_equal(b.ground_truth, EXPECTED)


def test_vprbench_plain_matrix(tmp_path):
    make_folder(tmp_path)
    np.save(tmp_path / "ground_truth.npy", EXPECTED)
    save_pickled(tmp_path, ROWS)  # present too, but the plain file needs no pickle
    b = load_benchmark("vprbench", root=tmp_path)
    np.testing.assert_array_equal(b.ground_truth, EXPECTED)
    assert b.tolerance == {"ground_truth_file": "ground_truth.npy"}
    np.save(tmp_path / "ground_truth.npy", EXPECTED.astype(np.uint8))
    np.testing.assert_array_equal(load_vprbench(tmp_path).ground_truth, EXPECTED)


@pytest.mark.parametrize(
    "matrix, match",
    [
        (np.ones((N_REF, N_QUERY), bool), r"must have shape \(n_query, n_reference\) = \(4, 5\)"),
        (np.full((N_QUERY, N_REF), 0.5), "expected a boolean ground-truth matrix"),
        (np.full((N_QUERY, N_REF), 2), "expected a boolean ground-truth matrix"),
    ],
)
def test_vprbench_plain_matrix_errors(tmp_path, matrix, match):
    make_folder(tmp_path)
    np.save(tmp_path / "ground_truth.npy", matrix)
    with pytest.raises(ValueError, match=match):
        load_vprbench(tmp_path)


@pytest.mark.parametrize(
    "rows, match",
    [
        ([[0, [0]], [4, [1]]], r"row 1: query index 4 out of range \[0, 4\)"),
        ([[0, [5]]], r"row 0: reference index 5 out of range \[0, 5\)"),
        ([[0, [-1]]], "reference index -1 out of range"),
        ([[1, [0]], [1, [2]]], "row 1: query index 1 is listed twice"),
        ([[0.5, [0]]], "row 0: query index must be an int"),
        ([[0, ["a"]]], "row 0: reference indices must be ints"),
    ],
)
def test_vprbench_rows_validated(tmp_path, rows, match):
    make_folder(tmp_path)
    save_pickled(tmp_path, rows)
    with pytest.raises(ValueError, match=match):
        load_vprbench(tmp_path, trust_pickle=True)


@pytest.mark.parametrize("writer", ["np.save", "pickle.dump"])
def test_vprbench_pickled_dict_is_refused_naming_the_file(tmp_path, writer):
    # Some conversions pickle {query_index: [reference indices]} instead of the rows array;
    # that once escaped as a bare KeyError from rows[0].
    make_folder(tmp_path)
    table = {"q0": [0, 1], "q1": [1]}
    path = tmp_path / "ground_truth_new.npy"
    if writer == "np.save":
        np.save(path, table, allow_pickle=True)
    else:
        with open(path, "wb") as fh:
            pickle.dump(table, fh, protocol=2)
    with pytest.raises(ValueError, match="ground_truth_new.npy: expected rows") as e:
        load_vprbench(tmp_path, trust_pickle=True)
    msg = str(e.value)
    assert "object array of shape (n, 2)" in msg
    assert "got a dict with 2 keys ('q0', 'q1')" in msg


def test_parse_rows_scalar_reference_and_missing_query():
    gt = parse_vprbench_rows([[2, 3], (0, np.array([1, 2]))], 3, 4)
    np.testing.assert_array_equal(gt, [[0, 1, 1, 0], [0, 0, 0, 0], [0, 0, 0, 1]])
    with pytest.raises(ValueError, match=r"row 0: expected \[query_index"):
        parse_vprbench_rows([[1, 2, 3]], 3, 4)
    with pytest.raises(ValueError, match="expected rows"):
        parse_vprbench_rows(5, 3, 4)


def test_vprbench_missing_pieces(tmp_path):
    with pytest.raises(FileNotFoundError, match="dataset root not found"):
        load_vprbench(tmp_path / "none")
    (tmp_path / "ref").mkdir()
    with pytest.raises(ValueError, match=r"no image files .*ref.*expected layout"):
        load_vprbench(tmp_path)
    root = make_folder(tmp_path / "ds")
    with pytest.raises(
        FileNotFoundError, match="no ground-truth file .*ground_truth.npy or ground_truth_new.npy"
    ):
        load_vprbench(root)
    (root / "ground_truth_new.npy").write_bytes(b"garbage, not numpy")
    with pytest.raises(ValueError, match="ground_truth_new.npy"):
        load_vprbench(root, trust_pickle=True)
    with pytest.raises(TypeError, match="trust_pickle must be a bool"):
        load_vprbench(root, trust_pickle="yes")


def test_vprbench_missing_query_folder(tmp_path):
    make_folder(tmp_path)
    for p in (tmp_path / "query").iterdir():
        p.unlink()
    (tmp_path / "query").rmdir()
    with pytest.raises(FileNotFoundError, match=r"image folder not found: .*query"):
        load_vprbench(tmp_path)
