"""Map building in parallel: --jobs N and a Dask cluster write the one-process map, bytewise."""

from __future__ import annotations

import shutil
import sys

import numpy as np
import pytest

import flyvpr._chunks
from flyvpr._chunks import ChunkRunner, check_parallel
from flyvpr.cli import main
from flyvpr.localization.maps import Map

N_FRAMES = 120


@pytest.fixture(scope="module")
def frames(nordland_64x32, tmp_path_factory):
    """The first N_FRAMES summer frames in a folder of their own."""
    folder = tmp_path_factory.mktemp("summer")
    for path in sorted((nordland_64x32 / "summer").glob("*.png"))[:N_FRAMES]:
        shutil.copy(path, folder / path.name)
    return folder


@pytest.fixture
def small_chunks(monkeypatch):
    # 120 frames in chunks of 50: three chunks, the last one short
    monkeypatch.setattr(flyvpr._chunks, "CHUNK", 50)


@pytest.fixture(scope="module")
def cluster():
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None
    ) as c:
        yield c


def _build(frames, out, method, *options):
    assert main(["map", str(frames), "--out", str(out), "--method", method, "-q", *options]) == 0
    return out.read_bytes()


@pytest.mark.parametrize("method", ["kenyon+cann", "pixels"])
def test_jobs_write_the_one_process_map_byte_for_byte(frames, tmp_path, small_chunks, method):
    one = _build(frames, tmp_path / "one.map", method)
    assert _build(frames, tmp_path / "j1.map", method, "--jobs", "1") == one
    assert _build(frames, tmp_path / "j2.map", method, "--jobs", "2") == one
    assert Map.load(tmp_path / "j2.map").n_places == N_FRAMES


@pytest.mark.parametrize("method", ["kenyon+cann", "pixels"])
def test_dask_cluster_writes_the_one_process_map_byte_for_byte(
    frames, tmp_path, small_chunks, cluster, method
):
    distributed = pytest.importorskip("distributed")
    one = _build(frames, tmp_path / "one.map", method)
    address = cluster.scheduler_address
    assert _build(frames, tmp_path / "dask.map", method, "--scheduler", address) == one
    with distributed.Client(cluster, set_as_default=False) as client:
        m = Map.build(frames, method, scheduler=client)
    assert m.save(tmp_path / "client.map").read_bytes() == one


def test_front_end_that_cannot_split_fits_in_one_process(frames, tmp_path, caplog):
    one = _build(frames, tmp_path / "one.map", "flyhash")
    with caplog.at_level("WARNING", logger="flyvpr.localization.maps"):
        assert _build(frames, tmp_path / "j2.map", "flyhash", "--jobs", "2") == one
    assert "cannot split its fit" in caplog.text


def test_chunks_come_back_in_order(small_chunks):
    rows = np.arange(173 * 3, dtype=np.float32).reshape(173, 3)
    with ChunkRunner(n_jobs=1) as run:
        np.testing.assert_array_equal(run(np.negative, rows), -rows)


@pytest.mark.parametrize(
    "n_jobs, scheduler, error, match",
    [
        (0, None, ValueError, "jobs.*got 0"),
        (-2, None, ValueError, "jobs.*got -2"),
        ("2", None, TypeError, "jobs.*got str"),
        (True, None, TypeError, "jobs.*got bool"),
        (2, "tcp://localhost:8786", ValueError, "jobs.*scheduler: give one"),
        (None, 8786, TypeError, "scheduler.*address.*got int"),
        (None, " ", ValueError, "scheduler.*empty"),
    ],
)
def test_bad_jobs_or_scheduler_is_refused_before_reading(n_jobs, scheduler, error, match):
    check = pytest.raises(error, match=match)
    with check:
        check_parallel(n_jobs, scheduler)
    with pytest.raises(error, match=match):  # before the source is even opened
        Map.build("no/such/folder", n_jobs=n_jobs, scheduler=scheduler)


def test_scheduler_without_dask_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)
    with pytest.raises(ImportError, match=r"flyvpr\[dask\]"):
        Map.build("no/such/folder", scheduler="tcp://localhost:8786")


def test_unreachable_scheduler_is_one_error_and_no_map(frames, tmp_path, capsys):
    dask = pytest.importorskip("dask")
    pytest.importorskip("distributed")
    out = tmp_path / "m.map"
    with dask.config.set({"distributed.comm.timeouts.connect": "1s"}):
        rc = main(["map", str(frames), "--out", str(out), "-q", "--scheduler", "tcp://127.0.0.1:9"])
    assert rc == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot reach the Dask scheduler at 'tcp://127.0.0.1:9'" in err[0]
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "options, match",
    [
        (["--jobs", "0"], "--jobs: must be >= 1 or -1"),
        (["--jobs", "-3"], "--jobs: must be >= 1 or -1"),
    ],
)
def test_cli_bad_jobs_is_a_usage_error(frames, tmp_path, capsys, options, match):
    assert main(["map", str(frames), "--out", str(tmp_path / "m.map"), *options]) == 2
    assert match in capsys.readouterr().err


def test_cli_jobs_and_scheduler_exclude_each_other(frames, tmp_path, capsys):
    argv = ["map", str(frames), "--out", str(tmp_path / "m.map"), "-j", "2", "--scheduler", "x"]
    assert main(argv) == 2
    assert "not allowed with argument" in capsys.readouterr().err
