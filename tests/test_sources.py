"""Recordings as frame sources: video, ROS 1/2 bags, image folders; thinning; positions; maps."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("av")
pytest.importorskip("rosbags")

from flyvpr.images import load_image, resize_area  # noqa: E402
from flyvpr.localization import Localizer  # noqa: E402
from flyvpr.localization.maps import Map  # noqa: E402
from flyvpr.modelio import ModelFileError, load_method  # noqa: E402
from flyvpr.sources import (  # noqa: E402
    Every,
    RecordingError,
    open_source,
    parse_every,
    read_positions,
)
from flyvpr.sources.writers import write_bag, write_video  # noqa: E402
from flyvpr.synthetic import make_route, save_route  # noqa: E402

N = 24
SIZE = (32, 64)


@pytest.fixture(scope="module")
def route():
    return make_route(N, size=(64, 128), conditions=("summer", "winter"), return_rgb=True)


@pytest.fixture(scope="module")
def pillow_frames(route, tmp_path_factory):
    """The summer frames as the image-folder loaders read them (PNG, Pillow, area resize)."""
    folder = tmp_path_factory.mktemp("png")
    paths = save_route(route, folder)["summer"]
    return np.stack([load_image(p, SIZE) for p in paths]), folder / "summer"


@pytest.mark.parametrize(
    "text, expected",
    [("3", Every(3, "frames")), ("0.5s", Every(0.5, "seconds")), ("2m", Every(2, "metres"))],
)
def test_parse_every(text, expected):
    assert parse_every(text) == expected


@pytest.mark.parametrize("text", ["0", "1.5", "-1s", "2km", "x", "0s", "1e400m", "1e400s"])
def test_parse_every_refuses(text):
    with pytest.raises(ValueError, match=f"^every: .*; got '{text}'$"):
        parse_every(text)


@pytest.mark.parametrize("codec", ["libx264", "mpeg4"])  # full-range and limited-range luma
def test_video_streams_small_gray_frames(route, pillow_frames, tmp_path, codec):
    path = write_video(tmp_path / "s.mp4", route.rgb["summer"], fps=10, codec=codec)
    src = open_source(path)
    batches = list(src.batches(SIZE, batch=5))
    assert [len(b) for b in batches] == [5, 5, 5, 5, 4]
    allf = np.concatenate([b.images for b in batches])
    assert allf.shape == (N, *SIZE) and allf.dtype == np.float32
    np.testing.assert_allclose(np.concatenate([b.timestamps for b in batches]), np.arange(N) / 10)
    # lossy codecs and 4:2:0 colour against Pillow's RGB: close, not identical, and unbiased
    # (a limited-range video read as full range would be off by about 0.06 on average)
    diff = allf - pillow_frames[0]
    assert np.abs(diff).mean() < 0.02 and abs(diff.mean()) < 0.005


@pytest.mark.parametrize("version", [1, 2])
@pytest.mark.parametrize(
    "encoding, compressed, tol",
    [
        ("rgb8", None, 1e-6),
        ("bgr8", None, 1e-6),
        ("rgba8", None, 1e-6),
        ("bgra8", None, 1e-6),
        ("mono8", None, 0.003),
        ("mono16", None, 0.003),
        ("rgb8", "png", 1e-6),
        ("rgb8", "jpeg", 0.03),
    ],
)
def test_bag_encodings_match_the_image_folder(
    route, pillow_frames, tmp_path, version, encoding, compressed, tol
):
    frames = route.rgb["summer"]
    if encoding.startswith("mono"):
        frames = np.rint(route.images["summer"] * 255).astype(np.uint8)
    path = tmp_path / ("s.bag" if version == 1 else "s2")
    write_bag(path, frames, version=version, encoding=encoding, compressed=compressed, fps=5)
    got = open_source(path).read_all(SIZE)
    assert got.images.shape == (N, *SIZE)
    np.testing.assert_allclose(got.timestamps, 1000.0 + np.arange(N) / 5)
    assert np.abs(got.images - pillow_frames[0]).mean() < tol


@pytest.mark.parametrize("storage, suffix", [("sqlite3", ".db3"), ("mcap", ".mcap")])
def test_ros2_bag_by_folder_or_storage_file(route, pillow_frames, tmp_path, storage, suffix):
    write_bag(tmp_path / "b", route.rgb["summer"], version=2, encoding="rgb8", storage=storage)
    (file,) = (tmp_path / "b").glob("*" + suffix)
    for path in (tmp_path / "b", file):
        got = open_source(path).read_all(SIZE)
        assert np.abs(got.images - pillow_frames[0]).mean() < 1e-6


def test_folder_source_is_the_loaders(pillow_frames):
    got = open_source(pillow_frames[1]).read_all(SIZE)
    np.testing.assert_array_equal(got.images, pillow_frames[0])
    assert np.isnan(got.timestamps).all()


def test_every_thins_by_count_time_and_distance(route, tmp_path):
    xy = np.c_[np.arange(N) * 1.5, np.zeros(N)]
    bag = write_bag(tmp_path / "p.bag", route.images["summer"], version=1, fps=10, positions=xy)
    src = open_source(bag)
    assert src.read_all(SIZE, every="3").indices.tolist() == list(range(0, N, 3))
    assert src.read_all(SIZE, every="0.25s").indices.tolist() == list(range(0, N, 3))
    pos = read_positions(bag=bag, topic="/odom")
    assert src.read_all(SIZE, every="4m", positions=pos).indices.tolist() == list(range(0, N, 3))
    with pytest.raises(ValueError, match="needs positions"):
        src.read_all(SIZE, every="4m")


def test_positions_csv_by_frame_and_timestamp(tmp_path):
    by_frame = tmp_path / "f.csv"
    by_frame.write_text("frame,x,y\n0,0,0\n2,4,1\n")
    p = read_positions(by_frame)
    out = p.at(np.array([0, 1, 2]), np.full(3, np.nan))
    assert out[0].tolist() == [0, 0] and np.isnan(out[1]).all() and out[2].tolist() == [4, 1]
    by_time = tmp_path / "t.csv"
    by_time.write_text("timestamp,x,y\n10,0,0\n11,5,5\n")
    q = read_positions(by_time)
    # the nearest row's position within the rows' span, widened by half the median interval
    # (0.5 s here); outside it none (a recording that runs on before or after its positions)
    assert q.span() == (9.5, 11.5)
    got = q.at(np.zeros(6), np.array([9.0, 9.5, 10.4, 10.6, 11.5, 20.0]))
    assert np.isnan(got[[0, 5]]).all()
    assert got[1:5].tolist() == [[0, 0], [0, 0], [5, 5], [5, 5]]
    assert np.isnan(q.at(np.zeros(2), np.array([9.499, 11.501]))).all()
    bad = tmp_path / "b.csv"
    bad.write_text("name,x,y\na,1,2\n")
    with pytest.raises(ValueError, match="timestamp,x,y or frame,x,y"):
        read_positions(bad)


@pytest.mark.parametrize(
    ("row", "message"),
    [
        ("5.5,1,2", r"line 3: frame must be a whole number >= 0 .*; got 5.5"),
        ("-5,1,2", r"line 3: frame must be a whole number >= 0 .*; got -5"),
        ("nan,1,2", r"line 3: not a finite frame,x,y"),
        ("4,inf,2", r"line 3: not a finite frame,x,y"),
    ],
)
def test_positions_csv_frames_are_indices(tmp_path, row, message):
    bad = tmp_path / "b.csv"
    bad.write_text(f"frame,x,y\n0,0,0\n{row}\n")
    with pytest.raises(ValueError, match=message):
        read_positions(bad)
    dup = tmp_path / "d.csv"
    dup.write_text("frame,x,y\n0,0,0\n4,1,1\n7,2,2\n4,3,3\n")
    with pytest.raises(ValueError, match=r"d.csv, line 5: frame 4 is on line 3 too"):
        read_positions(dup)
    dup.write_text("timestamp,x,y\n1.5,0,0\n1.50,1,1\n")
    with pytest.raises(ValueError, match=r"line 3: timestamp 1.50 is on line 2 too"):
        read_positions(dup)
    # a timestamp may be fractional or negative (seconds on any clock)
    ok = tmp_path / "t.csv"
    ok.write_text("timestamp,x,y\n-5,0,0\n5.5,1,2\n")
    assert read_positions(ok).keys.tolist() == [-5.0, 5.5]


def test_every_metres_says_how_many_frames_had_no_position(route, tmp_path, caplog):
    # positions for the first 5 frames only: a metres rule keeps from those and says it
    # skipped the rest
    folder = tmp_path / "f"
    save_route(route, folder)
    src = open_source(folder / "summer")
    short = tmp_path / "short.csv"
    short.write_text("frame,x,y\n" + "".join(f"{i},{2.0 * i},0\n" for i in range(5)))
    with caplog.at_level("WARNING", logger="flyvpr"):
        got = src.read_all(SIZE, every="4m", positions=read_positions(short))
    assert got.indices.tolist() == [0, 2, 4]
    (record,) = [r for r in caplog.records if "no position" in r.getMessage()]
    assert f"skipped {N - 5} of {N} frames that have no position in {short}" in record.getMessage()
    caplog.clear()
    with caplog.at_level("WARNING", logger="flyvpr"):  # read again (a compact map's 2nd pass)
        src.read_all(SIZE, every="4m", positions=read_positions(short))
    assert not [r for r in caplog.records if "no position" in r.getMessage()]
    full = tmp_path / "full.csv"
    full.write_text("frame,x,y\n" + "".join(f"{i},{2.0 * i},0\n" for i in range(N)))
    with caplog.at_level("WARNING", logger="flyvpr"):
        src.read_all(SIZE, every="4m", positions=read_positions(full))
    assert not [r for r in caplog.records if "no position" in r.getMessage()]


def test_positions_interpolated_between_rows(tmp_path):
    by_frame = tmp_path / "f.csv"
    by_frame.write_text("frame,x,y\n2,0,10\n6,8,2\n")
    p = read_positions(by_frame)
    frames = np.array([0, 2, 3, 4, 6, 7])
    near = p.at(frames, np.full(6, np.nan))
    assert np.isnan(near[[0, 2, 3, 5]]).all() and near[[1, 4]].tolist() == [[0, 10], [8, 2]]
    out = p.at(frames, np.full(6, np.nan), interpolate=True)
    assert np.isnan(out[[0, 5]]).all()  # outside the rows: no position, as without
    assert out[1:5].tolist() == [[0, 10], [2, 8], [4, 6], [8, 2]]
    by_time = tmp_path / "t.csv"
    by_time.write_text("timestamp,x,y\n10,0,0\n12,4,-2\n13,4,-2\n")
    q = read_positions(by_time)
    t = np.array([9.0, 10.0, 10.5, 11.0, 12.5, 14.0])
    assert q.span() == (9.25, 13.75)  # half the median interval (1.5 s) at either end
    out = q.at(np.zeros(6), t, interpolate=True)
    assert np.isnan(out[[0, 5]]).all()  # before the first fix, after the last: none
    assert out[1:5].tolist() == [[0, 0], [1, -0.5], [2, -1], [4, -2]]
    near = q.at(np.zeros(6), t)
    assert np.isnan(near[[0, 5]]).all()
    assert near[1:5].tolist() == [[0, 0], [0, 0], [0, 0], [4, -2]]
    # within the widened ends: the end row's position, as before
    assert q.at(np.zeros(2), np.array([9.3, 13.7]), interpolate=True).tolist() == [
        [0, 0], [4, -2]
    ]  # fmt: skip
    # frames keyed by index are not widened: a row's own index only
    assert p.span() == (2.0, 6.0)
    one = tmp_path / "one.csv"
    one.write_text("timestamp,x,y\n10,3,4\n")
    single = read_positions(one)
    assert single.span() == (10.0, 10.0)
    got = single.at(np.zeros(3), np.array([9.0, 10.0, 11.0]))
    assert got[1].tolist() == [3, 4] and np.isnan(got[[0, 2]]).all()


def test_navsatfix_positions_in_local_metres(tmp_path):
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    path = tmp_path / "gps.bag"
    with Writer(path) as w:
        conn = w.add_connection("/fix", "sensor_msgs/msg/NavSatFix", typestore=ts)
        for i, (lat, lon) in enumerate([(60.0, 10.0), (60.001, 10.0), (60.0, 10.002)]):
            hdr = T["std_msgs/msg/Header"](
                seq=i, stamp=T["builtin_interfaces/msg/Time"](sec=i, nanosec=0), frame_id="gps"
            )
            msg = T["sensor_msgs/msg/NavSatFix"](
                header=hdr, status=T["sensor_msgs/msg/NavSatStatus"](status=0, service=1),
                latitude=lat, longitude=lon, altitude=0.0,
                position_covariance=np.zeros(9), position_covariance_type=0,
            )  # fmt: skip
            w.write(conn, i * 10**9, ts.serialize_ros1(msg, "sensor_msgs/msg/NavSatFix"))
    pos = read_positions(bag=path, topic="/fix")
    xy = pos.at(np.zeros(3), np.array([0.0, 1.0, 2.0]))
    r = 6_371_000.0
    np.testing.assert_allclose(xy[1], [0, r * np.radians(0.001)], rtol=1e-9)
    np.testing.assert_allclose(xy[2], [r * np.radians(0.002) * np.cos(np.radians(60)), 0], 1e-9)


def test_bag_topic_errors_list_the_image_topics(route, tmp_path):
    bag = write_bag(tmp_path / "a.bag", route.images["summer"][:3], version=1, topic="/cam/a")
    with pytest.raises(RecordingError, match=r"no image topic '/cam/b'.*: /cam/a"):
        open_source(bag, topic="/cam/b")
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    two = tmp_path / "two.bag"
    with Writer(two) as w:
        for topic in ("/left", "/right"):
            w.add_connection(topic, "sensor_msgs/msg/Image", typestore=ts)
    with pytest.raises(
        RecordingError, match=r"topic=TOPIC.*/left \(sensor_msgs/msg/Image\), /right"
    ):
        open_source(two)
    with pytest.raises(RecordingError, match="holds no frame"):
        open_source(two, topic="/left").read_all(SIZE)


def test_unsupported_encoding_is_named(route, tmp_path):
    bag = write_bag(tmp_path / "d.bag", route.images["summer"][:2], version=1, encoding="16UC1")
    with pytest.raises(RecordingError, match=r"d.bag.*unsupported image encoding '16UC1'"):
        open_source(bag).read_all(SIZE)


def test_truncated_recordings_name_the_file(route, tmp_path):
    video = write_video(tmp_path / "v.mp4", route.images["summer"])
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(video.read_bytes()[: video.stat().st_size // 2])
    with pytest.raises(RecordingError, match="cut.mp4"):
        open_source(cut).read_all(SIZE)
    bag = write_bag(tmp_path / "b.bag", route.images["summer"], version=1)
    cutbag = tmp_path / "cut.bag"
    cutbag.write_bytes(bag.read_bytes()[: bag.stat().st_size // 2])
    with pytest.raises(RecordingError, match="cut.bag"):
        open_source(cutbag).read_all(SIZE)
    garbage = tmp_path / "g.mkv"
    garbage.write_bytes(b"not a video at all" * 10)
    with pytest.raises(RecordingError, match="g.mkv: not a readable video"):
        open_source(garbage)


def test_expected_video_frames_say_how_sure_they_are():
    from types import SimpleNamespace as NS

    from flyvpr.sources.video import _expected_frames

    # a header that counts its frames says so; one with a duration and a rate only implies
    # a count, one frame short for rounding; with neither there is nothing to check against
    assert _expected_frames(NS(duration=None), NS(frames=300)) == (300, "announces")
    ten_s = NS(duration=10_000_000)  # microseconds
    assert _expected_frames(ten_s, NS(frames=0, average_rate=30, guessed_rate=None)) == (
        299,
        "implies at least",
    )
    assert _expected_frames(ten_s, NS(frames=0, average_rate=None, guessed_rate=25))[0] == 249
    assert _expected_frames(
        NS(duration=None), NS(frames=0, average_rate=30, guessed_rate=None)
    ) == (
        None,
        "",
    )


def test_map_round_trip_and_from_map(route, tmp_path):
    xy = np.c_[np.arange(N) * 2.0, np.ones(N)]
    bag = write_bag(tmp_path / "m.bag", route.images["summer"], version=1, positions=xy)
    m = Map.build(bag, "pixels+cann", every="2", position_topic="/odom")
    assert m.n_places == N // 2 and m.source_index.tolist() == list(range(0, N, 2))
    path = m.save(tmp_path / "route.map")
    loaded = Map.load(path)
    np.testing.assert_array_equal(loaded.positions, xy[::2])
    np.testing.assert_array_equal(loaded.thumbnails, m.thumbnails)
    assert loaded.info == m.info
    loc = Localizer.from_map(path)
    q = np.stack([resize_area(f, SIZE) for f in route.images["summer"][::2]])
    places, _, scores, _, states = loc.update_batch(q)
    assert states.shape == (N // 2,)
    assert scores.shape == (N // 2, N // 2)
    assert np.mean(places == np.arange(N // 2)) > 0.8
    with pytest.raises(ModelFileError, match="fitted on 32x64 images"):
        Map.load(path, size=(16, 32))
    with pytest.raises(ModelFileError, match="not a bare model"):
        load_method(path)


def test_map_errors_call_it_a_map_file(route, tmp_path):
    from flyvpr.modelio import save_method

    bag = write_bag(tmp_path / "m.bag", route.images["summer"], version=1)
    m = Map.build(bag)
    path = m.save(tmp_path / "r.map")
    model = save_method(m.method, tmp_path / "bare.npz")
    with pytest.raises(ModelFileError, match=r"^map file .*bare\.npz: map: missing: not a flyvpr "
                       r"map file \(a bare model, as `flyvpr fit` writes; build one with "
                       r"`flyvpr map`\)"):  # fmt: skip
        Map.load(model)
    truncated = tmp_path / "cut.map"
    truncated.write_bytes(path.read_bytes()[:1000])
    with pytest.raises(ModelFileError, match=r"^map file .*cut\.map is not a readable \.npz"):
        Map.load(truncated)
    flipped = tmp_path / "flip.map"
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    flipped.write_bytes(bytes(data))
    with pytest.raises(ModelFileError, match=r"^map file .*flip\.map failed its file checksum"):
        Map.load(flipped)
    with pytest.raises(FileNotFoundError, match=r"^map file not found: .*none\.map"):
        Map.load(tmp_path / "none.map")
    # the model itself is still a model file
    with pytest.raises(ModelFileError, match=r"^model file .*cut\.map is not a readable"):
        load_method(truncated)


def test_map_of_another_version_is_refused(route, tmp_path, monkeypatch):
    import flyvpr.localization.maps as maps

    bag = write_bag(tmp_path / "m.bag", route.images["summer"], version=1)
    monkeypatch.setattr(maps, "MAP_VERSION", 99)
    path = Map.build(bag).save(tmp_path / "v99.map")
    monkeypatch.undo()
    with pytest.raises(ModelFileError, match="map version 99"):
        Map.load(path)


def test_update_batch_equals_update(route):
    ref = np.stack([resize_area(f, SIZE) for f in route.images["summer"]])
    qry = np.stack([resize_area(f, SIZE) for f in route.images["winter"]])
    a = Localizer("pixels+cann").fit(ref)
    b = Localizer("pixels+cann").fit(ref)
    places, conf, _, _, states = a.update_batch(qry)
    one = [b.update(f) for f in qry]
    assert places.tolist() == [p for p, _, _ in one]
    np.testing.assert_allclose(conf, [c for _, c, _ in one], rtol=1e-5)
    assert states.tolist() == [s for _, _, s in one]


@pytest.mark.parametrize("suffix", [".mkv", ".avi"])
def test_cut_video_without_an_index_is_refused(suffix, tmp_path):
    """Matroska and AVI decode up to the cut without an error: the header's frame count or
    duration catches it."""
    frames = (np.random.default_rng(0).random((30, 32, 64)) * 255).astype(np.uint8)
    whole = write_video(tmp_path / f"v{suffix}", frames)
    assert len(open_source(whole).read_all(SIZE)) == 30
    cut = tmp_path / f"cut{suffix}"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size * 2 // 3])
    with pytest.raises(
        RecordingError,
        match=rf"cut\{suffix}: truncated: its header (announces|implies at least) \d+ frames, "
        r"\d+ could be decoded",
    ):
        open_source(cut).read_all(SIZE)


def test_missing_extra_names_it(route, tmp_path, monkeypatch):
    import importlib

    path = write_video(tmp_path / "v.mp4", route.images["summer"][:4])
    real = importlib.import_module

    def without_av(name, *args, **kwargs):
        if name.split(".")[0] == "av":
            raise ImportError("No module named 'av'")
        return real(name, *args, **kwargs)

    monkeypatch.setattr(importlib, "import_module", without_av)
    with pytest.raises(
        ImportError, match=r"needs the 'av' package: pip install 'flyvpr\[recordings\]'"
    ):
        open_source(path)


def test_other_pixel_formats_go_through_swscale(route):
    import av

    from flyvpr.images import to_gray
    from flyvpr.sources.video import _decoder

    rgb = route.rgb["summer"][0]
    frame = av.VideoFrame.from_ndarray(np.rint(rgb * 255).astype(np.uint8), format="rgb24")
    got = _decoder(frame)(SIZE)
    assert got.shape == SIZE and got.dtype == np.float32
    assert np.abs(got - resize_area(to_gray(rgb), SIZE)).max() < 0.01


def test_area_matrix_averages_exactly():
    from flyvpr.images import area_matrix

    a = area_matrix(2, 5)  # output pixel 0 covers [0, 2.5): pixels 0, 1 and half of 2
    np.testing.assert_allclose(a, [[0.4, 0.4, 0.2, 0, 0], [0, 0, 0.2, 0.4, 0.4]], atol=1e-7)
    np.testing.assert_allclose(area_matrix(3, 6).sum(axis=1), 1.0, rtol=1e-6)


@pytest.mark.parametrize("shape", [(480, 640), (720, 1280), (361, 500), (64, 128), (20, 30)])
def test_area_resize_equals_the_dense_area_product(shape):
    from flyvpr.images import area_matrix, area_resize

    rng = np.random.default_rng(shape[0])
    y = rng.integers(0, 256, (shape[0], shape[1] + 5), dtype=np.uint8)[:, : shape[1]]
    dense = area_matrix(32, shape[0]) @ y.astype(np.float32) @ area_matrix(64, shape[1]).T
    out = area_resize(y, 32, 64)
    assert out.shape == (32, 64) and out.dtype == np.float32
    np.testing.assert_allclose(out, dense, atol=1e-3)
    # a constant frame stays that constant, whatever the band weights
    np.testing.assert_allclose(area_resize(np.full(shape, 200, np.uint8), 32, 64), 200, rtol=1e-5)


def test_writers_take_a_name_up_to_name_max(tmp_path):
    # the temporary file beside a 250-character target is short enough (and keeps the suffix
    # the container is picked from); nothing is left beside the written video
    from flyvpr.sources.writers import write_video

    frames = (np.random.default_rng(0).random((4, 32, 64)) * 255).astype(np.uint8)
    path = tmp_path / ("v" * 246 + ".mp4")
    write_video(path, frames, fps=10)
    assert path.is_file() and [p.name for p in tmp_path.iterdir()] == [path.name]


def test_an_every_object_is_checked_as_text_is():
    from flyvpr.sources import Every, parse_every

    assert parse_every(Every(3)) == Every(3.0, "frames")
    assert parse_every(Every(0.5, "seconds")) == Every(0.5, "seconds")
    for bad, match in (
        (Every(0), "a frame count must be an integer >= 1"),
        (Every(2.5), "a frame count must be an integer >= 1"),
        (Every(-1.0, "metres"), "the step must be a finite number > 0"),
        (Every(2, "bogus"), "unit must be 'frames', 'seconds' or 'metres'"),
        (Every("2", "frames"), "the step must be a number"),
    ):
        with pytest.raises(ValueError, match=match):
            parse_every(bad)


def test_a_missing_bag_is_not_found_and_a_lone_db3_says_what_it_lacks(tmp_path):
    pytest.importorskip("rosbags")
    from flyvpr.sources import RecordingError
    from flyvpr.sources.rosbag import BagSource

    with pytest.raises(FileNotFoundError, match="bag not found"):
        BagSource(tmp_path / "gone.bag")
    lone = tmp_path / "x.db3"
    lone.write_bytes(b"")
    with pytest.raises(RecordingError) as info:
        BagSource(lone)
    # one message, not wrapped in "not a readable ROS bag (...)"
    assert str(info.value) == f"bag {lone}: a ROS 2 bag file needs the metadata.yaml of its folder"


def test_positions_that_cover_no_frame_are_named_with_both_spans(tmp_path):
    from flyvpr.sources.positions import Positions

    by_time = Positions(np.array([100.0, 101.0, 102.5]), np.zeros((3, 2)), "timestamp", "gps.csv")
    assert by_time.describe_span() == "timestamps 100-102.5 s"
    t = np.array([0.0, 2.5, 5.0])
    xy = by_time.at(np.arange(3), t)
    assert np.isnan(xy).all()
    with pytest.raises(RecordingError) as info:
        by_time.check_covers(xy, np.arange(3), t, "video v.mp4")
    assert str(info.value) == (
        "video v.mp4: no frame has a position in gps.csv (its rows: timestamps 100-102.5 s; its "
        "frames' timestamps 0-5 s): the positions and the recording must share a clock"
    )
    by_frame = Positions(np.array([7, 9]), np.zeros((2, 2)), "frame", "f.csv")
    assert by_frame.describe_span() == "frames 7-9"
    with pytest.raises(RecordingError) as info:
        by_frame.check_covers(np.full((2, 2), np.nan), np.array([0, 5]), t[:2], "folder d")
    assert str(info.value) == (
        "folder d: no frame has a position in f.csv (its rows: frames 7-9; its frames 0-5): a "
        "frame,x,y row names a frame's index in the recording"
    )
    # one frame placed is enough; so is an empty recording (nothing to place)
    some = np.array([[np.nan, np.nan], [1.0, 2.0]])
    by_frame.check_covers(some, np.array([0, 8]), t[:2], "folder d")
    by_frame.check_covers(np.zeros((0, 2)), np.zeros(0, int), np.zeros(0), "folder d")
    # a row keyed by frame is not widened; a timestamp is, by half the median interval
    assert by_frame.span() == (7.0, 9.0) and by_time.span() == (99.375, 103.125)
    empty = tmp_path / "h.csv"
    empty.write_text("")
    with pytest.raises(ValueError, match="got nothing$"):
        read_positions(empty)
