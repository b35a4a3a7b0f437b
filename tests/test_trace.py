"""Traces of a localization run: the drawing helpers, the HTML page and the video."""

import base64
import json
from types import SimpleNamespace

import numpy as np
import pytest

from flyvpr.localization.trace import HTML_BINS, _bars, _binned, _normalised, _upscale, open_trace
from flyvpr.localization.tracking import Step
from flyvpr.sources.base import Batch

N_PLACES = 40


def _map(thumbnails=True):
    rng = np.random.default_rng(0)
    thumbs = rng.integers(0, 256, size=(N_PLACES, 8, 16), dtype=np.uint8) if thumbnails else None
    return SimpleNamespace(n_places=N_PLACES, thumbnails=thumbs, size=(8, 16))


def _step(first=0, n=5, lost=(1,), relocated=(3,), timestamps=True):
    rng = np.random.default_rng(first)
    images = rng.random((n, 8, 16), dtype=np.float32)
    t = np.arange(first, first + n, dtype=np.float64) / 10 if timestamps else np.full(n, np.nan)
    batch = Batch(images, t, np.arange(first, first + n, dtype=np.int64))
    scores = rng.random((n, N_PLACES)).astype(np.float32)
    places = scores.argmax(axis=1)
    states = np.array(["lost" if i in lost else "localized" for i in range(n)])
    reloc = np.array([i in relocated for i in range(n)])
    return Step(batch, places, scores.max(axis=1), scores, reloc, states, None)


def test_upscale_is_nearest_neighbour():
    img = np.array([[1, 2], [3, 4]], np.uint8)
    np.testing.assert_array_equal(
        _upscale(img, 4, 6),
        np.array([[1, 1, 1, 2, 2, 2]] * 2 + [[3, 3, 3, 4, 4, 4]] * 2, np.uint8),
    )


@pytest.mark.parametrize("n, bins", [(10, 4), (7, 7), (3, 8), (1000, 256)])
def test_binned_is_the_maximum_over_each_bin(n, bins):
    row = np.random.default_rng(n).random(n)
    got = _binned(row, bins)
    assert got.shape == (bins,)
    starts = np.arange(bins) * n // bins
    for b in range(bins):
        stop = starts[b + 1] if b + 1 < bins else n
        expected = row[starts[b] : max(stop, starts[b] + 1)].max() if n >= bins else row[starts[b]]
        assert got[b] == expected
    assert got.max() == row.max()  # every place is in a bin


def test_normalised():
    np.testing.assert_allclose(_normalised(np.array([2.0, 4.0, 3.0])), [0.0, 1.0, 0.5])
    np.testing.assert_array_equal(_normalised(np.array([5.0, 5.0])), [0.0, 0.0])


def test_bars_fill_from_the_bottom():
    panel = _bars(np.array([0.0, 1.0, 0.5]), 5, np.array([1, 2, 3], np.uint8))
    assert panel.shape == (5, 3, 3)
    coloured = (panel == [1, 2, 3]).all(axis=2)
    assert coloured[:, 0].sum() == 1 and coloured[-1, 0]  # height 0: the bottom row
    assert coloured[:, 1].all()  # height 1: the whole column
    assert coloured[:, 2].sum() == 3 and coloured[2:, 2].all()


def _page_data(path):
    text = path.read_text()
    start = text.index("const D = ") + len("const D = ")
    return json.loads(text[start : text.index(";\n", start)])


@pytest.mark.parametrize("thumbnails", [True, False])
def test_html_trace_holds_every_frame(tmp_path, thumbnails):
    m = _map(thumbnails)
    steps = [_step(0, 5), _step(5, 3, lost=(), relocated=(0,), timestamps=False)]
    path = tmp_path / "trace.html"
    with open_trace(path, m) as trace:
        for step in steps:
            trace.add(step)
    data = _page_data(path)
    assert data["n_places"] == N_PLACES and data["bins"] == HTML_BINS
    assert (data["h"], data["w"]) == (8, 16)
    rows = data["rows"]
    assert [r[0] for r in rows] == list(range(8))
    assert rows[1][5] == "lost" and rows[0][5] == "localized"
    assert rows[3][4] is True and rows[5][4] is True and rows[4][4] is False
    assert rows[2][1] == pytest.approx(0.2) and rows[6][1] is None  # no timestamp: null
    places = np.concatenate([s.places for s in steps])
    assert [r[2] for r in rows] == places.tolist()
    activity = np.frombuffer(base64.b64decode(data["activity"]), np.uint8).reshape(8, HTML_BINS)
    scores = np.concatenate([s.scores for s in steps])
    of_bin = np.arange(HTML_BINS) * N_PLACES // HTML_BINS  # the place each bin shows
    for i in range(8):  # the matched place's bins are the brightest
        assert (activity[i, of_bin == places[i]] == 255).all()
        expected = np.rint(_normalised(_binned(scores[i].astype(np.float64), HTML_BINS)) * 255)
        np.testing.assert_array_equal(activity[i], expected)
    assert data["queries"].startswith("data:image/png;base64,")


def test_a_failed_run_leaves_no_trace(tmp_path):
    path = tmp_path / "trace.html"
    with pytest.raises(RuntimeError, match="boom"):
        with open_trace(path, _map()) as trace:
            trace.add(_step())
            raise RuntimeError("boom")
    assert not path.exists() and list(tmp_path.iterdir()) == []


def test_video_trace_has_a_frame_per_step_frame(tmp_path):
    av = pytest.importorskip("av")
    path = tmp_path / "trace.mp4"
    with open_trace(path, _map()) as trace:
        trace.add(_step(0, 4))
        trace.add(_step(4, 3))
    with av.open(str(path)) as container:
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(frames) == 7
    assert frames[0].shape == (16 + 128 + 2 * 64, 512, 3)
    assert trace.n == 7


def _cann_map():
    """A map whose method's filter reports a state: its confidence is a probability."""
    m = _map()
    m.method = SimpleNamespace(filter=SimpleNamespace(state_="lost"))
    return m


def test_a_probability_is_drawn_on_its_own_scale_and_a_score_from_low_to_high(tmp_path):
    path = tmp_path / "trace.html"
    with open_trace(path, _cann_map()) as trace:
        trace.add(_step(0, 5))
    assert _page_data(path)["probabilities"] is True
    with open_trace(path, _map()) as trace:  # no filter state: raw scores
        trace.add(_step(0, 5))
    assert _page_data(path)["probabilities"] is False


def test_video_confidence_bars_keep_their_height_and_show_under_a_relocation(tmp_path):
    pytest.importorskip("av")
    green, red = np.array([60, 180, 90]), np.array([220, 50, 50])
    with open_trace(tmp_path / "trace.mp4", _cann_map()) as trace:
        first = _step(0, 5, relocated=(3,))
        trace.add(first)
        # the last plot (confidence over time) of the last frame drawn: a column per frame
        panel = trace._draw(first, 4)[-64:]
        heights = (panel == green).all(axis=2).sum(axis=0)
        # frame k's bar is column 512 - 5 + k, as high as its confidence: 1 + 63 rows at 1
        expected = 1 + np.rint(first.confidences * 63).astype(int)
        assert (panel[:6, 512 - 5 + 3] == red).all()  # a tick above the relocation's bar ...
        heights[512 - 5 + 3] += 6 - (64 - expected[3])  # ... over the bar's top rows
        np.testing.assert_array_equal(heights[-5:], expected)
        later = _step(5, 3, relocated=())
        later.confidences[:] = 0.01  # low confidences after: the earlier bars keep their height
        trace.add(later)
        panel = trace._draw(later, 2)[-64:]
        heights = (panel == green).all(axis=2).sum(axis=0)
        heights[512 - 8 + 3] += 6 - (64 - expected[3])
        np.testing.assert_array_equal(heights[-8:-3], expected)
