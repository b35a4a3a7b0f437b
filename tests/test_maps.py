"""Map properties that need no recording: the spacing between places; the positions a map
built from a recording gives its places; what a map of a video records of the decoding of its
frames, and the warning on maps from before it."""

from __future__ import annotations

import json
import logging
import warnings

import numpy as np
import pytest

from flyvpr.localization.maps import Map
from flyvpr.sources import Positions, Source


def _map(positions):
    n = 5 if positions is None else len(positions)
    return Map(None, (32, 64), np.zeros(n), np.arange(n), positions)


@pytest.mark.parametrize(
    "positions, spacing",
    [
        (None, None),
        ([[0, 0], [3, 4]], 5.0),
        ([[0, 0], [3, 4], [3, 6], [3, 9]], 3.0),  # steps 5, 2, 3: the median, not the mean
        ([[0, 0], [3, 4], [3, 6], [3, 7]], 2.0),  # steps 5, 2, 1
        ([[0, 0], [0, 1], [0, 4], [0, 8], [0, 9]], 2.0),  # steps 1, 3, 4, 1: mean of the middle
        # only neighbours that both have a position: steps 5 and 2 (not 10 across the gap)
        ([[0, 0], [3, 4], [np.nan, np.nan], [9, 12], [9, 14]], 3.5),
        ([[0, 0], [np.nan, 1.0], [2, 0]], None),  # no two neighbours with positions
        ([[np.nan, np.nan]] * 3, None),
        ([[1, 1]] * 4, None),  # a map recorded standing still has no spacing
    ],
)
def test_place_spacing_is_the_median_step_between_neighbours(positions, spacing):
    m = _map(None if positions is None else np.array(positions, dtype=np.float64))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "mean of empty slice" on the way to None
        assert m.place_spacing == spacing
    if spacing is not None:
        assert type(m.place_spacing) is float


@pytest.mark.parametrize(
    "positions, breaks",
    [
        (None, ()),
        ([[0, 0], [2, 0], [4, 0], [6, 0], [60, 0], [62, 0]], (4,)),  # a step of 54 over 2
        ([[0, 0], [2, 0], [4, 0], [14, 0], [16, 0]], ()),  # 10: 5 times the spacing, no more
        ([[0, 0], [2, 0], [4, 0], [14.1, 0], [16.1, 0]], (3,)),
        ([[0, 0], [2, 0], [4, 0], [4, 30], [4, 32], [0, 0]], (3, 5)),  # (positions, not x)
        # a step with an unknown end is not judged (the spacing: steps 2, 2 and 2)
        ([[0, 0], [2, 0], [np.nan, np.nan], [50, 0], [52, 0], [54, 0]], ()),
        ([[1, 1]] * 4, ()),  # (no spacing: nothing to judge a jump by)
        # a stretch driven six times faster (a map kept by time) is no break: the usual step
        # is the median of the 5 steps on either side, not the map's spacing
        (np.c_[np.cumsum([0] + [2] * 8 + [12] * 8), np.zeros(17)], ()),
        (np.c_[np.cumsum([0] + [12] * 8 + [61] + [12] * 8), np.zeros(18)], (9,)),
    ],
)
def test_breaks_are_where_the_positions_jump_more_than_five_usual_steps(positions, breaks):
    m = _map(None if positions is None else np.array(positions, dtype=np.float64))
    assert m.breaks == breaks
    assert all(type(b) is int for b in m.breaks)


@pytest.mark.parametrize(
    "field, value, match",
    [
        (
            "timestamps",
            np.zeros(3),
            r"timestamps must have shape \(5,\), one entry a place .*\(3,\)",
        ),
        ("positions", np.zeros((4, 2)), r"positions must have shape \(5, 2\).*got \(4, 2\)"),
        ("positions", np.zeros((5, 3)), r"positions must have shape \(5, 2\).*got \(5, 3\)"),
        ("thumbnails", np.zeros((3, 8, 8), np.uint8), r"thumbnails must have shape \(5, H, W\)"),
        ("thumbnails", np.zeros((5, 8), np.uint8), r"thumbnails must have shape \(5, H, W\)"),
        ("source_index", np.arange(0), r"source_index must have shape \(n_places,\)"),
        ("source_index", np.zeros((5, 1)), r"source_index must have shape \(n_places,\)"),
    ],
)
def test_a_map_refuses_arrays_that_do_not_hold_one_entry_a_place(field, value, match):
    args = {"timestamps": np.zeros(5), "source_index": np.arange(5), "positions": None,
            "thumbnails": np.zeros((5, 8, 8), np.uint8)}  # fmt: skip
    args[field] = value
    with pytest.raises(ValueError, match=match):
        Map(None, (32, 64), **args)


def test_a_map_of_a_fitted_method_has_its_places(synthetic_route):
    from flyvpr.methods import make_method

    ref = synthetic_route(20, random_state=0).reference_images
    method = make_method("pixels", 0).fit(ref)
    assert Map(method, (32, 64), np.zeros(20), np.arange(20)).n_places == 20
    with pytest.raises(ValueError, match=r"source_index must have shape \(20 \(the method's pl"):
        Map(method, (32, 64), np.zeros(19), np.arange(19))


class _Camera(Source):
    """``images`` as a 10 Hz recording from t = 1000 s (frame i at 1000 + i / 10)."""

    kind = "camera"

    def __init__(self, path, images):
        super().__init__(path)
        self.images = images

    def _frames(self):
        for i, image in enumerate(self.images):
            yield i, 1000 + i / 10, lambda size, image=image: image


def _gps(t):
    """Positions at the times ``t``: the robot drives 20 m/s along x."""
    t = np.asarray(t, np.float64)
    return Positions(t, np.c_[(t - 1000) * 20, np.zeros(len(t))], "timestamp", "gps")


@pytest.mark.parametrize("compact", [False, True])
def test_a_map_interpolates_positions_slower_than_the_camera(synthetic_route, tmp_path, compact):
    # a 10 Hz camera and 1 Hz positions: each place gets its point on the way (2 m apart),
    # not the nearest fix's (steps of 0 and 20 m, whose median gave the map no spacing)
    src = _Camera(tmp_path / "cam", synthetic_route(40, random_state=0).reference_images)
    gps = _gps(1000.0 + np.arange(5))
    if compact:
        from flyvpr.large.recording import build_compact_map

        m = build_compact_map(src, tmp_path / "m.fvmap", positions=gps, n_bits=64)
    else:
        m = Map.build(src, "pixels", positions=gps)
    np.testing.assert_allclose(m.positions, np.c_[2.0 * np.arange(40), np.zeros(40)], atol=1e-9)
    assert m.place_spacing == pytest.approx(2.0)


@pytest.mark.parametrize("compact", [False, True])
def test_a_map_leaves_places_in_a_gap_of_its_positions_without_one(
    synthetic_route, tmp_path, compact
):
    # 20 Hz positions with 2 s missing (from 1001.5 to 1003.5): the places recorded then have
    # none, as places before the first fix have none (not the fix next to them, nor a line
    # across, up to 20 m off)
    t = 1000 + np.r_[0:30, 70:80] / 20
    src = _Camera(tmp_path / "cam", synthetic_route(40, random_state=0).reference_images)
    if compact:
        from flyvpr.large.recording import build_compact_map

        m = build_compact_map(src, tmp_path / "m.fvmap", positions=_gps(t), n_bits=64)
    else:
        m = Map.build(src, "pixels", positions=_gps(t))
    unplaced = np.flatnonzero(np.isnan(m.positions).any(axis=1)).tolist()
    assert unplaced == list(range(15, 35))
    np.testing.assert_allclose(m.positions[[14, 35], 0], [28, 70], atol=1e-9)
    assert m.place_spacing == pytest.approx(2.0)


# -- a map of a video records how its frames were decoded ----------------------------------------
def _drive_frames(synthetic_route):
    """20 frames of a drive as 8-bit RGB (the synthetic route's reference images, in gray)."""
    gray = np.rint(synthetic_route(20, random_state=0).reference_images * 255).astype(np.uint8)
    return np.repeat(gray[..., None], 3, axis=-1)


@pytest.fixture
def drive_video(synthetic_route, tmp_path):
    pytest.importorskip("av")
    from videos import write_av

    return write_av(tmp_path / "drive.mkv", [{"frames": _drive_frames(synthetic_route)}])


@pytest.fixture
def drive_folder(synthetic_route, tmp_path):
    from PIL import Image

    folder = tmp_path / "drive"
    folder.mkdir()
    for i, rgb in enumerate(_drive_frames(synthetic_route)):
        Image.fromarray(rgb).save(folder / f"{i:03d}.png")
    return folder


def _build(source, path, compact):
    """Build a map of ``source`` and write it to ``path``; return what the file stores of
    where its places came from (the ``map`` section, or the compact map's metadata)."""
    if compact:
        from flyvpr.large.recording import build_compact_map

        return build_compact_map(source, path, n_bits=64).large_map.metadata
    Map.build(source, "pixels+cann").save(path)
    with np.load(path, allow_pickle=False) as z:
        return json.loads(z["__meta__"].tobytes())["map"]


def _open(path, compact):
    if compact:
        from flyvpr.large.recording import open_compact_map

        return open_compact_map(path)
    return Map.load(path)


def _places(m, compact, frames):
    """The places a localizer on the opened map ``m`` answers for ``frames``."""
    if compact:
        from flyvpr.large.recording import compact_localizer

        loc = compact_localizer(m)
        return np.array([loc.update(f).place for f in frames])
    from flyvpr.localization import Localizer

    return Localizer.from_map(m).update_batch(frames).places


def _with_info(path, out, edit, compact):
    """The map file ``path`` written again to ``out`` with ``edit`` applied to its ``map``
    section (a compact map: its metadata), every checksum recomputed: what an older flyvpr
    wrote, or a file crafted by one who knows the format."""
    if compact:
        from flyvpr.large import LargeMapWriter, open_large_map

        m = open_large_map(path)
        meta = dict(m.metadata)
        edit(meta)
        pos = None if m.positions is None else np.asarray(m.positions)
        n_dims = None if pos is None else pos.shape[1]
        with LargeMapWriter(out, m.n_places, m.codes.shape[1], n_dims, meta) as w:
            w.append(np.asarray(m.codes), pos)
            for name, array in m.arrays.items():
                if name not in ("codes", "positions"):
                    w.add_array(name, np.asarray(array))
        return out
    from flyvpr.modelio import _write_archive

    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files if k != "__meta__"}
        meta = json.loads(z["__meta__"].tobytes())
    edit(meta["map"])
    return _write_archive(out, meta, arrays)


def _warnings(caplog):
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


@pytest.mark.parametrize("compact", [False, True])
def test_a_map_of_a_video_records_how_its_frames_were_decoded(
    drive_video, tmp_path, caplog, compact
):
    from flyvpr.sources.video import _DECODE_VERSION

    path = tmp_path / "m.map"
    with caplog.at_level("WARNING", logger="flyvpr"):
        stored = _build(drive_video, path, compact)
        m = _open(path, compact)
    assert stored["source_kind"] == "video" and stored["video_decode"] == _DECODE_VERSION == 2
    assert m.info["video_decode"] == _DECODE_VERSION
    assert _warnings(caplog) == []


@pytest.mark.parametrize("compact", [False, True])
@pytest.mark.parametrize(
    "edit",
    [lambda info: info.pop("video_decode"), lambda info: info.update(video_decode=1)],
    ids=["without the field", "version 1"],
)
def test_a_map_of_a_video_from_before_rotation_warns_once_and_still_localizes(
    drive_video, tmp_path, caplog, compact, edit
):
    from flyvpr.sources import open_source

    path = tmp_path / "new.map"
    _build(drive_video, path, compact)
    old = _with_info(path, tmp_path / "old.map", edit, compact)
    frames = open_source(drive_video).read_all((32, 64)).images
    with caplog.at_level("WARNING", logger="flyvpr"):
        m = _open(old, compact)
    (message,) = _warnings(caplog)
    command = "flyvpr map --compact" if compact else "flyvpr map"
    assert message == (
        f"map file {old} was built from a video before flyvpr applied a video's rotation: its "
        "places are the frames as stored, while query frames now come upright; if the video "
        "was recorded rotated (a phone held sideways, a camera mounted upside down), rebuild "
        f"the map with `{command}`"
    )
    assert m.info.get("video_decode", 1) == 1
    places = _places(m, compact, frames)
    np.testing.assert_array_equal(places, _places(_open(path, compact), compact, frames))
    assert np.mean(places == np.arange(20)) > 0.8


@pytest.mark.parametrize("compact", [False, True])
def test_a_map_of_a_folder_never_warns(drive_folder, tmp_path, caplog, compact):
    path = tmp_path / "m.map"
    with caplog.at_level("WARNING", logger="flyvpr"):
        stored = _build(drive_folder, path, compact)
        m = _open(path, compact)
    assert stored["source_kind"] == "image folder" and "video_decode" not in stored
    assert "video_decode" not in m.info
    assert _warnings(caplog) == []


@pytest.mark.parametrize(
    "kind, version, warns",
    [
        ("video", None, True),
        ("video", 1, True),
        ("video", 2, False),
        ("video", 3, False),
        ("image folder", None, False),
        ("bag", None, False),
        ("camera", None, False),
        ("", None, False),
    ],
)
def test_only_maps_of_a_video_decoded_as_stored_warn(caplog, kind, version, warns):
    from flyvpr.localization.maps import _warn_unrotated

    info = {"source_kind": kind} | ({} if version is None else {"video_decode": version})
    with caplog.at_level("WARNING", logger="flyvpr"):
        _warn_unrotated("route.map", info)
    assert len(_warnings(caplog)) == warns


def test_a_changed_video_decode_fails_the_checksum(drive_video, tmp_path, monkeypatch):
    from flyvpr import modelio
    from flyvpr.modelio import ModelFileError, _write_archive

    path = tmp_path / "m.map"
    _build(drive_video, path, compact=False)
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays.pop("__meta__").tobytes())
    meta["map"]["video_decode"] = 1
    # changed as any other field: the file's checksum fails ...
    edited = tmp_path / "edited.map"
    blob = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    with open(edited, "wb") as fh:  # (np.savez adds .npz to a name)
        np.savez(fh, __meta__=blob, **arrays)
    with pytest.raises(ModelFileError, match=r"edited\.map failed its file checksum"):
        Map.load(edited)
    # ... and sealed again, the content's (the field is part of what it covers)
    stored = meta["checksum"]
    monkeypatch.setattr(modelio, "_checksum", lambda meta, arrays: stored)
    _write_archive(tmp_path / "sealed.map", meta, arrays)
    monkeypatch.undo()
    with pytest.raises(ModelFileError, match=r"sealed\.map: checksum: content checksum mismatch"):
        Map.load(tmp_path / "sealed.map")


def test_a_changed_video_decode_fails_the_compact_maps_id(drive_video, tmp_path):
    from flyvpr.large import MapFileError
    from flyvpr.large.recording import build_compact_map, open_compact_map

    path = build_compact_map(drive_video, tmp_path / "m.fvmap", n_bits=64).path
    raw = path.read_bytes()
    assert raw.count(b'"video_decode": 2') == 1
    path.write_bytes(raw.replace(b'"video_decode": 2', b'"video_decode": 1'))
    with pytest.raises(MapFileError, match=r"m\.fvmap: the content does not match the file's"):
        open_compact_map(path)


@pytest.mark.parametrize("compact", [False, True])
@pytest.mark.parametrize("value", ["2", True, 2.0, 0, None])
def test_a_crafted_video_decode_is_refused(drive_video, tmp_path, compact, value):
    path = tmp_path / "m.map"
    _build(drive_video, path, compact)
    bad = _with_info(
        path, tmp_path / "bad.map", lambda info: info.update(video_decode=value), compact
    )
    if compact:
        match = r"bad\.map: metadata\.video_decode must be an integer >= 1; got "
    else:
        match = r"bad\.map: map\.video_decode: (has the wrong type|must be >= 1)"
    with pytest.raises(ValueError, match=match):
        _open(bad, compact)
