"""The CANN on a window of a large map (WindowedCANN)."""

import numpy as np
import pytest

from flyvpr.temporal.cann import CANN, WindowedCANN
from flyvpr.temporal.cann._window import _shift, _shift_tied
from oracles import odometry_scale


def _route(n_query=200, n_places=3000, start=500, speed=1.0, strength=3.0, seed=0):
    """Noise scores with the true place (start + speed t) raised: a robot on the route."""
    rng = np.random.default_rng(seed)
    S = rng.normal(size=(n_query, n_places)).astype(np.float32)
    truth = (start + np.floor(speed * np.arange(n_query))).astype(int)
    S[np.arange(n_query), truth] += strength
    return S, truth


def _run(f, S, velocity=None):
    places, states = [], []
    for t, row in enumerate(S):
        lo, hi = f.window_
        v = None if velocity is None or t == 0 else velocity
        p, c, s = f.step(row[lo:hi], v)
        assert 0.0 <= c <= 1.0
        places.append(p)
        states.append(s)
    return np.array(places), np.array(states)


def test_a_map_within_the_window_is_the_cann_exactly():
    S, _ = _route(n_query=80, n_places=300, start=20)
    full = CANN(tolerance=2).filter(S)
    f = WindowedCANN(300, window=512, tolerance=2)
    assert f.width == 300 and f.window_ == (0, 300)
    for t, row in enumerate(S):
        place, confidence, state = f.step(row)
        assert place == int(full[t].argmax())
        assert confidence == pytest.approx(float(full[t].max()), rel=1e-6)
    assert f.n_moves_ == 0


def test_the_window_follows_a_localized_packet_along_the_map():
    S, truth = _route(n_query=400, n_places=3000, start=500)
    f = WindowedCANN(3000, window=256)
    f.reseed([500])
    places, states = _run(f, S)
    right = np.abs(places - truth) <= 2
    assert right[20:].mean() > 0.97
    assert (states[20:] == "localized").mean() > 0.9
    lo, hi = f.window_
    assert lo <= truth[-1] < hi and hi - lo == 256
    assert f.n_moves_ >= 400 // (256 // 8) - 2  # moved in steps of about recentre * window


@pytest.mark.parametrize(("start", "speed"), [(300, 1.0), (1700, -1.0)])
def test_on_the_places_it_covers_the_window_agrees_with_the_whole_map_filter(start, speed):
    # forwards, and reversing along the map (the sequence test then takes the packet's own
    # place, from the layer's velocity, which the window carries across its moves)
    S, truth = _route(n_query=300, n_places=2000, start=start, speed=speed, seed=3)
    full = CANN().filter(S).argmax(axis=1)
    f = WindowedCANN(2000, window=512)
    f.reseed([start])
    places, _ = _run(f, S)
    assert (places[10:] == full[10:]).mean() > 0.98
    assert f.n_moves_ >= 3
    if speed < 0:
        assert f.cann_.velocity_ < 0 and (np.abs(places - truth) <= 2)[20:].mean() > 0.97


def test_odometry_moves_the_window_too():
    S, truth = _route(n_query=300, n_places=2000, start=100, speed=0.5)
    f = WindowedCANN(2000, window=128)
    f.reseed([100])
    places, _ = _run(f, S, velocity=0.5)
    assert (np.abs(places - truth) <= 2)[10:].mean() > 0.97
    assert f.cann_.velocity_ == pytest.approx(0.5 * odometry_scale(f.cann_))  # the odometry, scaled


def test_a_lost_filter_keeps_its_window_until_reseeded():
    S, truth = _route(n_query=150, n_places=4000, start=3000)
    f = WindowedCANN(4000, window=256)  # starts at 0..255: the robot is elsewhere
    places, states = _run(f, S[:60])
    assert f.window_ == (0, 256) and f.n_moves_ == 0
    assert (states == "lost").mean() > 0.9
    f.reseed([1200, 3059, 2000], weights=[0.2, 1.0, 0.1])
    assert f.window_ == (3059 - 128, 3059 + 128) and f.place_ == 3059 and f.state_ == "lost"
    places, states = _run(f, S[60:])
    assert (np.abs(places - truth[60:]) <= 2)[10:].mean() > 0.97
    assert states[-1] == "localized"


def test_the_window_stops_at_the_ends_of_the_map():
    f = WindowedCANN(1000, window=200)
    f.reseed([990])
    assert f.window_ == (800, 1000)
    f.reseed([3])
    assert f.window_ == (0, 200)
    f._move(5000)
    assert f.window_ == (800, 1000)


def test_reseed_puts_the_mass_on_the_candidates():
    f = WindowedCANN(1000, window=100)
    f.reseed([500, 520, 900], weights=[1.0, 3.0, 5.0])  # 900 is the best: the window is there
    assert f.window_ == (850, 950)
    marginal = f.cann_._p.sum(axis=0)
    assert marginal.sum() == pytest.approx(1.0, rel=1e-5)
    assert int(np.argmax(marginal)) == 50
    assert marginal[50] == pytest.approx(0.9 + 0.1 / 100, rel=1e-5)  # the only one inside
    f.reseed([500, 520], weights=[1.0, 3.0])
    marginal = f.cann_._p.sum(axis=0)
    lo = f.window_[0]
    assert marginal[520 - lo] == pytest.approx(3 * (marginal[500 - lo] - 0.001) + 0.001, rel=1e-4)
    assert f.n_moves_ == 2


def test_moving_carries_the_state_and_fills_what_enters():
    f = WindowedCANN(1000, window=100)
    f.reseed([50])
    c = f.cann_
    c._mean[:] = np.arange(100, dtype=np.float32)
    c._var[:] = 2.0
    c._front_mean[:] = -np.arange(100, dtype=np.float32)  # (the front end's own, adapt_front)
    c._front_var[:] = 3.0
    before = c._p.copy()
    f._move(f.window_[0] + 10)
    np.testing.assert_array_equal(c._mean[:90], np.arange(10, 100, dtype=np.float32))
    np.testing.assert_array_equal(c._mean[90:], 0.0)
    np.testing.assert_array_equal(c._var[:90], 2.0)
    np.testing.assert_array_equal(c._var[90:], 1.0)
    np.testing.assert_array_equal(c._front_mean[:90], -np.arange(10, 100, dtype=np.float32))
    np.testing.assert_array_equal(c._front_mean[90:], 0.0)
    np.testing.assert_array_equal(c._front_var[:90], 3.0)
    np.testing.assert_array_equal(c._front_var[90:], 1.0)
    np.testing.assert_array_equal(c._p[:, :90], before[:, 10:])
    np.testing.assert_array_equal(c._p[:, 90:], np.repeat(before.min(axis=1)[:, None], 10, 1))
    # the last frame's row and answer and the map's ties move with the places
    c._last_row[:] = np.arange(100.0)
    c._last_out[:] = np.arange(100, dtype=np.float32)
    c._tied = np.array([3, 15, 60, 97], np.int32)
    f._move(f.window_[0] - 5)
    np.testing.assert_array_equal(c._last_row, np.r_[np.zeros(5), np.arange(95.0)])
    np.testing.assert_array_equal(c._last_out, np.r_[np.zeros(5), np.arange(95.0)])
    assert c._tied.dtype == np.int32 and c._tied.tolist() == [1, 2, 3, 4, 5, 8, 20, 65]
    f._move(f.window_[0] + 60)
    assert c._tied.tolist() == [5, *range(40, 100)]
    # the front end's last best place (for the snap) moves with the places; unknown stays so
    c._last_front = 70
    f._move(f.window_[0] + 8)
    assert c._last_front == 62
    c._last_front = None
    f._move(f.window_[0] - 8)
    assert c._last_front is None


def test_a_repeated_frame_is_held_in_the_window_too():
    # the window moved along the route, then the robot stands: its repeated frame is held
    S, truth = _route(n_query=200, n_places=3000, start=500)
    S = np.r_[S, np.repeat(S[-1:], 20, 0)]
    f = WindowedCANN(3000, window=256)
    f.reseed([500])
    places, states = _run(f, S)
    assert f.n_moves_ > 3 and f.cann_.n_held_ == 20
    assert (places[200:] == places[199]).all() and (states[200:] == states[199]).all()
    assert abs(places[-1] - truth[-1]) <= 2


@pytest.mark.parametrize("d", [-7, -1, 0, 1, 7, 10, 12, -12])
def test_shift(d):
    a = np.arange(10.0)
    expected = np.array([a[i + d] if 0 <= i + d < 10 else -1.0 for i in range(10)])
    _shift(a, d, -1.0)
    np.testing.assert_array_equal(a, expected)


def test_errors():
    with pytest.raises(ValueError, match="n_places"):
        WindowedCANN(0)
    with pytest.raises(ValueError, match="window"):
        WindowedCANN(100, window=8)
    with pytest.raises(ValueError, match="recentre"):
        WindowedCANN(100, recentre=0.5)
    with pytest.raises(ValueError, match="tolerance"):
        WindowedCANN(100, tolerance=-1)
    f = WindowedCANN(1000, window=100)
    with pytest.raises(ValueError, match=r"100 places of window_ \(0, 100\)"):
        f.step(np.zeros(1000))
    with pytest.raises(ValueError, match="NaN"):
        f.step(np.full(100, np.nan))
    with pytest.raises(ValueError, match=r"places must lie in \[0, 1000\)"):
        f.reseed([1000])
    with pytest.raises(ValueError, match="integers"):
        f.reseed([1.5])
    with pytest.raises(ValueError, match="integers"):
        f.reseed([])
    with pytest.raises(ValueError, match="weights"):
        f.reseed([1, 2], weights=[0.0, 0.0])
    with pytest.raises(ValueError, match="weights"):
        f.reseed([1, 2], weights=[1.0])


def test_a_frame_held_just_after_the_window_moved_keeps_the_window():
    # scores that are 0 away from the robot: the frame after a move can repeat the last one
    # exactly (the places entering the window score 0 as they are filled); the held frame
    # must not move the window again (its packet moved with the window)
    rng = np.random.default_rng(1)
    n, start = 3000, 500
    truth = start + np.arange(400)
    S = np.zeros((400, n))
    for t, p in enumerate(truth):
        idx = np.arange(p - 20, p + 21)
        S[t, idx] = np.exp(-0.5 * ((idx - p) / 2.0) ** 2) + 0.3 * rng.random(idx.size)
    f = WindowedCANN(n, window=256)
    f.reseed([start])
    t = 0
    while True:
        moves = f.n_moves_
        lo, hi = f.window_
        f.step(S[t, lo:hi])
        if f.n_moves_ > moves and t > 100:
            break
        t += 1
    window, place = f.window_, f.place_
    for _ in range(5):
        lo, hi = f.window_
        assert f.step(S[t, lo:hi])[0] == place
        assert f.window_ == window and f.state_ == "localized"
    assert f.cann_.n_held_ == 5
    lo, hi = f.window_
    assert abs(f.step(S[t + 1, lo:hi])[0] - truth[t + 1]) <= 2


@pytest.mark.parametrize("d", [1, -1, 2, -3, 30, -30, 38, -38, 39, -39, 40, -40, 45, -45])
def test_shift_tied_against_a_loop(d):
    # place i is tied with i - 1; after the move new place i is old place i + d: tied when
    # either of the two entered the window (nothing known), else as the old pair was
    n = 40
    tied = np.array([1, 2, 5, 6, 17, 30, 38, 39], np.int32)

    def entered(j):
        return not 0 <= j < n

    expected = [i for i in range(1, n) if entered(i + d) or entered(i - 1 + d) or i + d in tied]
    out = _shift_tied(tied, d, n)
    assert out.dtype == np.int32 and out.tolist() == expected


def test_moving_by_one_place_and_by_none():
    f = WindowedCANN(1000, window=100)
    f.reseed([500])
    lo, moves = f.window_[0], f.n_moves_
    f._move(lo)  # no move: nothing counted
    assert f.window_[0] == lo and f.n_moves_ == moves
    f._move(lo + 1)
    assert f.window_ == (lo + 1, lo + 101) and f.n_moves_ == moves + 1
    assert f.cann_._tied[-1] == 99  # the place that entered is tied with its neighbour
    f._move(-50)  # clipped to the start of the map
    assert f.window_ == (0, 100) and f.n_moves_ == moves + 2


@pytest.mark.parametrize(
    ("window", "packet", "lo"),
    [
        # recentre * window = 12.625 places: 13 from the centre (50) moves, 12 does not
        (101, 62, 450),
        (101, 63, 463),
        (101, 37, 437),
        (101, 38, 450),
        # 16 places exactly (centre 64): not more than recentre * window, no move
        (128, 80, 436),
        (128, 81, 453),
        (128, 47, 419),
        (128, 48, 436),
    ],
)
def test_the_window_moves_when_the_packet_strays_more_than_recentre(window, packet, lo):
    f = WindowedCANN(1000, window=window)
    f.reseed([500])
    start = f.window_[0]
    c = f.cann_
    c._marginal[:] = 0.0
    c._marginal[packet] = 1.0
    f.state_ = "localized"
    f._follow()
    assert f.window_ == (lo, lo + window)
    assert f.n_moves_ == 1 + (lo != start)
    if lo != start:  # the packet is now at the centre
        assert int(np.argmax(c._marginal)) == window // 2


def test_reseed_at_the_edges_of_its_input():
    f = WindowedCANN(1000, window=100)
    # 100 is the best: the window is 50..149; 50 (its first place) is inside, 150 (one past
    # its last) and 0 are not; a weight may be 0 and the weights need not sum to 1
    f.reseed([50, 100, 150, 0], weights=[0.125, 0.25, 0.1, 0.0])
    assert f.window_ == (50, 150) and f.place_ == 100
    assert f.confidence_ == 0.0 and f.state_ == "lost"
    marginal = f.cann_._p.sum(axis=0)
    assert marginal[0] == pytest.approx(0.9 / 3 + 0.001, rel=1e-5)
    assert marginal[50] == pytest.approx(0.9 * 2 / 3 + 0.001, rel=1e-5)
    assert marginal[99] == pytest.approx(0.001, rel=1e-5)
    f.reseed([0])  # the map's first place is a place
    assert f.window_ == (0, 100) and f.place_ == 0 and f.confidence_ == 0.0
    with pytest.raises(ValueError, match="1-d"):
        f.reseed(np.array([[1, 2]]))
    with pytest.raises(ValueError, match="non-empty"):
        f.reseed(np.array([], dtype=int))


def test_defaults_and_reset():
    assert WindowedCANN(5000).window_ == (0, 2048)  # the documented default window
    assert WindowedCANN(100, window=16).width == 16  # the smallest window allowed
    with pytest.raises(ValueError, match="window"):
        WindowedCANN(100, window=15)
    S, _ = _route(n_query=30, n_places=1000, start=400)
    f = WindowedCANN(1000, window=100)
    f.reseed([400])
    _run(f, S)
    assert f.confidence_ > 0.0 and f.n_moves_ > 0
    f.reset()
    # no answer: place -1 (no place of the map, as the index's -1), confidence 0
    assert (f.place_, f.confidence_, f.state_) == (-1, 0.0, "lost")
    assert f.window_ == (0, 100) and f.n_moves_ == 0


def test_a_map_within_the_window_with_breaks_is_the_cann_exactly():
    # the robot drives places 20-99 and then off the map: the map's route is broken at 100
    S, _ = _route(n_query=120, n_places=300, start=20)
    S[80:] = np.random.default_rng(5).normal(size=(40, 300)).astype(np.float32)
    full = CANN(tolerance=2, breaks=(100, 250)).filter(S)
    f = WindowedCANN(300, window=512, tolerance=2, breaks=(100, 250))
    assert f.cann_.breaks == (100, 250)
    for t, row in enumerate(S):
        place, confidence, state = f.step(row)
        assert place == int(full[t].argmax())
        assert confidence == pytest.approx(float(full[t].max()), rel=1e-6)
    # (and the breaks change what it says: without them the packet runs on past 100)
    plain = CANN(tolerance=2).filter(S)
    assert not np.array_equal(plain.argmax(axis=1), full.argmax(axis=1))


def test_the_layer_gets_the_breaks_inside_its_window_as_window_places():
    f = WindowedCANN(1000, window=100, breaks=(50, 100, 130, 199, 200, 650))
    np.testing.assert_array_equal(f.breaks_, [50, 100, 130, 199, 200, 650])
    # the window 0-99: 50; 100 is the first place after it
    assert f.cann_.breaks == (50,)
    assert f._window_breaks(100).tolist() == [30, 99]  # 100 starts the window: nothing cut
    assert f._window_breaks(101).tolist() == [29, 98, 99]
    assert f._window_breaks(600).tolist() == [50]
    assert f._window_breaks(900).tolist() == []
    S, _ = _route(n_query=40, n_places=1000, start=620)
    f.reseed([620])  # the window 570-669
    assert f.window_ == (570, 670) and f.cann_.breaks == (80,)
    f.step(S[0, 570:670])
    np.testing.assert_array_equal(f.cann_._params["breaks"], [80])  # what the layer runs with
    f._move(600)  # the window moves: the breaks move with it, in what the layer runs with
    assert f.cann_.breaks == (50,)
    np.testing.assert_array_equal(f.cann_._params["breaks"], [50])
    f._move(660)
    assert f.cann_.breaks == () and f.cann_._params["breaks"].size == 0
    f.step(S[1, 660:760])  # (an empty set runs as none)
    f.reset()
    assert f.window_ == (0, 100) and f.cann_.breaks == (50,)
    np.testing.assert_array_equal(f.cann_._params["breaks"], [50])


def test_breaks_at_the_edges_of_the_window():
    f = WindowedCANN(1000, window=100, breaks=(400, 499, 500))
    S, _ = _route(n_query=3, n_places=1000, start=420)
    f.reseed([450])  # the window 400-499: its first place is a break (nothing to cut there)
    assert f.window_ == (400, 500) and f.cann_.breaks == (99,)
    f.step(S[0, 400:500])
    np.testing.assert_array_equal(f.cann_._params["breaks"], [99])
    f._move(401)  # 499 and 500 are places 98 and 99 of the window
    assert f.cann_.breaks == (98, 99)
    f.step(S[1, 401:501])
    f._move(300)  # the window 300-399 ends just before the break at 400
    assert f.cann_.breaks == ()
    f.step(S[2, 300:400])


def test_the_window_does_not_carry_the_robot_across_a_break():
    # the map: two recordings joined at place 1500; the robot drives the first to its end
    # (places 1300-1499) and on, off the map (noise rows); the window follows it there
    S, truth = _route(n_query=260, n_places=3000, start=1300, strength=4.0)
    S[200:] = np.random.default_rng(2).normal(size=(60, 3000)).astype(np.float32)
    runs = {}
    for breaks in ((), (1500,)):
        f = WindowedCANN(3000, window=256, breaks=breaks)
        f.reseed([1300])
        places, states = _run(f, S)
        assert (np.abs(places - truth) <= 2)[20:200].mean() > 0.95
        runs[breaks] = places, states
    places, states = runs[()]
    # one route: carried on into the next recording, localized there for a few frames
    assert (states[200:204] == "localized").all() and (places[200:204] >= 1500).all()
    # broken: it left the map, lost from the first frame off it
    assert (runs[(1500,)][1][200:] == "lost").all()


def test_breaks_are_checked_against_the_whole_map():
    with pytest.raises(ValueError, match=r"breaks must be places 1 \.\. 999 of this map of 1000"):
        WindowedCANN(1000, window=100, breaks=(300, 1000))
    with pytest.raises(ValueError, match="breaks"):
        WindowedCANN(1000, window=100, breaks=(300, 200))
    with pytest.raises(ValueError, match="breaks"):
        WindowedCANN(1000, window=100, breaks=(0,))
    assert WindowedCANN(1000, window=100, breaks=(999,)).breaks_.tolist() == [999]
    assert WindowedCANN(1000, window=100).cann_.breaks == ()
