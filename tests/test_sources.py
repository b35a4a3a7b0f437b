"""Recordings as frame sources: video, ROS 1/2 bags, image folders; thinning; positions; maps."""

from __future__ import annotations

import re

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
    Positions,
    RecordingError,
    Source,
    open_source,
    parse_every,
    read_positions,
)
from flyvpr.sources.writers import write_bag, write_video  # noqa: E402
from flyvpr.synthetic import make_route, save_route  # noqa: E402
from videos import write_av  # noqa: E402

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


@pytest.mark.parametrize(
    ("header", "message"),
    [
        ("frame,x,y,x", r"column 'x' appears 2 times in the header \(columns 2, 4\)"),
        ("y,frame,x,Y", r"column 'y' appears 2 times in the header \(columns 1, 4\)"),
        ("timestamp,timestamp,x,y", r"column 'timestamp' appears 2 times .*columns 1, 2"),
    ],
)
def test_positions_csv_with_a_column_named_twice_is_refused(tmp_path, header, message):
    # which of the two columns holds the positions would be a guess (the last one was taken)
    bad = tmp_path / "b.csv"
    bad.write_text(f"{header}\n0,1,2,3\n")
    with pytest.raises(ValueError, match=f"positions CSV {re.escape(str(bad))}: {message}"):
        read_positions(bad)
    # a column that is not read may repeat
    ok = tmp_path / "ok.csv"
    ok.write_text("frame,note,x,y,note\n0,a,1,2,b\n")
    assert read_positions(ok).at(np.array([0]), np.array([np.nan])).tolist() == [[1.0, 2.0]]


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

    # a header that counts its frames says so; one with a rate only implies a count from the
    # seconds missing, one frame short for rounding; without a rate there is nothing to say
    assert _expected_frames(NS(frames=300), decoded=100, missing_s=5.0) == (300, "announces")
    thirty = NS(frames=0, average_rate=30, guessed_rate=None)
    assert _expected_frames(thirty, decoded=0, missing_s=10.0) == (299, "implies at least")
    assert _expected_frames(thirty, decoded=50, missing_s=10.0) == (349, "implies at least")
    guessed = NS(frames=0, average_rate=None, guessed_rate=25)
    assert _expected_frames(guessed, decoded=0, missing_s=10.0)[0] == 249
    # frames that came further apart than the nominal rate (a variable rate): one per interval
    assert _expected_frames(thirty, decoded=10, missing_s=10.0, interval=0.5)[0] == 29
    none = NS(frames=0, average_rate=None, guessed_rate=None)
    assert _expected_frames(none, decoded=10, missing_s=10.0) == (None, "")


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
    from flyvpr.sources.video import _decoder, _display_ops

    rgb = route.rgb["summer"][0]
    frame = av.VideoFrame.from_ndarray(np.rint(rgb * 255).astype(np.uint8), format="rgb24")
    got = _decoder(frame, _display_ops)(SIZE)
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


class _Stamped(Source):
    """A recording of blank frames stamped ``stamps`` (seconds): clocks no writer makes."""

    kind = "stamped"

    def __init__(self, path, stamps):
        super().__init__(path)
        self.stamps = np.asarray(stamps, np.float64)

    def _frames(self):
        for i, t in enumerate(self.stamps):
            yield i, float(t), lambda size: np.zeros(size, np.float32)


def _step_back_warnings(caplog):
    return [r.getMessage() for r in caplog.records if "step back" in r.getMessage()]


def test_every_metres_interpolates_positions_slower_than_the_camera(tmp_path):
    # a 10 Hz camera and 1 Hz positions, 2 m per frame: each frame its own point on the way
    # (the nearest row gave frames 0-4 x = 0 and 5-14 x = 20: one frame kept per fix)
    src = _Stamped(tmp_path / "cam", 1000 + 0.1 * np.arange(40))
    t = 1000.0 + np.arange(5)
    pos = Positions(t, np.c_[20 * np.arange(5.0), np.zeros(5)], "timestamp", "gps")
    got = src.read_all(SIZE, every="4m", positions=pos)
    assert got.indices.tolist() == list(range(0, 40, 2))
    # keyed by frame, rows every 5th frame: interpolated by index (the docs' promise)
    by_frame = Positions(np.arange(0, 40, 5), np.c_[np.arange(0, 40, 5) * 2.0, np.zeros(8)],
                         "frame", "f.csv")  # fmt: skip
    got = src.read_all(SIZE, every="4m", positions=by_frame)
    assert got.indices.tolist() == list(range(0, 36, 2))  # frames 36-39: after the last row


def test_positions_leave_frames_in_a_gap_without_one():
    # 20 Hz odometry at 20 m/s from t = 1003, silent from 1006 to 1008 (2 s: 40 intervals)
    k = np.r_[0:60, 100:180]
    t = 1003 + k / 20
    pos = Positions(t, np.c_[(t - 1000) * 20, np.zeros(len(t))], "timestamp", "odom")
    assert pos.gaps.tolist() == [[pytest.approx(1005.95), 1008.0]]
    assert pos.describe_gaps() == "1 gap: timestamps 1005.95-1008 s"
    q = np.array([1005.9, 1005.95, 1005.97, 1005.99, 1007.0, 1007.98, 1008.0, 1008.125])
    for interpolate in (False, True):
        x = pos.at(np.zeros(len(q)), q, interpolate=interpolate)[:, 0]
        # within half the median interval (0.025 s) of the row either side: that row's, as at
        # the ends; further inside: none (not the row next to it, not a line across)
        assert x[[0, 1, 2]] == pytest.approx([118, 119, 119])
        assert np.isnan(x[[3, 4]]).all()
        assert x[5:7] == pytest.approx([160, 160])
        assert x[7] == pytest.approx(162.5 if interpolate else 162)
    # not gaps: a 1 Hz GPS that lost one fix (2 s, not more than 3 median intervals), a 20 Hz
    # topic delayed by 0.5 s (not more than 1 s); a GPS that lost 3 fixes (4 s) is one
    lost_one = Positions(np.r_[0:5, 6:10] + 100.0, np.c_[np.r_[0:5, 6:10], np.zeros(9)],
                         "timestamp", "gps")  # fmt: skip
    assert not len(lost_one.gaps) and lost_one.describe_gaps() == ""
    assert lost_one.at(np.zeros(1), np.array([105.5]), interpolate=True)[0, 0] == 5.5
    delayed = np.r_[np.arange(40) / 20, 2.45 + np.arange(40) / 20]
    assert not len(Positions(delayed, np.zeros((80, 2)), "timestamp", "odom").gaps)
    lost_three = Positions(np.r_[0:5, 8:10] + 100.0, np.zeros((7, 2)), "timestamp", "gps")
    assert lost_three.gaps.tolist() == [[104.0, 108.0]]
    assert np.isnan(lost_three.at(np.zeros(1), np.array([106.0]), interpolate=True)).all()
    # keyed by frame: rows 10-11 missing is an interval of 3 rows (interpolated), rows 20-29
    # missing a gap (none, interpolated or not); never widened into it
    frames = np.r_[0:10, 12:20, 30:40]
    by_frame = Positions(frames, np.c_[frames * 1.0, np.zeros(len(frames))], "frame", "f.csv")
    assert by_frame.describe_gaps() == "1 gap: frames 19-30"
    x = by_frame.at(np.array([10, 11, 19, 20, 29, 30]), np.full(6, np.nan), interpolate=True)
    assert x[[0, 1, 2, 5], 0].tolist() == [10, 11, 19, 30] and np.isnan(x[[3, 4]]).all()
    many = Positions(np.r_[0, 10, 11, 12, 30, 31, 50, 51, 70, 71], np.zeros((10, 2)), "frame", "m")
    assert many.describe_gaps() == "4 gaps: frames 0-10, 12-30, 31-50 and 1 more"


def test_every_metres_skips_frames_in_a_gap_and_says_so(tmp_path, caplog):
    src = _Stamped(tmp_path / "cam", 1000 + 0.1 * np.arange(120))
    t = 1003 + np.r_[0:60, 100:180] / 20
    pos = Positions(t, np.c_[(t - 1000) * 20, np.zeros(len(t))], "timestamp", "odom")
    with caplog.at_level("WARNING", logger="flyvpr"):
        got = src.read_all(SIZE, every="2m", positions=pos)
    # frames 30-59 and 80-119 are 2 m apart; 0-29 (before the rows) and 60-79 (the gap) have
    # none (a straight line across kept frames 59, 70, 81 as if 20 m had been driven in 1 s)
    assert got.indices.tolist() == list(range(30, 60)) + list(range(80, 120))
    (message,) = [r.getMessage() for r in caplog.records if "no position" in r.getMessage()]
    assert message.endswith(
        "every=2m skipped 50 of 120 frames that have no position in odom (its rows: timestamps "
        "1003-1011.95 s; 1 gap: timestamps 1005.95-1008 s)"
    )


def test_every_seconds_goes_on_after_the_clock_steps_back(tmp_path, caplog):
    # image stamps set back 3 s at frame 60 (a clock correction): the seconds rule used to
    # wait for the old time again, dropping frames 60-89 without a word
    stamps = 1000 + 0.1 * np.arange(120) - np.where(np.arange(120) >= 60, 3.0, 0.0)
    src = _Stamped(tmp_path / "jump", stamps)
    with caplog.at_level("WARNING", logger="flyvpr"):
        got = src.read_all(SIZE, every="0.5s")
    # the step back counts as no time: 0.5 s of the clock after frame 55 is frame 61
    assert got.indices.tolist() == list(range(0, 60, 5)) + list(range(61, 120, 5))
    assert _step_back_warnings(caplog) == [
        f"stamped {tmp_path / 'jump'}: the timestamps step back by 2.9 s at frame 60; every=0.5s "
        "counts the step as no time and goes on from the new time (later steps back are not "
        "reported)"
    ]
    caplog.clear()
    with caplog.at_level("WARNING", logger="flyvpr"):  # read again (a compact map's 2nd pass)
        assert src.read_all(SIZE, every="0.5s").indices.tolist() == got.indices.tolist()
    assert not _step_back_warnings(caplog)
    # stamps out of order in pairs (0.1, 0, 0.3, 0.2, ...): warned once, and the rule still
    # thins (forward steps of 0.3 s per 2 frames) rather than keeping every frame after a step
    swapped = 1000 + 0.1 * (np.arange(40) + np.where(np.arange(40) % 2, -1, 1))
    with caplog.at_level("WARNING", logger="flyvpr"):
        got = _Stamped(tmp_path / "swap", swapped).read_all(SIZE, every="0.5s")
    assert got.indices.tolist() == list(range(0, 40, 4))
    assert len(_step_back_warnings(caplog)) == 1 and "at frame 1;" in caplog.text
    # a clock that only goes forward: no warning, as before
    caplog.clear()
    with caplog.at_level("WARNING", logger="flyvpr"):
        got = _Stamped(tmp_path / "even", 1000 + 0.1 * np.arange(40)).read_all(SIZE, every="1s")
    assert got.indices.tolist() == [0, 10, 20, 30] and not _step_back_warnings(caplog)


@pytest.mark.parametrize("origin", [0.0, 512_345.0])  # local metres, UTM eastings
def test_every_metres_allows_for_rounding(tmp_path, origin):
    # x = i * 0.1 m exactly as read from a CSV: 0.30000000000000004 < 0.3 used to fail, keeping
    # steps of 3, 3, 4, 3, ... (34 frames of 120 instead of 40)
    pos = tmp_path / "p.csv"
    pos.write_text("frame,x,y\n" + "".join(f"{i},{origin + i * 0.1!r},0\n" for i in range(120)))
    src = _Stamped(tmp_path / "cam", 1000 + 0.1 * np.arange(120))
    got = src.read_all(SIZE, every="0.3m", positions=read_positions(pos))
    assert got.indices.tolist() == list(range(0, 120, 3))
    # a real shortfall is not rounding
    xy = np.c_[np.arange(120) * 0.1 - 1e-6 * (np.arange(120) == 2), np.zeros(120)]
    short = Positions(np.arange(120), xy, "frame", "short")
    assert src.read_all(SIZE, every="0.2m", positions=short).indices.tolist()[:3] == [0, 3, 5]


def test_gaps_at_either_end_of_the_rows_and_their_edges():
    # rows 1 s apart with gaps after the first row (10 s) and before the last (17 s): the
    # half-interval margin (0.5 s) holds on the gap's side of each row, boundary included
    keys = np.array([0.0, 10, 11, 12, 13, 30])
    pos = Positions(keys, np.c_[2 * keys, np.zeros(6)], "timestamp", "gps")
    assert pos.gaps.tolist() == [[0.0, 10.0], [13.0, 30.0]]
    q = np.array([0.0, 0.4, 0.6, 9.4, 9.5, 10.0, 13.5, 13.6, 29.4, 29.5, 30.0, 30.5, 31.0])
    want = [0, 0, None, None, 20, 20, 26, None, None, 60, 60, 60, None]
    for interpolate in (False, True):
        x = pos.at(np.zeros(len(q)), q, interpolate=interpolate)[:, 0]
        assert [None if np.isnan(v) else v for v in x] == want, interpolate
    two = Positions(np.array([0.0, 1.0, 2.0, 3.0, 9.0, 10.0, 11.0]), np.zeros((7, 2)),
                    "timestamp", "gps")  # fmt: skip
    more = Positions(np.r_[0:4, 10:14, 20:24, 30:34, 40:44] * 1.0, np.zeros((20, 2)),
                     "timestamp", "gps")  # fmt: skip
    assert two.describe_gaps() == "1 gap: timestamps 3-9 s"
    assert more.describe_gaps(most=4) == ("4 gaps: timestamps 3-10 s, 13-20 s, 23-30 s, 33-40 s")
    assert more.describe_gaps(most=3).endswith("23-30 s and 1 more")


def test_positions_read_twice_keep_their_interval():
    # every message of a 0.5 Hz GPS twice (two connections of one topic): the median interval
    # was 0, so every interval was a gap of more than 1 s and no frame between fixes got one
    keys = np.repeat(1000.0 + 2.0 * np.arange(30), 2)
    xy = np.c_[np.repeat(np.arange(30.0), 2), np.zeros(60)]
    twice = Positions(keys, xy, "timestamp", "gps")
    assert twice.interval == 2.0 and len(twice.gaps) == 0
    frames = 1000.0 + 0.1 * np.arange(580)
    got = twice.at(np.arange(580), frames, interpolate=True)
    assert np.isfinite(got).all()
    np.testing.assert_allclose(got[:, 0], 0.05 * np.arange(580), atol=1e-9)


@pytest.mark.parametrize("start", [1000.0, 1_700_000_000.013])  # bag time, Unix time
def test_every_metres_allows_for_rounding_of_interpolated_unix_times(tmp_path, start):
    # a 1 Hz GPS at 1 m/s under a 10 Hz camera: each frame's point is interpolated at its
    # timestamp, whose float64 rounding at Unix time (0.2 us) moved the points by as much,
    # and every=0.3m kept steps of 4, 4, 4, 4, 3 (54 frames of 200 instead of 67)
    stamps = np.array([start + i * 0.1 for i in range(200)])
    fixes = np.array([start + i for i in range(21)])
    gps = Positions(fixes, np.c_[np.arange(21.0), np.zeros(21)], "timestamp", "gps")
    got = _Stamped(tmp_path / "cam", stamps).read_all(SIZE, every="0.3m", positions=gps)
    assert got.indices.tolist() == list(range(0, 200, 3))


@pytest.mark.parametrize("start", [1000.0, 1_700_000_000.013])  # bag time, Unix time
def test_every_seconds_allows_for_rounding(tmp_path, start):
    # Unix timestamps hold about 0.2 us in a float64: 0.3 s between two of them came out
    # 0.2999998 s, and a 10 Hz camera kept steps of 4, 4, 4, 4, 3 with every=0.3s
    stamps = np.array([start + i * 0.1 for i in range(200)])
    got = _Stamped(tmp_path / "cam", stamps).read_all(SIZE, every="0.3s")
    assert got.indices.tolist() == list(range(0, 200, 3))
    got = _Stamped(tmp_path / "cam", stamps).read_all(SIZE, every="0.7s")
    assert got.indices.tolist() == list(range(0, 200, 7))


# -- videos of the kinds cameras and editors make; GPS without a fix ----------------------------
def _rgb(route, season="summer", n=N):
    return np.rint(route.rgb[season][:n] * 255).astype(np.uint8)


def _upright(route, n=N, size=SIZE):
    """The route's frames as the video path reads a lossless 4:4:4 video of them."""
    return np.stack([resize_area(f, size) for f in route.images["summer"][:n]])


def test_variable_frame_rate_video_is_read_whole(route, tmp_path):
    # 12 frames at 10 fps, then 12 at 1 fps: the old check took the container's duration
    # (13.2 s) times the average rate (10 fps) as a minimum and refused the file as truncated
    from fractions import Fraction

    pts = [100 * i for i in range(12)] + [1200 + 1000 * i for i in range(12)]
    spec = {"frames": _rgb(route), "pts": pts, "time_base": Fraction(1, 1000)}
    path = write_av(tmp_path / "vfr.mkv", [spec])
    got = open_source(path).read_all(SIZE)
    assert len(got) == N
    np.testing.assert_allclose(got.timestamps, np.array(pts) / 1000)
    # cut, it is still refused; the frames it implies are at most those it had
    cut = tmp_path / "cut.mkv"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size * 2 // 3])
    with pytest.raises(RecordingError, match=r"cut\.mkv: truncated: ") as err:
        open_source(cut).read_all(SIZE)
    import re

    implied = int(re.search(r"implies at least (\d+) frames", str(err.value))[1])
    assert implied <= N


@pytest.mark.parametrize(
    ("suffix", "codec", "pix_fmt"),
    [(".mkv", "ffv1", "yuv444p"), (".webm", "libvpx-vp9", "yuv420p")],
)
def test_camera_that_dropped_frames_is_read(route, tmp_path, suffix, codec, pix_fmt):
    # a 10 fps camera that dropped 2 frames: 22 frames over 2.4 s were refused ("implies at
    # least 23 frames, 22 could be decoded")
    pts = [i for i in range(N) if i not in (5, 13)]
    spec = {"frames": _rgb(route, n=len(pts)), "pts": pts, "codec": codec, "pix_fmt": pix_fmt}
    path = write_av(tmp_path / f"drop{suffix}", [spec])
    got = open_source(path).read_all(SIZE)
    assert len(got) == N - 2
    np.testing.assert_allclose(got.timestamps, np.array(pts) / 10)


def test_losslessly_trimmed_mp4_with_an_edit_list_is_read(route, tmp_path):
    # what `ffmpeg -ss 1 -i v.mp4 -c copy` writes: every sample is kept (the header still
    # announces 24) and an edit list hides the first second: 14 frames play, the old check
    # wanted 24
    import av

    whole = write_video(tmp_path / "v.mp4", _rgb(route), fps=10)
    trim = tmp_path / "trim.mp4"
    with av.open(str(whole)) as src, av.open(str(trim), "w") as dst:
        ist = src.streams.video[0]
        ost = dst.add_stream_from_template(ist)
        shift = int(1 / ist.time_base)
        for packet in src.demux(ist):
            if packet.dts is None:
                continue
            packet.pts -= shift
            packet.dts -= shift
            packet.stream = ost
            dst.mux(packet)
    with av.open(str(trim)) as c:
        assert c.streams.video[0].frames == N  # the samples are all there
    got = open_source(trim).read_all(SIZE)
    assert len(got) == N - 10
    full = open_source(whole).read_all(SIZE)
    np.testing.assert_allclose(got.images, full.images[10:], atol=1e-6)


def test_video_with_a_longer_audio_track_is_read(route, tmp_path):
    # the container lasts 5 s (the audio), the video 2.4 s: the video's own end counts
    path = write_av(tmp_path / "a.mkv", [{"frames": _rgb(route)}], audio_s=5)
    assert len(open_source(path).read_all(SIZE)) == N
    # and cut, its video stream's own duration (a DURATION tag) still shows the cut
    cut = tmp_path / "cut.mkv"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(
        RecordingError,
        match=r"cut\.mkv: truncated: its header implies at least \d+ frames, \d+ could be "
        r"decoded \(its video stream lasts until 2\.40 s, the decoded frames reach",
    ):
        open_source(cut).read_all(SIZE)


def test_cut_mp4_with_its_index_first_is_refused(route, tmp_path):
    # faststart: the index (moov) before the frames, so the cut file opens
    path = write_av(
        tmp_path / "fs.mp4",
        [{"frames": _rgb(route), "codec": "libx264", "pix_fmt": "yuv420p"}],
        container_options={"movflags": "faststart"},
    )
    assert len(open_source(path).read_all(SIZE)) == N
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size * 2 // 3])
    with pytest.raises(RecordingError, match=r"cut\.mp4: (truncated|damaged or truncated)"):
        open_source(cut).read_all(SIZE)


def _rotated_mp4(src, dst, matrix):
    """``src`` with the video track's display matrix (tkhd) set to ``matrix`` = (a, b, c, d):
    QuickTime's x' = a x + c y, y' = b x + d y on the screen (y down)."""
    import struct

    data = bytearray(src.read_bytes())
    at = data.find(b"tkhd")
    version = data[at + 4]
    offset = at + 4 + 4 + (32 if version == 1 else 20) + 16  # flags, times, reserved ...
    a, b, c, d = (int(v * 0x10000) & 0xFFFFFFFF for v in matrix)
    data[offset : offset + 36] = struct.pack(">9I", a, b, 0, c, d, 0, 0, 0, 0x40000000)
    dst.write_bytes(bytes(data))
    return dst


@pytest.mark.parametrize(
    ("matrix", "turns"),
    [
        # (x, y) -> (-y, x): right becomes down, a clockwise quarter turn on the screen, as
        # `ffmpeg` applies it (transpose=clock); np.rot90 counts counter-clockwise turns
        ((0, 1, -1, 0), -1),
        ((-1, 0, 0, -1), 2),  # what a phone held upside down writes
        ((0, -1, 1, 0), 1),
    ],
)
def test_rotated_video_is_read_upright(route, tmp_path, matrix, turns):
    import av

    plain = write_video(tmp_path / "v.mp4", _rgb(route, n=6), fps=10, crf=0)
    rotated = _rotated_mp4(plain, tmp_path / "r.mp4", matrix)
    with av.open(str(rotated)) as c:  # FFmpeg reads the matrix as this rotation
        assert round(next(c.decode(video=0)).rotation) % 360 == 90 * turns % 360
    upright = open_source(plain).read_all(SIZE).images
    size = SIZE if turns == 2 else SIZE[::-1]  # a quarter turn swaps height and width
    got = open_source(rotated).read_all(size).images
    np.testing.assert_allclose(got, np.rot90(upright, turns, axes=(1, 2)), atol=1e-5)


def test_display_rotation_other_than_quarter_turns_is_not_applied(caplog, monkeypatch):
    from types import SimpleNamespace as NS

    from flyvpr.sources import video
    from flyvpr.sources.video import _display_ops

    monkeypatch.setattr(video, "_WARNED_ANGLES", set())  # each warning is said once
    # the angle alone (no matrix in the side data): a pure turn; PyAV's angle counter-clockwise
    turns = [_display_ops(NS(rotation=r)) for r in (0, -90, 90, 180, -180, 89.6)]
    assert turns == [(), ("clock",), ("cclock",), ("hflip", "vflip"), ("hflip", "vflip"),
                     ("cclock",)]  # fmt: skip
    with caplog.at_level("WARNING", logger="flyvpr"):
        assert _display_ops(NS(rotation=45.0)) == ()
        assert _display_ops(NS()) == ()  # a frame of a PyAV without the attribute
        # a singular matrix: PyAV 18's angle is INT_MIN (NaN in others); no angle to warn of
        assert _display_ops(NS(rotation=-(2**31))) == _display_ops(NS(rotation=float("nan"))) == ()
    assert "rotates it by 45.0 degrees; only multiples of 90" in caplog.text
    assert "2147483648" not in caplog.text and "nan degrees" not in caplog.text
    assert "rotated videos are read as stored: pip install 'av>=14.1'" in caplog.text


def test_a_display_matrix_is_applied_as_the_ffmpeg_command_does():
    # the eight matrices of quarter turns and flips, as ffmpeg's autorotate shows them (checked
    # against ffmpeg itself by a second reader); frame.rotation alone cannot tell a mirror
    from types import SimpleNamespace as NS

    from flyvpr.sources.video import _OPS, _display_ops

    def frame(a, b, c, d, rotation):  # a 16.16 fixed-point display matrix, FFmpeg's layout
        m = np.array([a << 16, b << 16, 0, c << 16, d << 16, 0, 0, 0, 1 << 30], np.int32)
        return NS(rotation=rotation, side_data={"DISPLAYMATRIX": m.tobytes()})

    y = np.arange(12).reshape(3, 4)
    cases = {  # matrix, PyAV's angle: the picture a player shows
        (1, 0, 0, 1, 0.0): y,
        (0, -1, 1, 0, 90.0): np.rot90(y, 1),
        (0, 1, -1, 0, -90.0): np.rot90(y, -1),
        (-1, 0, 0, -1, -180.0): np.rot90(y, 2),
        (-1, 0, 0, 1, -180.0): y[:, ::-1],  # hflip
        (1, 0, 0, -1, 0.0): y[::-1],  # vflip
        (0, 1, 1, 0, -90.0): y.T,  # transpose
        (0, -1, -1, 0, 90.0): y[::-1, ::-1].T,  # anti-transpose
    }
    for (a, b, c, d, rotation), shown in cases.items():
        got = y
        for op in _display_ops(frame(a, b, c, d, rotation)):
            got = _OPS[op](got)
        np.testing.assert_array_equal(got, shown, err_msg=str((a, b, c, d)))


def test_a_stream_s_display_matrix_is_read_once_per_angle(monkeypatch):
    # frame.side_data (the matrix) makes PyAV hold each frame in a reference cycle: it is read
    # on the first frame and again only when the angle changes, which frame.rotation tells
    from flyvpr.sources import video
    from flyvpr.sources.video import _DisplayOps

    class Frame:
        reads = 0

        def __init__(self, matrix, rotation):
            self.matrix, self.rotation = matrix, rotation

        @property
        def side_data(self):
            Frame.reads += 1
            m = [v << 16 for v in self.matrix]
            m = np.array(m[:2] + [0] + m[2:] + [0, 0, 0, 1 << 30], np.int32)
            return {"DISPLAYMATRIX": m.tobytes()}

    vflip, turned, hflip = ((1, 0, 0, -1), 0.0), ((0, 1, -1, 0), -90.0), ((-1, 0, 0, 1), -180.0)
    display = _DisplayOps()
    seen = [display(Frame(*m)) for m in (vflip, vflip, vflip, turned, turned, hflip, vflip)]
    assert seen == [("vflip",)] * 3 + [("clock",)] * 2 + [("hflip",), ("vflip",)]
    assert Frame.reads == 4  # (the first frame, then each change of angle)
    calls = []
    real = video._display_ops
    monkeypatch.setattr(video, "_display_ops", lambda f: calls.append(f.rotation) or real(f))
    nan = _DisplayOps()  # a singular matrix's angle, NaN, is one angle too
    assert [nan(Frame((0, 0, 0, 0), float("nan"))) for _ in range(3)] == [()] * 3
    assert len(calls) == 1


def test_decoded_video_frames_are_freed_at_once(route, tmp_path):
    # each picture is freed when the batch that decoded it is done, not left to the cyclic
    # garbage collector (reading every frame's side data kept them: 95 MB more at 640 x 480)
    import gc

    import av

    path = write_video(tmp_path / "v.mp4", _rgb(route), fps=10)
    src = open_source(path)
    gc.collect()
    gc.disable()
    try:
        # (type(), not isinstance: a dead weak proxy among the objects raises on __class__;
        # frames other tests left alive are counted out)
        before = sum(type(o) is av.VideoFrame for o in gc.get_objects())
        n = 0
        for batch in src.batches(SIZE):
            n += len(batch.images)
        alive = sum(type(o) is av.VideoFrame for o in gc.get_objects()) - before
    finally:
        gc.enable()
    assert n == N and alive <= 1  # (the first frame, whose matrix was read)


def test_several_video_streams_read_the_default_one(route, tmp_path, caplog):
    # stream 0: a small preview (5 frames); stream 1: the main track, flagged default
    small = np.stack([f[::2, ::2] for f in _rgb(route, "winter", 5)])
    path = write_av(
        tmp_path / "two.mkv",
        [{"frames": small, "default": False}, {"frames": _rgb(route), "default": True}],
    )
    with caplog.at_level("INFO", logger="flyvpr"):
        src = open_source(path)
    assert "reading video stream #1 (ffv1 128x64, default), the one FFmpeg would play, of 2" in (
        caplog.text
    )
    got = src.read_all(SIZE)
    assert len(got) == N
    assert np.abs(got.images - _upright(route)).mean() < 0.01
    # with one video stream nothing is said
    caplog.clear()
    with caplog.at_level("INFO", logger="flyvpr"):
        open_source(write_av(tmp_path / "one.mkv", [{"frames": _rgb(route, n=3)}]))
    assert "video stream #" not in caplog.text


def _navsat_bag(path, fixes):
    """A ROS 1 bag of NavSatFix messages: (t, latitude, longitude, status) each."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    with Writer(path) as w:
        conn = w.add_connection("/fix", "sensor_msgs/msg/NavSatFix", typestore=ts)
        for i, (t, lat, lon, status) in enumerate(fixes):
            stamp = T["builtin_interfaces/msg/Time"](sec=int(t), nanosec=int(t % 1 * 1e9))
            msg = T["sensor_msgs/msg/NavSatFix"](
                header=T["std_msgs/msg/Header"](seq=i, stamp=stamp, frame_id="gps"),
                status=T["sensor_msgs/msg/NavSatStatus"](status=status, service=1),
                latitude=lat, longitude=lon, altitude=0.0,
                position_covariance=np.zeros(9), position_covariance_type=0,
            )  # fmt: skip
            w.write(conn, int(t * 1e9), ts.serialize_ros1(msg, "sensor_msgs/msg/NavSatFix"))
    return path


def test_navsatfix_without_a_fix_is_skipped(tmp_path, caplog):
    from flyvpr.sources.rosbag import EARTH_RADIUS_M, read_bag_positions

    # a receiver's first messages before its first fix: STATUS_NO_FIX (-1) at 0, 0; then fixes
    # at latitude 60 moving 2 m east each; one of them NaN
    east = np.degrees(2.0 / (EARTH_RADIUS_M * np.cos(np.radians(60.0))))
    fixes = [(100.0 + i, 0.0, 0.0, -1) for i in range(4)]
    fixes += [(104.0 + k, 60.0, 10.0 + k * east, 0) for k in range(6)]
    fixes[6] = (106.0, float("nan"), float("nan"), 0)
    with caplog.at_level("WARNING", logger="flyvpr"):
        t, xy = read_bag_positions(_navsat_bag(tmp_path / "gps.bag", fixes), "/fix")
    np.testing.assert_array_equal(t, [104, 105, 107, 108, 109])
    # metres from the first fix, not from (0, 0), on the scale of latitude 60
    np.testing.assert_allclose(xy, np.c_[[0, 2, 6, 8, 10], np.zeros(5)], atol=1e-6)
    assert (
        f"bag {tmp_path / 'gps.bag'} topic /fix: skipped 4 without a fix (status < 0) and 1 "
        "with a non-finite position of 10 position messages"
    ) in caplog.text
    # as positions of a recording, the same
    pos = read_positions(bag=tmp_path / "gps.bag", topic="/fix")
    np.testing.assert_allclose(pos.xy[:, 0], [0, 2, 6, 8, 10], atol=1e-6)


def test_navsatfix_that_never_fixed_is_refused(tmp_path):
    bag = _navsat_bag(tmp_path / "nofix.bag", [(100.0 + i, 0.0, 0.0, -1) for i in range(3)])
    with pytest.raises(
        RecordingError,
        match=r"nofix\.bag topic /fix: no usable position \(3 messages: 3 without a fix "
        r"\(status < 0\)\)",
    ):
        read_positions(bag=bag, topic="/fix")


def test_every_metres_with_no_frame_placed_names_both_spans(tmp_path):
    # GPS on another clock: the message gives the recording's timestamps beside the rows'
    gps = Positions(np.array([5000.0, 5001.0]), np.zeros((2, 2)), "timestamp", "gps.csv")
    with pytest.raises(RecordingError) as info:
        _Stamped(tmp_path / "cam", 100.0 + 0.5 * np.arange(8)).read_all(
            SIZE, every="2m", positions=gps
        )
    assert str(info.value).endswith(
        "every=2m keeps frames by distance, and no frame has a position in gps.csv (its rows: "
        "timestamps 5000-5001 s; its frames' timestamps 100-103.5 s): the positions and the "
        "recording must share a clock"
    )
    # rows by frame, none of this recording's
    by_frame = Positions(np.array([50, 60]), np.zeros((2, 2)), "frame", "f.csv")
    with pytest.raises(RecordingError, match=r"\(its rows: frames 50-60; its frames 0-7\): a "):
        _Stamped(tmp_path / "cam", np.arange(8.0)).read_all(SIZE, every="2m", positions=by_frame)
