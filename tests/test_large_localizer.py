"""LargeLocalizer: the windowed CANN on a large map, re-seeded from an index when lost."""

import numpy as np
import pytest

from flyvpr.large import ExhaustiveIndex, LargeLocalizer, MultiIndexHash
from oracles import odometry_scale


def _map(n=20000, n_bytes=32, seed=0):
    return np.random.default_rng(seed).integers(0, 256, size=(n, n_bytes), dtype=np.uint8)


def _query(codes, place, rng, flip=0.3):
    bits = np.unpackbits(codes[place])
    return np.packbits(bits ^ (rng.random(bits.size) < flip))


def _drive(loc, codes, places, rng, flip=0.3):
    return [loc.update_code(_query(codes, p, rng, flip)) for p in places]


@pytest.mark.parametrize("index", [ExhaustiveIndex(), MultiIndexHash(radius=2)])
def test_finds_the_route_from_anywhere_and_tracks_it(index):
    codes = _map()
    rng = np.random.default_rng(1)
    loc = LargeLocalizer(codes, index.build(codes), window=512)
    truth = 15000 + np.arange(120)
    fixes = _drive(loc, codes, truth, rng)
    right = np.array([abs(f.place - t) <= 2 for f, t in zip(fixes, truth, strict=True)])
    assert right[30:].all()
    assert fixes[-1].state == "localized" and fixes[-1].confidence > 0.9
    lo, hi = loc.filter_.window_
    assert lo <= truth[-1] < hi
    # tracked frames do not ask the index (only the checks' frames do)
    searches = loc.n_searches_
    _drive(loc, codes, 15120 + np.arange(50), rng)
    assert loc.n_searches_ - searches <= loc.pool


def test_relocates_after_a_kidnap():
    codes = _map()
    rng = np.random.default_rng(2)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=512)
    _drive(loc, codes, 3000 + np.arange(60), rng)
    assert abs(loc.filter_.place_ - 3059) <= 2
    reseeds = loc.n_reseeds_
    after = 17000 + np.arange(80)
    fixes = _drive(loc, codes, after, rng)
    right = [
        abs(f.place - t) <= 2 and f.state == "localized" for f, t in zip(fixes, after, strict=True)
    ]
    assert any(right[:20])
    assert all(right[-20:])
    assert loc.n_reseeds_ > reseeds


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_reseed_replays_the_lost_frames(seed):
    # The layer re-seeds at the lost stretch's 4th frame, from 4 codes, and is run over those
    # frames again: the fix of the frame that re-seeds it is already localized and right.
    codes = _map(seed=seed)
    rng = np.random.default_rng(10 + seed)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=512)
    _drive(loc, codes, 3000 + np.arange(60), rng)
    reseeds, searches = loc.n_reseeds_, loc.n_searches_
    for t in 17000 + np.arange(30):
        fix = loc.update_code(_query(codes, t, rng))
        if loc.n_reseeds_ > reseeds:
            break
    assert loc.n_reseeds_ == reseeds + 1
    assert loc.n_searches_ - searches == loc.reseed_after
    assert fix.state == "localized" and abs(fix.place - t) <= 2


@pytest.mark.parametrize("seed", [1, 3, 4])
def test_frames_that_match_nothing_keep_the_track(seed):
    # Codes that match nothing: the best of the candidates' tracks beats the layer's own at
    # chance, never by the margin, so the stretch is searched every 4th frame (4 new codes
    # each) and never re-seeded; the layer picks its track up again when the frames match.
    codes = _map(seed=seed)
    rng = np.random.default_rng(20 + seed)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=512)
    _drive(loc, codes, 3000 + np.arange(60), rng)
    reseeds = loc.n_reseeds_
    searched = []
    for frame in range(40):
        before = loc.n_searches_
        loc.update_code(rng.integers(0, 256, 32, dtype=np.uint8))
        if loc.n_searches_ > before:
            searched.append((frame, loc.n_searches_ - before))
    frames, codes_sent = zip(*searched, strict=True)
    assert set(np.diff(frames).tolist()) == {4}
    assert set(codes_sent) == {4}
    assert loc.n_reseeds_ == reseeds
    fixes = _drive(loc, codes, 3100 + np.arange(30), rng)
    assert fixes[-1].state == "localized" and abs(fixes[-1].place - 3129) <= 2


class _OwnTrackBest(LargeLocalizer):
    """A localizer whose lost searches never re-seed and find the layer's own track the best."""

    def _reseed_lost(self, n_frames):
        super()._reseed_lost(n_frames)
        return False, True


@pytest.mark.parametrize("seed", [1, 3])
def test_a_dip_whose_own_track_is_the_best_backs_off(seed):
    # Searched at the 4th, 8th, 16th and 32nd lost frame, 4 codes each: a long dip on the
    # right stretch does not ask the index every few frames.
    codes = _map(seed=seed)
    rng = np.random.default_rng(20 + seed)
    loc = _OwnTrackBest(codes, ExhaustiveIndex().build(codes), window=512)
    _drive(loc, codes, 3000 + np.arange(60), rng)
    searched = []
    for frame in range(40):
        before = loc.n_searches_
        loc.update_code(rng.integers(0, 256, 32, dtype=np.uint8))
        if loc.n_searches_ > before:
            searched.append((frame, loc.n_searches_ - before))
    frames, codes_sent = zip(*searched, strict=True)
    assert np.diff(frames).tolist() == [4, 8, 16]
    assert codes_sent == (4, 4, 4, 4)


@pytest.mark.parametrize("seed", [1, 2])
def test_a_weakly_matching_kidnap_is_searched_again_soon(seed):
    # After a kidnap to frames that match their places weakly (42% of the bits flipped), the
    # true track beats the layer's own at the 2nd search without clearing the margin: the
    # next search comes 4 frames later, not 8 (the back-off of a dip), and re-seeds it.
    codes = _map(seed=seed)
    rng = np.random.default_rng(30 + seed)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=512)
    _drive(loc, codes, 3000 + np.arange(60), rng)
    searched, got = [], None
    for i, t in enumerate(17000 + np.arange(40)):
        before = loc.n_searches_
        fix = loc.update_code(_query(codes, t, rng, 0.42))
        if loc.n_searches_ > before:
            searched.append(i)
        if got is None and fix.state == "localized" and abs(fix.place - t) <= 2:
            got = i
    assert np.diff(searched[:3]).tolist() == [4, 4]
    assert got is not None and got <= 15


def _biased_map(rng, n=20000):
    """Random codes, some of whose places have every bit set that the queries' conditions
    tend to set (a place that resembles every query), and a query maker."""
    bits = rng.random((n, 256)) < 0.5
    bias = np.zeros(256, bool)
    bias[:96] = True
    hubs = 9000 + np.arange(0, 400, 20)
    bits[np.ix_(hubs, np.flatnonzero(bias))] = True

    def query(place):
        b = bits[place] ^ (rng.random(256) < 0.3)
        b[bias] |= rng.random(bias.sum()) < 0.8
        return np.packbits(b)

    return np.packbits(bits, axis=1), query


@pytest.mark.parametrize("seed", [0, 1])
def test_places_that_resemble_every_query_do_not_win(seed):
    # Each hub is as similar to every query as the true place is to its own: raw similarity
    # along a standing track at a hub ties the true track; less each place's baseline it
    # does not.
    rng = np.random.default_rng(seed)
    codes, query = _biased_map(rng)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=512)
    fixes = [loc.update_code(query(3000 + t)) for t in range(60)]
    assert fixes[-1].state == "localized" and abs(fixes[-1].place - 3059) <= 2
    fixes = [loc.update_code(query(17000 + t)) for t in range(40)]
    right = [f.state == "localized" and abs(f.place - 17000 - t) <= 2 for t, f in enumerate(fixes)]
    assert any(right[:15])
    assert all(right[-10:])


@pytest.mark.parametrize("check_every", [0, 50])
def test_a_check_catches_a_kidnap_the_layer_has_not_noticed(check_every):
    # Places 3000.. are a noisier copy of 12000..: a layer that locked on there from their
    # own codes tracks the queries of 12060.. on 3060.. (localized), until a check finds the
    # better track outside its window.
    rng = np.random.default_rng(5)
    codes = _map()
    copy = np.unpackbits(codes[12000:12200], axis=1)
    codes[3000:3200] = np.packbits(copy ^ (rng.random(copy.shape) < 0.25), axis=1)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=512, check_every=check_every)
    _drive(loc, codes, 3000 + np.arange(60), rng, flip=0.25)
    reseeds = loc.n_reseeds_
    fixes = _drive(loc, codes, 12060 + np.arange(120), rng, flip=0.25)
    assert fixes[20].state == "localized" and abs(fixes[20].place - 3080) <= 2
    if check_every:
        assert loc.n_reseeds_ == reseeds + 1 and abs(fixes[-1].place - 12179) <= 2
    else:
        assert loc.n_reseeds_ == reseeds and abs(fixes[-1].place - 3179) <= 2


def test_odometry_and_images_need_what_they_need():
    codes = _map(n=5000)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=256)
    rng = np.random.default_rng(3)
    truth = 2000 + 2 * np.arange(60)
    fixes = [
        loc.update_code(_query(codes, p, rng), velocity=None if t == 0 else 2.0)
        for t, p in enumerate(truth)
    ]
    assert abs(fixes[-1].place - truth[-1]) <= 2
    with pytest.raises(ValueError, match="encoder"):
        loc.update(np.zeros((32, 64), np.float32))


def test_errors():
    codes = _map(n=1000)
    index = ExhaustiveIndex().build(codes)
    with pytest.raises(ValueError, match="1000 codes"):
        LargeLocalizer(codes, ExhaustiveIndex().build(codes[:10]))
    with pytest.raises(TypeError, match="CandidateIndex"):
        LargeLocalizer(codes, object())
    with pytest.raises(ValueError, match="multiple of 8"):
        LargeLocalizer(codes[:, :5], index)
    with pytest.raises(ValueError, match="k"):
        LargeLocalizer(codes, index, k=0)
    with pytest.raises(ValueError, match="reseed_after"):
        LargeLocalizer(codes, index, reseed_after=0)
    loc = LargeLocalizer(codes, index, window=128)
    with pytest.raises(ValueError, match=r"code must be uint8 of shape \(32,\)"):
        loc.update_code(np.zeros(16, np.uint8))
    with pytest.raises(ValueError, match="code must be uint8"):
        loc.update_code(np.zeros(32, np.int64))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_reseed_in_a_dip_keeps_the_track_it_displaced(seed):
    # A lost layer on the right stretch (frames that match nothing) re-seeded onto a wrong
    # place: the layer it displaced is held and integrated on, and when the frames match the
    # route again it answers again, localized, with no second re-seed; then it is let go.
    codes = _map(seed=seed)
    rng = np.random.default_rng(30 + seed)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=512)
    _drive(loc, codes, 3000 + np.arange(60), rng)
    for _ in range(3):
        loc.update_code(rng.integers(0, 256, 32, dtype=np.uint8))
    incumbent, reseeds = loc.filter_, loc.n_reseeds_
    loc._replay(np.array([12000]), np.array([0.1]), np.array([1.0]), 3, hold=True)
    assert loc.held_ is incumbent and loc.filter_ is not incumbent
    fixes = _drive(loc, codes, 3063 + np.arange(20), rng)
    right = [f.state == "localized" and abs(f.place - 3063 - t) <= 2 for t, f in enumerate(fixes)]
    assert all(right[5:])
    assert loc.filter_ is incumbent and loc.held_ is None and loc.n_reseeds_ == reseeds + 1


@pytest.mark.parametrize("speed", [1.0, 2.0])
def test_every_track_finds_a_route_no_single_frame_does(speed):
    # frames with 42% of their bits flipped: each one's true place is down its own list
    # (about 2.6 standard deviations above chance), but its track over 10 frames stands out
    # (a standing track less: each place's baseline is its own mean, shrunk towards chance)
    codes = _map(seed=4)
    rng = np.random.default_rng(40)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=512)
    truth = 7000 + np.rint(speed * np.arange(10)).astype(int)
    queries = np.stack([_query(codes, p, rng, flip=0.42) for p in truth])
    top, _ = ExhaustiveIndex().build(codes).search(queries, 20)
    assert not any(abs(top[t] - truth[t]).min() <= 2 for t in range(10))  # no frame finds it
    loc._recent.extend(queries)
    ends = loc._full_track_ends(10)
    assert ends.size == 50 and abs(ends[0] - truth[-1]) <= 1
    # best first, at least 11 places apart
    gaps = np.abs(ends[:, None] - ends[None, :]) + np.eye(ends.size, dtype=int) * 100
    assert gaps.min() > 10
    # the same scores as the candidates' tracks: the best end's is the highest of all
    scores, _, best_speed = loc._track_scores(ends, 10)
    assert np.argmax(scores) == 0 and best_speed[0] == speed


def test_every_track_is_searched_only_for_a_lost_guess_on_a_map_small_enough():
    codes = _map(seed=5)
    index = ExhaustiveIndex().build(codes)
    truth = 9000 + np.arange(60)

    def cold_start(**kw):
        loc = LargeLocalizer(codes, index, window=512, k=20, **kw)
        fixes = _drive(loc, codes, truth, np.random.default_rng(50), flip=0.43)
        return loc, fixes

    loc, fixes = cold_start()
    assert loc.n_full_searches_ >= 1  # the cold start's guesses were lost
    assert fixes[-1].state == "localized" and abs(fixes[-1].place - truth[-1]) <= 2
    assert cold_start(full_search_places=0)[0].n_full_searches_ == 0
    assert cold_start(full_search_places=len(codes) - 1)[0].n_full_searches_ == 0
    assert cold_start(full_search_places=len(codes))[0].n_full_searches_ >= 1
    # tracked (localized since its seed), and lost for a few frames: the index only
    full, searches = loc.n_full_searches_, loc.n_searches_
    rng = np.random.default_rng(51)
    for _ in range(8):
        loc.update_code(rng.integers(0, 256, 32, dtype=np.uint8))
    assert loc.n_searches_ > searches and loc.n_full_searches_ == full


def test_hold_bounds_how_long_a_displaced_layer_is_stepped():
    # the displaced layer is stepped on until the answering one is localized or for ``hold``
    # frames, whichever comes first
    codes = _map(seed=6)
    for hold, seed in ((3, 60), (12, 60), (12, 61)):
        rng = np.random.default_rng(seed)
        loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=512, hold=hold)
        _drive(loc, codes, 3000 + np.arange(40), rng)
        for _ in range(15):  # the frames stop matching: the layer is no longer localized
            loc.update_code(rng.integers(0, 256, 32, dtype=np.uint8))
        reseeds = loc.n_reseeds_
        loc._replay(np.array([12000]), np.array([0.1]), np.array([1.0]), 3, hold=True)
        let_go = None
        for i in range(20):
            fix = loc.update_code(rng.integers(0, 256, 32, dtype=np.uint8))
            if loc.held_ is None and let_go is None:
                let_go = i
                assert fix.state == "localized" or i == hold - 1, (hold, seed, i)
                # while a localized layer was held, no guess beat it by the margin
                assert loc.n_reseeds_ == reseeds + 1
                assert loc._held_proven is False  # nothing held: the layer is a guess again
            if let_go is None:
                assert fix.state != "localized" and i < hold - 1, (hold, seed, i)
        assert let_go is not None
        if hold == 3:
            assert let_go == 2


def test_the_documented_defaults():
    codes = _map(n=5000)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes))
    assert (loc.k, loc.pool, loc.reseed_after, loc.check_every) == (300, 10, 4, 1000)
    assert loc.speed == (0.0, 2.0) and loc.hold == 30 and loc.full_search_places == 2**20
    assert loc.filter_.window == 2048 and loc.n_bits == 256 and loc.n_places == 5000
    assert loc.encoder is None
    # the CANN's own parameters go to the layer
    assert LargeLocalizer(codes, loc.index, evidence_gain=0.3).filter_.cann_.evidence_gain == 0.3


@pytest.mark.parametrize(
    ("params", "error", "message"),
    [
        ({"k": 0}, ValueError, "k must be >= 1; got 0"),
        ({"pool": 0}, ValueError, "pool must be >= 1; got 0"),
        ({"reseed_after": 0}, ValueError, "reseed_after must be >= 1; got 0"),
        ({"check_every": -1}, ValueError, "check_every must be >= 0; got -1"),
        ({"hold": 0}, ValueError, "hold must be >= 1; got 0"),
        ({"full_search_places": -1}, ValueError, "full_search_places must be >= 0; got -1"),
        ({"pool": 2.5}, TypeError, "pool must be an int; got float"),
        (
            {"speed": (2, 0)},
            ValueError,
            r"speed must be \(low, high\) with 0 <= low <= high, finite; got \(2, 0\)",
        ),
        (
            {"speed": (0, float("inf"))},
            ValueError,
            r"speed must be \(low, high\) with 0 <= low <= high, finite; got \(0, inf\)",
        ),
        ({"speed": 2.0}, ValueError, r"speed must be \(low, high\), two numbers; got 2.0"),
    ],
)
def test_each_bad_parameter_is_named(params, error, message):
    codes = _map(n=1000)
    with pytest.raises(error, match=f"^{message}$"):
        LargeLocalizer(codes, ExhaustiveIndex().build(codes), **params)


def test_bad_maps_and_indexes_are_named():
    codes = _map(n=1000)
    index = ExhaustiveIndex().build(codes)
    with pytest.raises(TypeError, match="^codes must be bit-packed uint8 codes; got dtype int64$"):
        LargeLocalizer(codes.astype(np.int64), index)
    bad = r"^codes must be a 2-d uint8 array \(n_places, n_bytes\); got "
    with pytest.raises(ValueError, match=bad + r"uint8 \(0, 32\)$"):
        LargeLocalizer(codes[:0], index)
    shape = r"^codes must have shape \(n, n_bytes\) with n_bytes a positive multiple of 8; got "
    with pytest.raises(ValueError, match=shape + r"\(1, 32, 1\)$"):
        LargeLocalizer(codes[:, :, None], index)
    with pytest.raises(ValueError, match=shape + r"\(1, 5\)$"):
        LargeLocalizer(codes[:, :5], index)
    with pytest.raises(TypeError, match="^index must be a CandidateIndex; got dict$"):
        LargeLocalizer(codes, {})
    with pytest.raises(
        ValueError, match=r"^index must be built over the map's 1000 codes; it holds 10 places"
    ):
        LargeLocalizer(codes, ExhaustiveIndex().build(codes[:10]))
    with pytest.raises(ValueError, match="it holds no places \\(build it first\\)$"):
        LargeLocalizer(codes, ExhaustiveIndex())


def test_reset_forgets_everything():
    codes = _map(n=5000)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=256)
    rng = np.random.default_rng(4)
    _drive(loc, codes, 1000 + np.arange(40), rng)
    _drive(loc, codes, 4000 + np.arange(20), rng)  # a kidnap: searches and a re-seed
    assert loc.n_searches_ > 0 and loc.n_reseeds_ > 0 and loc.search_s_ > 0
    loc.reset()
    assert (loc.n_frames_, loc.n_searches_, loc.n_reseeds_, loc.n_full_searches_) == (0, 0, 0, 0)
    assert loc.search_s_ == 0.0 and loc.held_ is None and loc.filter_.state_ == "lost"
    # after a reset the first frame is searched for in the whole map, as on the first run
    fresh = LargeLocalizer(codes, loc.index, window=256)
    rng_a, rng_b = np.random.default_rng(5), np.random.default_rng(5)
    a = _drive(loc, codes, 2500 + np.arange(30), rng_a)
    b = _drive(fresh, codes, 2500 + np.arange(30), rng_b)
    assert [(f.place, f.state) for f in a] == [(f.place, f.state) for f in b]
    assert loc.n_searches_ == fresh.n_searches_ and loc.n_frames_ == 30


def _image_map(seed):
    """300 random frames, a 64-bit compact encoder fitted on them, its codes and their exact
    index (and the generator, for the queries)."""
    from flyvpr.large import CompactEncoder

    rng = np.random.default_rng(seed)
    images = rng.random((300, 32, 64)).astype(np.float32)
    enc = CompactEncoder(n_bits=64, random_state=0).fit(images)
    codes = enc.reference_codes_
    return rng, images, enc, codes, ExhaustiveIndex().build(codes)


def test_update_encodes_the_image_and_passes_the_odometry_on():
    _, images, enc, codes, index = _image_map(6)
    by_image = LargeLocalizer(codes, index, encoder=enc, window=64)
    by_code = LargeLocalizer(codes, index, window=64)
    for t in range(20):
        velocity = None if t == 0 else 1.0
        a = by_image.update(images[100 + t], velocity)
        b = by_code.update_code(enc.encode(images[100 + t][None])[0], velocity)
        assert (a.place, a.state, a.confidence) == (b.place, b.state, b.confidence)
        if velocity is not None:
            layer = by_image.filter_.cann_
            assert layer.velocity_ == pytest.approx(odometry_scale(layer))  # 1 place, scaled
    with pytest.raises(
        ValueError, match=r"^update needs an encoder \(LargeLocalizer\(\.\.\., encoder=\.\.\.\)\)$"
    ):
        by_code.update(images[0])


def _reference_tracks(loc, places, n_frames):
    """_track_scores by loops: every speed and end around each place, each frame's similarity
    less the place's baseline (shrunk towards 1/2 as if 5 more frames had scored 1/2)."""
    from flyvpr.large import localizer as mod

    frames = [np.unpackbits(c) for c in list(loc._recent)[-n_frames:]]
    bits = np.unpackbits(loc.codes, axis=1)
    n = loc.n_places

    def sim(t, p):
        return 1.0 - np.count_nonzero(frames[t] != bits[p]) / bits.shape[1]

    def baseline(p):
        return (sum(sim(t, p) for t in range(n_frames)) + 0.5 * mod._PRIOR_FRAMES) / (
            n_frames + mod._PRIOR_FRAMES
        )

    out = []
    for c in places:
        best = None
        for s in mod._TRACK_SPEEDS:
            for e in range(c - mod._REFINE, c + mod._REFINE + 1):
                track = [
                    min(max(e - round(s * (n_frames - 1 - t)), 0), n - 1) for t in range(n_frames)
                ]
                score = np.mean([sim(t, p) - baseline(p) for t, p in enumerate(track)])
                if best is None or score > best[0] + 1e-9:
                    best = (score, min(max(e, 0), n - 1), s)
        out.append(best)
    return out


@pytest.mark.parametrize("n_frames", [1, 4, 7])
def test_track_scores_equal_a_loop_reference(n_frames):
    codes = _map(n=400, n_bytes=8, seed=5)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=64)
    rng = np.random.default_rng(7)
    for p in 200 + np.arange(n_frames):
        loc._recent.append(_query(codes, int(p), rng, flip=0.2))
    places = np.array([3, 150, 200 + n_frames - 1, 396])  # both ends of the map too
    scores, ends, speeds = loc._track_scores(places, n_frames)
    ref = _reference_tracks(loc, places, n_frames)
    np.testing.assert_allclose(scores, [r[0] for r in ref], atol=1e-5)
    np.testing.assert_array_equal(ends, [r[1] for r in ref])
    np.testing.assert_array_equal(speeds, [r[2] for r in ref])


@pytest.mark.parametrize(
    ("frames", "candidate", "end", "speed"),
    [
        ([0, 0, 0, 0], 2, 0, 0.0),  # standing on the first place
        ([395, 397, 399, 399], 397, 399, 2.0),  # 2 per frame into the last place: end past it
    ],
)
def test_tracks_at_the_ends_of_the_map(frames, candidate, end, speed):
    codes = _map(n=400, n_bytes=8, seed=6)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=64)
    for p in frames:
        loc._recent.append(codes[p])
    places = np.array([candidate])
    scores, ends, speeds = loc._track_scores(places, len(frames))
    ref = _reference_tracks(loc, places, len(frames))[0]
    assert (ends[0], speeds[0]) == (end, speed) == (ref[1], ref[2])
    np.testing.assert_allclose(scores[0], ref[0], atol=1e-6)


def _spy_on_reseeds(monkeypatch) -> list:
    """The (places, weights) of every WindowedCANN.reseed from now on, in a list."""
    from flyvpr.temporal.cann import WindowedCANN

    seeded = []
    real = WindowedCANN.reseed

    def spy(self, places, weights=None):
        seeded.append((np.array(places), np.array(weights)))
        return real(self, places, weights)

    monkeypatch.setattr(WindowedCANN, "reseed", spy)
    return seeded


def test_a_replay_seeds_the_tracks_starts_weighted_by_their_scores(monkeypatch):

    codes = _map(n=3000, n_bytes=8)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=128)
    rng = np.random.default_rng(8)
    for p in 1000 + np.arange(6):
        loc._recent.append(_query(codes, int(p), rng, flip=0.2))
        loc._velocities.append(None)
    seeded = _spy_on_reseeds(monkeypatch)
    ends = np.array([1005, 20, 2999])
    tracks = np.array([0.30, 0.25, 0.10])
    speeds = np.array([1.0, 2.0, 0.5])
    before = loc.search_s_
    loc._replay(ends, tracks, speeds, 6)
    ((places, weights),) = seeded
    # each track's start, 5 frames back at its speed, clipped to the map
    np.testing.assert_array_equal(places, [1000, 10, 2997])  # 2.5 places rounds to 2
    # weights: exp of the score less the best's, in units of 8 bits of a 64-bit code
    np.testing.assert_allclose(weights, np.exp((tracks - 0.30) * 64 / 8.0))
    assert loc.n_reseeds_ == 1 and loc.held_ is None and loc.search_s_ > before
    # a start before the first place is clipped to it
    seeded.clear()
    loc._replay(np.array([3]), np.array([0.2]), np.array([2.0]), 6)
    np.testing.assert_array_equal(seeded[0][0], [0])
    assert loc.n_reseeds_ == 2
    # a standing track on the last place starts there
    seeded.clear()
    loc._replay(np.array([2999]), np.array([0.2]), np.array([0.0]), 6)
    np.testing.assert_array_equal(seeded[0][0], [2999])
    # with hold, of the displaced layers those localized since their seed are kept, the more
    # confident one; a guess is not
    loc._replay(ends, tracks, speeds, 6, hold=True)
    assert loc.held_ is None and loc._held_proven is False  # the layer was a guess
    first = loc.filter_
    loc._proven = True
    loc._replay(ends, tracks, speeds, 6, hold=True)
    assert loc.held_ is first and loc._held_proven is True and loc._proven is False
    for proven, held_proven in ((True, True), (True, False), (False, True), (False, False)):
        loc._proven, loc._held_proven = proven, held_proven
        loc._held_frames = 5
        # (the replays made equal layers: the held one the more confident, so that the
        # choice between two localized layers shows)
        loc.held_.confidence_ = loc.filter_.confidence_ + 0.1
        layers = [(loc.filter_, proven), (loc.held_, held_proven)]
        kept = [layer for layer, p in layers if p]
        expected = max(kept, key=lambda layer: layer.confidence_) if kept else None
        loc._replay(ends, tracks, speeds, 6, hold=True)
        assert loc.held_ is expected and loc._held_proven is (expected is not None)
        assert loc._proven is False and loc._held_frames == 0
        if expected is None:  # (a layer to hold for the next case)
            loc._proven = True
            loc._replay(ends, tracks, speeds, 6, hold=True)


def test_the_time_spent_relocating_adds_up(monkeypatch):
    from flyvpr.large import localizer as mod

    class Clock:  # every reading one second later
        now = 0.0

        def __call__(self):
            self.now += 1.0
            return self.now

    clock = Clock()
    monkeypatch.setattr(mod.time, "perf_counter", clock)
    codes = _map(n=5000)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=256, check_every=20)
    rng = np.random.default_rng(9)
    seen = [0.0]
    for places in (1000 + np.arange(30), 4000 + np.arange(30), 2500 + np.arange(30)):
        for p in places:
            loc.update_code(_query(codes, int(p), rng))
            seen.append(loc.search_s_)
    assert loc.n_reseeds_ >= 3
    assert all(b >= a for a, b in zip(seen, seen[1:], strict=False))  # it only grows
    # each timed stretch counts at least one tick, and no more ticks than were read
    assert loc.n_reseeds_ <= loc.search_s_ <= clock.now


def test_a_check_leaves_a_layer_on_the_better_of_two_look_alikes():
    # Places 3000.. are a slightly noisier copy of 12000..: on the queries of 12000.. the true
    # track beats the copy's by less than the check's margin, and the checks must not move it.
    rng = np.random.default_rng(6)
    codes = _map()
    copy = np.unpackbits(codes[12000:12300], axis=1)
    codes[3000:3300] = np.packbits(copy ^ (rng.random(copy.shape) < 0.05), axis=1)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=512, check_every=10)
    _drive(loc, codes, 12000 + np.arange(60), rng, flip=0.25)
    assert abs(loc.filter_.place_ - 12059) <= 2
    reseeds = loc.n_reseeds_
    fixes = _drive(loc, codes, 12060 + np.arange(200), rng, flip=0.25)
    assert loc.n_reseeds_ == reseeds
    assert all(abs(f.place - t) <= 2 for f, t in zip(fixes, 12060 + np.arange(200), strict=True))


def test_a_replay_steps_the_new_layer_with_the_frames_odometry():
    from flyvpr.large.codes import hamming_similarity
    from flyvpr.temporal.cann import WindowedCANN

    codes = _map(n=3000, n_bytes=8)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=128)
    rng = np.random.default_rng(11)
    places = 1000 + 2 * np.arange(6)  # 2 places per frame, and the odometry says so
    for t, p in enumerate(places):
        loc._recent.append(_query(codes, int(p), rng, flip=0.3))
        loc._velocities.append(None if t == 0 else 2.0)
    ends, tracks, speeds = np.array([1010]), np.array([0.3]), np.array([2.0])
    loc._replay(ends, tracks, speeds, 6)
    # the same layer stepped by hand through the first five frames with their odometry
    ref = WindowedCANN(loc.n_places, **loc._layer)
    ref.reseed(np.array([1000]), np.array([1.0]))
    for i in range(-6, -1):
        lo, hi = ref.window_
        ref.step(
            hamming_similarity(loc._recent[i][None], codes, lo, hi)[0],
            None if i == -6 else loc._velocities[i],
        )
    assert loc.filter_.place_ == ref.place_
    assert loc.filter_.confidence_ == ref.confidence_
    assert loc.filter_.cann_.velocity_ == pytest.approx(2.0 * odometry_scale(loc.filter_.cann_))


def test_the_first_frame_displaces_no_layer():
    # the first frame re-seeds a layer that never had a place: there is no hypothesis to hold
    codes = _map(n=5000)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=256)
    loc.update_code(_query(codes, 2500, np.random.default_rng(12)))
    assert loc.n_reseeds_ == 1 and loc.held_ is None


def test_a_check_acts_on_the_index_s_best_answer_alone():
    # As in the kidnap a check catches (places 3000.. a noisier copy of 12000..), with the
    # index answering one candidate a frame: the one candidate outside the window is enough.
    rng = np.random.default_rng(5)
    codes = _map()
    copy = np.unpackbits(codes[12000:12200], axis=1)
    codes[3000:3200] = np.packbits(copy ^ (rng.random(copy.shape) < 0.25), axis=1)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=512, k=1, check_every=50)
    _drive(loc, codes, 3000 + np.arange(60), rng, flip=0.25)
    reseeds = loc.n_reseeds_
    fixes = _drive(loc, codes, 12060 + np.arange(120), rng, flip=0.25)
    assert fixes[20].state == "localized" and abs(fixes[20].place - 3080) <= 2
    assert loc.n_reseeds_ == reseeds + 1 and abs(fixes[-1].place - 12179) <= 2


def test_checks_on_every_frame_send_each_code_once():
    # a check on every tracked frame searches that frame's code only (the others were sent)
    codes = _map()
    rng = np.random.default_rng(13)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=512, check_every=1)
    _drive(loc, codes, 15000 + np.arange(40), rng)
    searches, reseeds = loc.n_searches_, loc.n_reseeds_
    fixes = _drive(loc, codes, 15040 + np.arange(20), rng)
    right = [f.state == "localized" and abs(f.place - 15040 - t) <= 2 for t, f in enumerate(fixes)]
    assert all(right)
    assert loc.n_searches_ - searches == 20 and loc.n_reseeds_ == reseeds


def test_candidates_at_the_end_of_the_map_are_places_of_the_map():
    # a query standing on the last place: its candidates, moved on at the pooling's mid speed,
    # would lie past the end; the candidates are the map's places, the last one first
    codes = _map(n=400, n_bytes=8, seed=6)
    rng = np.random.default_rng(3)
    for k in (20, 300):
        loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=64, k=k)
        for _ in range(4):
            loc.update_code(_query(codes, 399, rng, flip=0.2), velocity=0.0)
        places = loc._candidates(4)
        assert places.size > 0 and places.min() >= 0 and places.max() <= 399, k
        assert places[0] == 399 and np.unique(places).size == places.size


def test_a_lost_guess_s_candidates_lead_with_every_track_s_ends_once():
    # the ends of the search of every place's track come first, then the index's candidates
    # that are not among them: no place twice
    codes = _map(seed=5)
    rng = np.random.default_rng(7)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=512)
    for p in 9000 + np.arange(4):
        loc._recent.append(_query(codes, int(p), rng))
        loc._velocities.append(1.0)
    loc.n_frames_ = loc._lost = 4  # lost since the start: a guess, on a small enough map
    places = loc._candidates(4)
    ends = loc._full_track_ends(4)
    assert loc.n_full_searches_ == 1
    np.testing.assert_array_equal(places[: ends.size], ends)
    assert places.size == 300 and np.unique(places).size == 300
    assert ends[0] == 9003  # the route's end, which the index finds too


@pytest.mark.parametrize(
    ("truth", "speed"),
    [([0, 0, 0, 0], 0.0), ([2997, 2998, 2999, 3000], 1.0), ([19999] * 4, 0.0)],
)
def test_a_layer_whose_track_the_index_finds_again_is_not_reseeded(truth, speed):
    # the layer's place is among the candidates (the first and the last place of the map
    # too): its own track is as good as the best of theirs, no re-seed, and the search says
    # so (the stretch backs off as a dip does)
    codes = _map(seed=2)
    rng = np.random.default_rng(4)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=512)
    for t, p in enumerate(truth):
        loc._recent.append(_query(codes, p, rng, flip=0.2))
        loc._velocities.append(None if t == 0 else speed)
    loc.n_frames_ = 4
    loc._replay(np.array([truth[-1]]), np.array([0.0]), np.array([speed]), 4)
    assert abs(loc.filter_.place_ - truth[-1]) <= 1
    loc._lost = 4
    reseeds = loc.n_reseeds_
    assert loc._reseed_lost(4) == (False, True)
    assert loc.n_reseeds_ == reseeds


class _FindsNothing(ExhaustiveIndex):
    """An index that finds no place for any query (every answer -1)."""

    def _search(self, q, k, places, dist):
        pass


@pytest.mark.parametrize("seed", [1, 3])
def test_a_dip_where_the_index_finds_nothing_backs_off(seed):
    # no candidate beats the layer's own track: searched at the 4th, 8th, 16th and 32nd lost
    # frame, never re-seeded, and the layer picks its track up again
    codes = _map(seed=seed)
    rng = np.random.default_rng(20 + seed)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=512)
    _drive(loc, codes, 3000 + np.arange(60), rng)
    loc.index = _FindsNothing().build(codes)
    reseeds, searched = loc.n_reseeds_, []
    for frame in range(40):
        before = loc.n_searches_
        fix = loc.update_code(rng.integers(0, 256, 32, dtype=np.uint8))
        if loc.n_searches_ > before:
            searched.append((frame, loc.n_searches_ - before, fix.state))
    frames, codes_sent, states = zip(*searched, strict=True)
    assert np.diff(frames).tolist() == [4, 8, 16] and set(states) == {"lost"}
    assert codes_sent == (4, 4, 4, 4) and loc.n_reseeds_ == reseeds
    fixes = _drive(loc, codes, 3100 + np.arange(30), rng)
    assert fixes[-1].state == "localized" and abs(fixes[-1].place - 3129) <= 2


@pytest.mark.parametrize(("start", "speed"), [(150, 1), (0, 2)])
def test_every_track_s_ends_are_the_best_tracks_at_least_11_places_apart(start, speed):
    # a map too small for 50 ends: greedily the best track's end, then the best at least 11
    # places from every end taken, until none is left; a track's score is its frames'
    # similarities less each place's shrunk baseline (a loop reference, at its end exactly);
    # a route from the first place is found at its full speed
    from flyvpr.large import localizer as mod

    codes = _map(n=300, n_bytes=8, seed=7)
    rng = np.random.default_rng(14)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=64)
    n_frames = 6
    truth = start + speed * np.arange(n_frames)
    for p in truth:
        loc._recent.append(_query(codes, int(p), rng, flip=0.2))
    ends = loc._full_track_ends(n_frames)

    frames = [np.unpackbits(c) for c in loc._recent]
    bits = np.unpackbits(codes, axis=1)
    sims = np.array([[1.0 - np.count_nonzero(f != b) / 64 for b in bits] for f in frames])
    sims -= (sims.sum(axis=0) + 0.5 * mod._PRIOR_FRAMES) / (n_frames + mod._PRIOR_FRAMES)
    ref = np.full(300, -np.inf)
    for s in mod._TRACK_SPEEDS:
        for e in range(300):
            track = [e - round(s * (n_frames - 1 - t)) for t in range(n_frames)]
            if track[0] >= 0:  # a track may not begin before the first place
                ref[e] = max(ref[e], np.mean([sims[t, p] for t, p in enumerate(track)]))

    assert ends[0] == truth[-1] and 12 < ends.size < 50
    gaps = np.abs(ends[:, None] - ends[None, :]) + np.eye(ends.size, dtype=int) * 100
    assert gaps.min() > 10
    assert np.all(np.diff(ref[ends]) <= 1e-6)  # best first
    for p in range(300):  # every place left out is near an end at least as good
        near = ends[np.abs(ends - p) <= 10]
        assert near.size and ref[near].max() >= ref[p] - 1e-6, p


def test_frames_never_searched_add_no_candidates():
    # a search sends the newest reseed_after codes: the older frames of the pool were never
    # searched, and the candidates over all ten frames are those of the four searched ones
    # (a route at the start of the map, where anything the others added would be scored)
    codes = _map(n=400, n_bytes=8, seed=8)
    rng = np.random.default_rng(15)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=64, k=5)
    for p in range(10):
        loc._recent.append(_query(codes, p, rng, flip=0.2))
        loc._velocities.append(1.0)
    loc.n_frames_ = 9
    loc._proven = True  # a layer that had a track: the index's candidates only
    places = loc._candidates(10)
    assert loc.n_searches_ == 4 and places[0] == 9
    np.testing.assert_array_equal(places, loc._candidates(4))
    assert loc.n_searches_ == 4  # each code is searched once


@pytest.mark.parametrize(
    ("seed_at", "reseeds"),
    [
        (2000 - 256, 1),  # the window ends just before the route's end: outside, re-seeded
        (2000 + 1 + 256, 1),  # the window starts just after it: outside
        (2000 - 255, 0),  # its last place: inside (the layer finds it itself)
        (2000 + 256, 0),  # its first place: inside
    ],
)
def test_a_check_re_seeds_for_a_candidate_just_outside_the_window(seed_at, reseeds):
    codes = _map(n=5000)
    rng = np.random.default_rng(16)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=512, k=1)
    for p in 1991 + np.arange(10):  # the route ends at 2000; the index answers it alone
        loc._recent.append(_query(codes, int(p), rng, flip=0.2))
        loc._velocities.append(1.0)
    loc.n_frames_ = 9
    loc.filter_.reseed(np.array([seed_at]))  # a window of 512 places centred on seed_at
    lo, hi = loc.filter_.window_
    assert hi - lo == 512 and (lo <= 2000 < hi) == (reseeds == 0)
    np.testing.assert_array_equal(loc._candidates(10), [2000])
    loc._check()
    assert loc.n_reseeds_ == reseeds
    lo, hi = loc.filter_.window_
    assert lo <= 2000 < hi


def test_the_time_spent_relocating_counts_the_index_and_the_tracks(monkeypatch):
    # a clock that moves only while the index searches (10 s a call) and while tracks are
    # scored (100 s a call): the time relocating is all of that time and nothing else
    from flyvpr.large import localizer as mod

    now = [0.0]
    monkeypatch.setattr(mod.time, "perf_counter", lambda: now[0])
    codes = _map(n=5000)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=256, check_every=20)
    calls = {"search": 0, "tracks": 0}

    def slow(name, seconds, method):
        def timed(*args, **kwargs):
            calls[name] += 1
            now[0] += seconds
            return method(*args, **kwargs)

        return timed

    loc.index.search = slow("search", 10.0, loc.index.search)
    loc._track_scores = slow("tracks", 100.0, loc._track_scores)
    rng = np.random.default_rng(9)
    for places in (1000 + np.arange(30), 4000 + np.arange(30), 2500 + np.arange(30)):
        _drive(loc, codes, places, rng)
    assert loc.n_reseeds_ >= 3 and calls["tracks"] > loc.n_reseeds_
    assert loc.search_s_ == 10.0 * calls["search"] + 100.0 * calls["tracks"]


def test_a_lost_re_seed_holds_the_layer_it_displaced():
    # a kidnap whose re-seed leaves the new layer lost at first: the kidnapped layer is held
    # beside it, and let go once the new one is localized on the route (the frames after the
    # kidnap noisier, 40% of their bits flipped: on 30% the re-seed is localized at once)
    codes = _map(seed=2)
    rng = np.random.default_rng(32)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=512)
    _drive(loc, codes, 3000 + np.arange(60), rng)
    reseeds = loc.n_reseeds_
    for t in 17000 + np.arange(20):
        incumbent = loc.filter_
        fix = loc.update_code(_query(codes, t, rng, flip=0.4))
        if loc.n_reseeds_ > reseeds:
            break
    assert loc.n_reseeds_ == reseeds + 1 and fix.state == "lost"
    assert loc.held_ is incumbent and loc.filter_ is not incumbent
    fixes = _drive(loc, codes, t + 1 + np.arange(20), rng, flip=0.4)
    assert fixes[-1].state == "localized" and abs(fixes[-1].place - t - 20) <= 2
    assert loc.held_ is None and loc.filter_ is not incumbent


def test_every_search_of_a_lost_guess_from_its_4th_frame_scores_every_track():
    # a cold start on frames that match nothing: its guess is never localized, searched at
    # lost frames 1, 5, 9, 13 and 17, and each search from the 4th lost frame on scores every
    # place's track
    # (a re-seed on the best of chance tracks is at times localized for a frame or two; on
    # these frames it is not)
    codes = _map(n=5000)
    rng = np.random.default_rng(18)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=256)
    fixes = [loc.update_code(rng.integers(0, 256, 32, dtype=np.uint8)) for _ in range(20)]
    assert {f.state for f in fixes} == {"lost"}
    assert loc.n_searches_ == 1 + 4 * 4 and loc.n_full_searches_ == 4


def test_frames_no_place_matches_better_than_chance_give_no_candidates():
    # every place's code has few bits set, the frames nearly all: the index still answers
    # its k nearest, but none is nearer than chance, so there is no candidate
    rng = np.random.default_rng(18)
    codes = _map(n=2000, n_bytes=8, seed=9) & _map(n=2000, n_bytes=8, seed=10)
    codes &= _map(n=2000, n_bytes=8, seed=11)  # a bit set in 1 code of 8
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=64, k=50)
    for _ in range(4):
        loc._recent.append(np.packbits(rng.random(64) < 0.95))  # nearly every bit set
        loc._velocities.append(1.0)
    loc.n_frames_ = 3
    loc._proven = True  # a layer that had a track: the index's candidates only
    assert loc._candidates(4).size == 0 and loc.n_searches_ == 4


def test_the_second_frame_s_re_seed_drops_the_first_frame_s_guess():
    # with reseed_after=1 the second frame is searched too; its re-seed does not hold the
    # guess the first frame made (never localized: no track to keep)
    codes = _map(n=5000)
    rng = np.random.default_rng(1)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=256, reseed_after=1)
    loc.update_code(rng.integers(0, 256, 32, dtype=np.uint8))  # matches nothing: a guess
    guess = loc.filter_
    fix = loc.update_code(_query(codes, 4000, rng, flip=0.05))
    assert loc.n_reseeds_ == 2 and abs(fix.place - 4000) <= 1 and fix.state == "lost"
    assert loc.filter_ is not guess and loc.held_ is None


def _scored_search(monkeypatch, proven, held_proven, lead):
    """A lost search whose one candidate's track beats the layers' own by ``lead`` standard
    margins: (its result, the places and weights a re-seed started from, the localizer)."""
    from flyvpr.large import localizer as mod
    from flyvpr.temporal.cann import WindowedCANN

    codes = _map(n=3000, n_bytes=8)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=128)
    rng = np.random.default_rng(3)
    for p in 700 + np.arange(6):
        loc._recent.append(_query(codes, int(p), rng, flip=0.2))
        loc._velocities.append(None)
    loc.n_frames_ = loc._lost = 6
    loc.filter_.reseed(np.array([1500]))
    loc._proven = proven
    if held_proven is not None:
        loc.held_ = WindowedCANN(3000, window=128)
        loc.held_.reseed(np.array([2500]))
        loc._held_proven = held_proven
    margin = mod._LOST_Z * 0.5 / np.sqrt(64 * 6)
    own = 0.05 if held_proven is None else np.array([0.05, 0.04])

    def scores(places, n_frames):
        assert n_frames == 6
        tracks = np.zeros(len(places))
        tracks[0] = 0.05 + lead * margin
        tracks[1:] = own
        return tracks, places.copy(), np.ones(len(places))

    monkeypatch.setattr(loc, "_candidates", lambda n: np.array([705]))
    monkeypatch.setattr(loc, "_track_scores", scores)
    seeded = _spy_on_reseeds(monkeypatch)
    return loc._reseed_lost(6), seeded, loc


@pytest.mark.parametrize("held_proven", [None, False])
def test_a_guess_gives_way_to_any_better_track(monkeypatch, held_proven):
    # only guesses: a candidate's track better than theirs by less than the margin re-seeds
    # the layer, from the candidate and the guesses' own tracks weighed alike
    result, seeded, loc = _scored_search(monkeypatch, False, held_proven, 0.5)
    assert result == (True, False) and loc.n_reseeds_ == 1 and loc.held_ is None
    ((places, weights),) = seeded
    own = [1500] if held_proven is None else [1500, 2500]
    np.testing.assert_array_equal(places, np.array([705] + own) - 5)
    tracks = np.array([0.05 + 0.5 * (3.5 * 0.5 / np.sqrt(384))] + [0.05, 0.04][: len(own)])
    np.testing.assert_allclose(weights, np.exp((tracks - tracks.max()) * 8.0))
    # a candidate no better than the guesses' own tracks: no re-seed, their track the best
    result, seeded, loc = _scored_search(monkeypatch, False, held_proven, 0.0)
    assert result == (False, True) and loc.n_reseeds_ == 0 and not seeded


@pytest.mark.parametrize(("proven", "held_proven"), [(True, None), (False, True), (True, False)])
def test_a_localized_layer_gives_way_only_beyond_the_margin(monkeypatch, proven, held_proven):
    # a layer localized since its seed (answering or held): a better track within the margin,
    # or exactly at it, does not re-seed, one beyond it does, from the candidates alone; a
    # tie with the layers' own track counts as their own being the best
    for lead in (0.9, 1.0):
        result, seeded, loc = _scored_search(monkeypatch, proven, held_proven, lead)
        assert result == (False, False) and loc.n_reseeds_ == 0 and not seeded
    result, seeded, loc = _scored_search(monkeypatch, proven, held_proven, 0.0)
    assert result == (False, True) and loc.n_reseeds_ == 0 and not seeded
    result, seeded, loc = _scored_search(monkeypatch, proven, held_proven, 1.1)
    assert result == (True, False) and loc.n_reseeds_ == 1
    ((places, _),) = seeded
    np.testing.assert_array_equal(places, [700])


def test_a_track_at_full_speed_ending_10_places_short_of_the_candidate():
    # the farthest end back and the fastest speed: the track's oldest place is the first of
    # the places the candidate's tracks visit
    codes = _map(n=400, n_bytes=8, seed=6)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=64)
    rng = np.random.default_rng(19)
    for p in 180 + 2 * np.arange(6):  # 180, 182, ..., 190
        loc._recent.append(_query(codes, int(p), rng, flip=0.1))
    places = np.array([200])
    scores, ends, speeds = loc._track_scores(places, 6)
    ref = _reference_tracks(loc, places, 6)[0]
    assert (ends[0], speeds[0]) == (190, 2.0) == (ref[1], ref[2])
    np.testing.assert_allclose(scores[0], ref[0], atol=1e-6)


def test_a_cold_start_whose_index_finds_nothing():
    # no candidate from the index: lost, and nothing to re-seed around, until the search of
    # every place's track (a lost guess, from its 4th frame) finds the route; without that
    # search the layer stays lost
    codes = _map(n=5000)
    for full_search_places, found in ((1 << 20, True), (0, False)):
        loc = LargeLocalizer(
            codes, _FindsNothing().build(codes), window=256, full_search_places=full_search_places
        )
        rng = np.random.default_rng(20)
        fixes = [loc.update_code(_query(codes, 1000 + t, rng)) for t in range(10)]
        assert {f.state for f in fixes[:4]} == {"lost"} and loc.n_searches_ == (5 if found else 9)
        if found:
            assert loc.n_reseeds_ == 1 and loc.n_full_searches_ == 1
            assert all(
                f.state == "localized" and f.place == 1000 + t
                for t, f in enumerate(fixes)
                if t >= 4
            )
        else:
            assert {f.state for f in fixes} == {"lost"} and loc.n_reseeds_ == 0


def test_the_odometry_given_to_update_code_steps_the_replay(monkeypatch):
    # a kidnap onto a stretch driven at 2 places a frame, the odometry saying so: the layer
    # the re-seed starts is stepped through the lost frames with that odometry
    from flyvpr.large.codes import hamming_similarity
    from flyvpr.temporal.cann import WindowedCANN

    codes = _map(n=5000)
    rng = np.random.default_rng(21)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=256)
    replays = []
    real = LargeLocalizer._replay

    def spy(self, ends, tracks, speeds, n_frames, hold=False):
        frames = list(self._recent)[-n_frames:-1]
        real(self, ends, tracks, speeds, n_frames, hold)
        layer = self.filter_
        replays.append((ends, tracks, speeds, frames, layer.place_, layer.confidence_))

    monkeypatch.setattr(LargeLocalizer, "_replay", spy)
    for t, p in enumerate(1000 + 2 * np.arange(40)):
        loc.update_code(_query(codes, int(p), rng), None if t == 0 else 2.0)
    replays.clear()
    for p in 3000 + 2 * np.arange(30):
        loc.update_code(_query(codes, int(p), rng), 2.0)
        if replays:
            break
    ((ends, tracks, speeds, frames, place, confidence),) = replays
    ref = WindowedCANN(loc.n_places, **loc._layer)
    start = ends - np.rint(speeds * len(frames)).astype(np.int64)
    ref.reseed(np.clip(start, 0, loc.n_places - 1), np.exp((tracks - tracks.max()) * 256 / 8))
    for i, code in enumerate(frames):
        lo, hi = ref.window_
        ref.step(hamming_similarity(code[None], codes, lo, hi)[0], None if i == 0 else 2.0)
    assert (place, confidence) == (ref.place_, ref.confidence_)


@pytest.mark.parametrize("n", [1, 2, 6, 17])
def test_a_map_shorter_than_the_fastest_track_is_searched(n):
    # The every-track search of a lost guess reaches back up to 2 places per frame over the
    # pooled frames: on a map shorter than that the far-back frames have no place to score.
    codes = _map(n=n, n_bytes=8)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=16, k=1)
    rng = np.random.default_rng(0)
    for _ in range(12):
        fix = loc.update_code(rng.integers(0, 256, 8, dtype=np.uint8))
        assert 0 <= fix.place < n and 0.0 <= fix.confidence <= 1.0
    # and a route on it is still found
    loc.reset()
    for t in range(12):
        fix = loc.update_code(_query(codes, min(t, n - 1), rng, flip=0.05))
    assert abs(fix.place - min(11, n - 1)) <= 2


def test_a_map_smaller_than_k_offers_every_place():
    # k (300 by default) above the map's 100 places: the index returns all of them
    codes = _map(n=100)
    rng = np.random.default_rng(21)
    index = ExhaustiveIndex().build(codes)
    asked = []
    search = index.search

    def spy(q, k):
        asked.append(k)
        places, dist = search(q, k)
        assert all(sorted(row.tolist()) == list(range(100)) for row in places)
        return places, dist

    index.search = spy
    loc = LargeLocalizer(codes, index, window=32)
    fixes = _drive(loc, codes, 20 + np.arange(40), rng, flip=0.2)
    assert asked and set(asked) == {100}
    assert fixes[-1].state == "localized" and abs(fixes[-1].place - 59) <= 2


def test_frames_never_searched_pool_as_no_candidates_on_a_map_smaller_than_k():
    # 6 frames pooled, only the newest 2 searched (reseed_after=2): the 4 others give no
    # candidate, padded to the index's width (every place of the 100)
    codes = _map(n=100)
    rng = np.random.default_rng(22)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=32, reseed_after=2)
    for p in 40 + np.arange(6):
        loc._recent.append(_query(codes, int(p), rng, flip=0.1))
        loc._velocities.append(None)
    loc.n_frames_ = 5
    loc._proven = True  # the index's candidates only
    places = loc._candidates(6)
    assert loc.n_searches_ == 2 and sorted(loc._found) == [4, 5]
    assert places.size > 0 and 45 in places[:10].tolist()


def test_repeated_codes_are_not_held_unless_asked():
    # a map's short codes repeat over frames that differ by sensor noise only, so the layer
    # takes a repeated code as a new frame by default; hold_repeats=True holds it
    codes = _map(n=3000)
    rng = np.random.default_rng(2)
    truth = 1000 + np.arange(60)
    queries = [_query(codes, p, rng) for p in truth]
    for hold, held in ((None, 0), (True, 10)):
        params = {} if hold is None else {"hold_repeats": hold}
        loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=512, **params)
        assert loc.filter_.cann_.hold_repeats is bool(hold)
        fixes = [loc.update_code(q) for q in queries + [queries[-1]] * 10]
        assert loc.filter_.cann_.n_held_ == held
        assert abs(fixes[-1].place - truth[-1]) <= 2


def test_on_a_map_of_at_most_k_places_every_place_is_a_candidate():
    # 200 places, answers 0.4 of their bits flipped: multi-index hashing (radius 1) finds few
    # of them near the query, the exact scan every place; with k >= the map's places both
    # localizers search every place, and answer alike
    codes = _map(n=200)
    truth = 50 + np.arange(80)
    runs = {}
    for name, index in (("exact", ExhaustiveIndex()), ("mih", MultiIndexHash(radius=1))):
        loc = LargeLocalizer(codes, index.build(codes), k=300)
        runs[name] = _drive(loc, codes, truth, np.random.default_rng(3), flip=0.4)
        found, _ = loc._search.search(_query(codes, 60, np.random.default_rng(0))[None], 200)
        assert (found >= 0).all()  # every place
        assert loc.index is index  # (the given index stays the localizer's)
    assert [f.place for f in runs["mih"]] == [f.place for f in runs["exact"]]
    assert [f.confidence for f in runs["mih"]] == [f.confidence for f in runs["exact"]]
    # a larger map than k: the index's own answers (multi-index hashing finds fewer)
    small_k = LargeLocalizer(codes, MultiIndexHash(radius=1).build(codes), k=100)
    found, _ = small_k._search.search(_query(codes, 60, np.random.default_rng(0), 0.4)[None], 100)
    assert isinstance(small_k._search, MultiIndexHash) and (found < 0).any()


def test_a_refused_frame_leaves_nothing_behind():
    codes = _map(n=2000)
    rng = np.random.default_rng(5)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=256)
    _drive(loc, codes, 100 + np.arange(20), rng)
    kept = (list(loc._recent), list(loc._velocities), loc.n_frames_)
    for bad, error in ((float("nan"), ValueError), (float("inf"), ValueError), ("1", TypeError)):
        with pytest.raises(error, match="velocity must be"):
            loc.update_code(_query(codes, 120, rng), bad)
        assert (list(loc._recent), list(loc._velocities), loc.n_frames_) == kept
    # lost frames whose re-seed replays the stored odometry: no refused value among it
    for place in 1500 + np.arange(12):
        loc.update_code(_query(codes, int(place), rng), None)
    assert None in loc._velocities and loc.n_frames_ == kept[2] + 12


def test_distances_in_metres_are_places_over_the_spacing():
    # odometry in metres with place_spacing 2.5 m steps the layer as the same odometry given
    # in places, frame by frame, in a batch of images and on a code
    rng, images, enc, codes, index = _image_map(7)
    frames = np.clip(images[100:130] + rng.normal(0, 0.05, (30, 32, 64)), 0, 1).astype(np.float32)
    moved = np.r_[np.nan, np.full(29, 1.0)]  # places; the first frame has none
    moved[10] = np.nan  # an outage
    in_places = LargeLocalizer(codes, index, encoder=enc, window=64)
    in_metres = LargeLocalizer(codes, index, encoder=enc, window=64, place_spacing=2.5)
    batch = LargeLocalizer(codes, index, encoder=enc, window=64, place_spacing=2.5)
    fixes = batch.update_batch(frames, distances=2.5 * moved)
    assert fixes.places.dtype == np.int64 and fixes.states.dtype.kind == "U"
    for t in range(30):
        v = None if np.isnan(moved[t]) else float(moved[t])
        a = in_places.update(frames[t], v)
        b = in_metres.update(frames[t], distance=None if v is None else 2.5 * v)
        assert (a.place, a.state, a.confidence) == (b.place, b.state, b.confidence)
        assert (fixes.places[t], fixes.states[t], fixes.confidences[t]) == (
            a.place,
            a.state,
            a.confidence,
        )
    assert fixes.places[-1] == 129 and fixes.states[-1] == "localized"
    assert fixes.relocated.sum() == in_places.n_reseeds_ == batch.n_reseeds_ >= 1
    assert fixes.relocated[0]  # the first frame is searched for in the whole map
    # velocities in a batch: the same again
    again = LargeLocalizer(codes, index, encoder=enc, window=64).update_batch(
        frames, velocities=[None if np.isnan(m) else m for m in moved]
    )
    np.testing.assert_array_equal(again.places, fixes.places)
    np.testing.assert_array_equal(again.confidences, fixes.confidences)


def test_odometry_errors_are_named_and_change_nothing():
    codes = _map(n=1000)
    index = ExhaustiveIndex().build(codes)
    loc = LargeLocalizer(codes, index, window=128)
    code = codes[500]
    with pytest.raises(ValueError, match=r"needs place_spacing.*LargeLocalizer\(place_spacing="):
        loc.update_code(code, distance=3.0)
    spaced = LargeLocalizer(codes, index, window=128, place_spacing=2.0)
    with pytest.raises(ValueError, match="velocity .places. or distance .metres., not both"):
        spaced.update_code(code, 1.0, distance=2.0)
    with pytest.raises(ValueError, match="distance must be >= 0"):
        spaced.update_code(code, distance=-1.0)
    with pytest.raises(ValueError, match="velocity must be finite"):
        spaced.update_code(code, float("nan"))
    with pytest.raises(TypeError, match="velocity must be a number"):
        spaced.update_code(code, "1")
    assert loc.n_frames_ == spaced.n_frames_ == 0  # refused frames leave nothing
    with pytest.raises(ValueError, match="update_batch needs an encoder"):
        loc.update_batch(np.zeros((2, 32, 64), np.float32))
    with pytest.raises(ValueError, match="place_spacing must be > 0"):
        LargeLocalizer(codes, index, place_spacing=0.0)


def test_a_compact_localizer_takes_the_map_s_spacing(tmp_path):
    from flyvpr.large.recording import CompactMap, compact_localizer

    class _Map:  # what compact_localizer reads of a CompactMap
        large_map = type("M", (), {"codes": _map(n=300)})()
        encoder = None
        path = tmp_path / "m.fvmap"
        place_spacing = 4.0

        breaks = (120,)

    assert compact_localizer(_Map()).place_spacing == 4.0
    assert compact_localizer(_Map(), place_spacing=1.5).place_spacing == 1.5
    _Map.place_spacing = None
    assert compact_localizer(_Map()).place_spacing is None
    assert CompactMap.place_spacing.__doc__.startswith("Metres between consecutive places")
    # the map's breaks go to every layer, unless given: () reads the map as one route
    loc = compact_localizer(_Map())
    assert loc.filter_.breaks_.tolist() == [120] and loc._layer["breaks"] == (120,)
    assert compact_localizer(_Map(), breaks=()).filter_.breaks_.size == 0
    assert compact_localizer(_Map(), breaks=[7, 9]).filter_.breaks_.tolist() == [7, 9]
    assert compact_localizer(_Map(), breaks=None).filter_.breaks_.tolist() == [120]


def test_refused_odometry_is_counted_across_re_seeds():
    # a glitch of the odometry (a jump of 200 places in one frame) is refused by the layer
    # and counted on the localizer, also after a re-seed has replaced the layer that refused
    # an earlier one; reset() forgets the count
    codes = _map(n=5000)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=256)
    rng = np.random.default_rng(4)
    place = 1000
    for t in range(80):
        if t == 40:  # kidnapped: the layer re-seeds elsewhere
            place = 3000
        v = None if t in (0, 40) else (200.0 if t in (25, 70) else 1.0)
        loc.update_code(_query(codes, place, rng), v)
        place += 1
        if t == 30:
            assert loc.n_odometry_refused_ == 1
    assert loc.n_reseeds_ >= 2 and loc.filter_.cann_.n_odometry_refused_ == 1
    assert loc.n_odometry_refused_ == 2
    loc.reset()
    assert loc.n_odometry_refused_ == 0


def test_every_layer_runs_with_the_breaks_of_its_own_window():
    # a map of two recordings joined at 3000 (and one more break at 7000); the robot drives
    # up to the join, is kidnapped to 6800 (re-seeds, a held layer) and drives past 7000
    codes = _map(n=10000)
    breaks = (3000, 7000)
    loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=256, breaks=breaks)
    rng = np.random.default_rng(2)  # (a draw whose kidnap holds a displaced layer)
    places = [*range(2850, 3000), *range(6800, 7100)]
    checked = 0
    for p in places:
        loc.update_code(_query(codes, p, rng, flip=0.38))
        for layer in (loc.filter_, loc.held_):
            if layer is None:
                continue
            assert layer.breaks_.tolist() == list(breaks)
            lo, hi = layer.window_
            local = [b - lo for b in breaks if lo < b < hi]
            assert list(layer.cann_.breaks) == local
            assert layer.cann_._params["breaks"].tolist() == local
            checked += 1
    assert loc.n_reseeds_ >= 1 and checked > len(places)
    assert abs(loc.filter_.place_ - 7099) <= 2 and loc.filter_.state_ == "localized"
