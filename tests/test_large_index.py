import numpy as np
import pytest

from flyvpr.large import INDEXES, ExhaustiveIndex, MultiIndexHash, pool_candidates


def slow_top_k(q, codes, k):
    bits = np.unpackbits(codes, axis=1)
    out = []
    for row in np.unpackbits(q, axis=1):
        d = (bits != row).sum(axis=1)
        order = np.lexsort((np.arange(len(d)), d))[:k]
        out.append((order, d[order]))
    return np.array([o for o, _ in out]), np.array([d for _, d in out])


@pytest.fixture(scope="module")
def codes():
    return np.random.default_rng(0).integers(0, 256, (2000, 32), dtype=np.uint8)


def near(codes, idx, n_flips, seed):
    rng = np.random.default_rng(seed)
    q = codes[idx].copy()
    for row in q:
        bits = rng.choice(256, n_flips, replace=False)
        np.bitwise_xor.at(row, bits // 8, (1 << (bits % 8)).astype(np.uint8))
    return q


@pytest.mark.parametrize("n_query", [1, 5])
def test_exhaustive_is_exact(codes, n_query):
    q = near(codes, np.arange(n_query) * 7, 40, 0)
    places, dist = ExhaustiveIndex().build(codes).search(q, 10)
    ref_p, ref_d = slow_top_k(q, codes, 10)
    np.testing.assert_array_equal(places, ref_p)
    np.testing.assert_array_equal(dist, ref_d)


def test_exhaustive_ties_lower_place_first():
    codes = np.zeros((6, 8), np.uint8)
    codes[[1, 4], 0] = 1
    places, dist = ExhaustiveIndex().build(codes).search(codes[1], 4)
    assert places.tolist() == [[1, 4, 0, 2]] and dist.tolist() == [[0, 0, 1, 1]]


def test_mih_exact_within_its_guarantee(codes):
    # 16 tables, radius 1: exact for neighbours nearer than 16 * 2 = 32 bits
    q = near(codes, np.arange(20), 20, 1)
    places, dist = MultiIndexHash(radius=1).build(codes).search(q, 1)
    np.testing.assert_array_equal(places[:, 0], np.arange(20))
    np.testing.assert_array_equal(dist[:, 0], 20)


def test_mih_reranks_exactly(codes):
    q = near(codes, [3], 60, 2)
    index = MultiIndexHash(radius=2).build(codes)
    places, dist = index.search(q, 5)
    found = places[places >= 0]
    bits = np.unpackbits(codes[found], axis=1) != np.unpackbits(q, axis=1)
    np.testing.assert_array_equal(dist[0, : len(found)], bits.sum(axis=1))
    assert np.all(np.diff(dist[0, : len(found)]) >= 0)


def test_mih_tables_are_a_counting_sort(codes):
    index = MultiIndexHash(n_tables=3).build(codes)
    assert index.starts_.shape == (3, 65537) and index.places_.shape == (3, 2000)
    keys = codes.view(np.uint16)[:, 1]
    b = int(keys[10])
    bucket = index.places_[1, index.starts_[1, b] : index.starts_[1, b + 1]]
    np.testing.assert_array_equal(bucket, np.flatnonzero(keys == b))


def test_mih_pads_when_few_found():
    codes = np.random.default_rng(5).integers(0, 256, (50, 32), dtype=np.uint8)
    q = ~codes[0]  # 256 bits away from place 0, random to the rest
    places, dist = MultiIndexHash(radius=0).build(codes).search(q, 50)
    assert (places == -1).any() and (dist[places == -1] == 257).all()


@pytest.mark.parametrize(
    ("index", "k", "match"),
    [
        (MultiIndexHash(radius=3), 1, "radius"),
        (MultiIndexHash(n_tables=17), 1, "n_tables"),
        (ExhaustiveIndex(), 0, "k must be"),
        (ExhaustiveIndex(), 5000, "k must be"),
    ],
)
def test_index_errors(codes, index, k, match):
    with pytest.raises(ValueError, match=match):
        index.build(codes).search(codes[0], k)


def test_search_before_build(codes):
    with pytest.raises(ValueError, match="not built"):
        ExhaustiveIndex().search(codes[0], 1)


@pytest.mark.parametrize("name", ["faiss-ivf", "faiss-hnsw"])
def test_faiss_indexes_find_near_codes(codes, name):
    pytest.importorskip("faiss")
    q = near(codes, np.arange(10), 10, 3)
    places, dist = INDEXES[name]().build(codes).search(q, 3)
    assert places.shape == (10, 3)
    np.testing.assert_array_equal(places[:, 0], np.arange(10))
    np.testing.assert_array_equal(dist[:, 0], 10)


def test_faiss_missing_names_the_extra(monkeypatch, codes):
    import sys

    monkeypatch.setitem(sys.modules, "faiss", None)
    with pytest.raises(ImportError, match=r"flyvpr\[faiss\]"):
        INDEXES["faiss-ivf"]().build(codes)


def test_pool_prefers_a_consistent_track():
    places = [[100, 500], [101, 700], [900, 102]]
    dist = [[80, 100], [80, 100], [70, 85]]
    best, score = pool_candidates(places, dist, n_bits=256)
    assert best[0] == 102
    assert np.all(np.diff(score) <= 0)
    # the score of 102: each frame's best supporting weight, 0.5 - d / 256
    assert score[0] == pytest.approx(3 * 0.5 - (80 + 80 + 85) / 256)


def test_pool_reaches_a_place_missing_from_the_last_frame():
    best, _ = pool_candidates([[50], [51], [52], [7]], [[60], [60], [60], [100]], 256)
    assert best[0] == 53


def test_pool_ignores_padding_and_checks_input():
    best, score = pool_candidates([[-1, 3]], [[257, 90]], 256)
    assert best.tolist() == [3]
    empty, _ = pool_candidates([[-1]], [[257]], 256)
    assert empty.size == 0
    with pytest.raises(ValueError, match="same shape"):
        pool_candidates([[1, 2]], [[1]], 256)
    with pytest.raises(ValueError, match="speed"):
        pool_candidates([[1]], [[1]], 256, speed=(2, 1))


def _pool_by_loop(places, dist, n_bits, speed, slack):
    """pool_candidates written as its docstring says, one place and one candidate at a time."""
    n_frames = len(places)
    low, high = speed
    scored = set()
    for t in range(n_frames):
        for p in places[t]:
            if p >= 0:
                scored.add(int(np.rint(p + 0.5 * (low + high) * (n_frames - 1 - t))))
    scored |= {int(p) for p in places[-1] if p >= 0}
    totals = {}
    for s in scored:
        total = 0.0
        for t in range(n_frames):
            ahead = n_frames - 1 - t
            best = 0.0
            for p, d in zip(places[t], dist[t], strict=True):
                if p >= 0 and p + low * ahead - slack <= s <= p + high * ahead + slack:
                    best = max(best, 0.5 - d / n_bits)
            total += best
        totals[s] = total
    order = sorted(totals, key=lambda s: (-totals[s], s))
    return np.array(order, dtype=np.int64), np.array([totals[s] for s in order])


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("speed, slack", [((0.0, 2.0), 3), ((0.5, 2.0), 0), ((1.0, 1.0), 2)])
def test_pool_matches_a_loop(seed, speed, slack):
    rng = np.random.default_rng(seed)
    n_frames, k = int(rng.integers(1, 12)), int(rng.integers(1, 40))
    places = rng.integers(0, 300, (n_frames, k))
    places[rng.random((n_frames, k)) < 0.2] = -1  # padding
    if n_frames > 2:
        places[1] = -1  # a frame that was not searched
    dist = rng.integers(40, 200, (n_frames, k))
    best, score = pool_candidates(places, dist, 256, speed=speed, slack=slack)
    ref_best, ref_score = _pool_by_loop(places, dist, 256, speed, slack)
    np.testing.assert_array_equal(best, ref_best)
    np.testing.assert_allclose(score, ref_score)


def test_stored_tables_naming_a_place_past_the_map_are_refused_not_read(codes):
    built = MultiIndexHash().build(codes)
    places = np.array(built.places_)
    places[:, :] = len(codes)  # every entry one past the last place (as a corrupt file holds)
    index = MultiIndexHash.from_arrays(codes, built.starts_, places)
    with pytest.raises(ValueError, match=r"name a place past the map's \d+ places: the index is"):
        index.search(codes[:3], 5)


@pytest.mark.parametrize("damage", ["first", "falls"])
def test_stored_bucket_starts_must_rise_from_0(codes, damage):
    built = MultiIndexHash().build(codes)
    starts = np.array(built.starts_)
    if damage == "first":
        starts[0, 0] = 1
    else:
        starts[0, 100] = starts[0, 101] + 1
    with pytest.raises(ValueError, match=r"starts must rise from 0 to the number of places"):
        MultiIndexHash.from_arrays(codes, starts, built.places_)
