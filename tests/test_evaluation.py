import numpy as np
import pytest

from flyvpr.evaluation import RESULT_FIELDS, evaluate_method, self_match_share, speed_profile
from flyvpr.methods import make_method


def test_speed_profile_constant():
    np.testing.assert_array_equal(speed_profile(10, 2.0), [0, 2, 4, 6, 8])
    np.testing.assert_array_equal(speed_profile(5, 1.0), np.arange(5))


def test_speed_profile_random_range_is_seeded_and_bounded():
    a = speed_profile(1000, (1.0, 1.5), random_state=3)
    b = speed_profile(1000, (1.0, 1.5), random_state=3)
    np.testing.assert_array_equal(a, b)
    steps = np.diff(a)
    assert steps.min() >= 1 and steps.max() <= 2
    assert 1000 / 1.5 - 5 < len(a) < 1000 / 1.0
    assert a[0] == 0 and a[-1] < 1000


@pytest.mark.parametrize("speed", [0.0, -1.0, (1.5, 1.0), "fast"])
def test_speed_profile_errors(speed):
    with pytest.raises(ValueError, match="speed"):
        speed_profile(10, speed)


def test_evaluate_method_fields(random_images):
    ref = random_images(30)
    gt = np.eye(30, dtype=bool)
    res = evaluate_method("flyhash", ref, ref, gt, seed=0)
    assert set(RESULT_FIELDS) <= set(res)  # the documented fields are all there
    assert res["auc"] == pytest.approx(1.0)
    assert res["recall_at_1"] == 1.0
    assert res["extended_precision"] == 1.0
    assert res["timing"]["per_query_ms"] >= 0
    assert res["frontend_params"]["random_state"] == "from seed 0"


def test_evaluate_method_counts_the_queries_with_a_match(random_images):
    # recall's denominator, so that R@1 and the curve can be recomputed from a result file
    ref, qry = random_images(20), random_images(26)
    gt = np.abs(np.arange(26)[:, None] - np.arange(20)[None, :]) <= 1  # queries 21..25: none
    res, S = evaluate_method("pixels", ref, qry, gt, return_scores=True)
    assert res["n_query_with_match"] == 21
    best = S.argmax(axis=1)
    assert res["recall_at_1"] == gt[np.arange(26), best].sum() / 21


def test_check_true_matches_refuses_a_ground_truth_without_any():
    from flyvpr.datasets import Benchmark, Traverse
    from flyvpr.evaluation import check_true_matches

    ref = Traverse("ref", [f"r{i}.png" for i in range(3)])
    qry = Traverse("qry", [f"q{i}.png" for i in range(2)])
    gt = np.zeros((2, 3), dtype=bool)
    none = Benchmark("generic", ref, qry, gt, {"metres": 5.0})
    with pytest.raises(
        ValueError,
        match=r"^the ground truth gives no query a true match: none of the 2 queries lies "
        r"within the tolerance \(5\.0 metres\) of any of the 3 references, so recall is undef",
    ):
        check_true_matches(none)
    gt[1, 2] = True
    assert check_true_matches(Benchmark("generic", ref, qry, gt, {"metres": 5.0})) is None


def test_check_true_matches_warns_of_a_ground_truth_that_matches_everything(caplog):
    # a tolerance as long as the traverses, or degrees read as metres: every method scores 1
    from flyvpr.datasets import Benchmark, Traverse
    from flyvpr.evaluation import check_true_matches

    ref = Traverse("ref", [f"r{i}.png" for i in range(3)])
    qry = Traverse("qry", [f"q{i}.png" for i in range(2)])
    gt = np.ones((2, 3), dtype=bool)
    with caplog.at_level("WARNING", logger="flyvpr"):
        check_true_matches(Benchmark("generic", ref, qry, gt, {"frames": 30}))
    (record,) = caplog.records
    assert record.getMessage().startswith(
        "the ground truth matches every one of the 2 queries with every one of the 3 references "
        "(tolerance 30 frames): every method scores 1 whatever it answers"
    )
    caplog.clear()
    gt[0, 0] = False
    with caplog.at_level("WARNING", logger="flyvpr"):
        check_true_matches(Benchmark("generic", ref, qry, gt, {"frames": 30}))
    assert not caplog.records


def test_evaluate_method_checks_gt_shape(random_images):
    ref = random_images(5)
    with pytest.raises(ValueError, match="ground_truth must have shape"):
        evaluate_method("pixels", ref, ref[:3], np.eye(5, dtype=bool))


def test_evaluate_method_measures_model_bytes(random_images):
    ref = random_images(20)
    res = evaluate_method("flyhash", ref, ref, np.eye(20, dtype=bool), measure_model_bytes=True)
    assert 1000 < res["model_bytes"] < 64 * 2048 // 8 + 20_000


def test_evaluate_method_extended_precision_matches_metrics(random_images):
    from flyvpr import metrics

    ref, qry = random_images(25), random_images(25)
    gt = np.abs(np.arange(25)[:, None] - np.arange(25)[None, :]) <= 1
    res, S = evaluate_method("pixels", ref, qry, gt, return_scores=True)
    assert res["extended_precision"] == metrics.extended_precision(S, gt)
    assert res["recall_at_100_precision"] == metrics.recall_at_100_precision(S, gt)


def test_self_match_share_tells_a_models_own_frames(random_images):
    ref = random_images(50)
    model = make_method("pixels").fit(ref)
    assert self_match_share(model, ref) == 1.0  # every image is its own best place
    other = random_images(50)
    assert self_match_share(model, other) <= 0.2  # chance: 5 of 50 places within 2
    # the first 40 images, then the first 10 again: only the first 40 find themselves
    mixed = np.concatenate([ref[:40], ref[:10]])
    assert self_match_share(model, mixed) == pytest.approx(0.8)
    # evenly sampled, the ends included: 5 of [0, 12, 24, 37, 49] are 0, 12, 24, 37 (own) and
    # 49 (not)
    assert self_match_share(model, mixed, sample=5) == pytest.approx(0.8)
    # within radius places: images shifted by 3 places find their own only with radius >= 3
    shifted = np.concatenate([ref[3:], ref[:3]])
    assert self_match_share(model, shifted, radius=2) <= 0.1
    assert self_match_share(model, shifted, radius=3) >= 0.9
    with pytest.raises(ValueError, match="empty"):
        self_match_share(model, ref[:0])
    with pytest.raises(ValueError, match="knows 50 reference places; got 49 images"):
        self_match_share(model, ref[:49])
    with pytest.raises(ValueError, match="sample must be >= 1"):
        self_match_share(model, ref, sample=0)
    with pytest.raises(ValueError, match="radius must be >= 0"):
        self_match_share(model, ref, radius=-1)
    # identical frames tie everywhere: each still finds its own place (a tie with it counts)
    blank = np.full((30, 32, 64), 0.5, np.float32)
    assert self_match_share(make_method("pixels").fit(blank), blank, radius=0) == 1.0


@pytest.mark.parametrize("name", ["flyhash", "kenyon+cann", "flynet+rnn"])
def test_an_int_seed_refits_the_same_map_and_a_generator_goes_on(synthetic_route, name):
    r = synthetic_route(40, random_state=3)
    ref, qry = r.reference_images, r.query_images
    params = {"epochs": 3} if name.startswith("flynet") else None
    model = make_method(name, 0, frontend_params=params)
    first = model.fit(ref).score(qry)
    np.testing.assert_array_equal(model.fit(ref).score(qry), first)
    # the first fit is that of a new method with the same seed
    np.testing.assert_array_equal(make_method(name, 0, params).fit(ref).score(qry), first)
    # a Generator is a stream: a refit draws on (the projections differ)
    model = make_method(name, np.random.default_rng(0), params)
    np.testing.assert_array_equal(model.fit(ref).score(qry), first)
    assert not np.array_equal(model.fit(ref).score(qry), first)


def test_a_part_seeded_after_make_method_keeps_its_seed(synthetic_route):
    ref = synthetic_route(40, random_state=3).reference_images
    model = make_method("flyhash", 0)
    model.frontend.set_params(random_state=7)
    model.fit(ref)
    assert model.frontend.random_state == 7
    np.testing.assert_array_equal(
        model.frontend.score(ref), make_method("flyhash", 7).fit(ref).frontend.score(ref)
    )


def test_a_method_name_must_be_a_str():
    with pytest.raises(TypeError, match=r"^method must be a method name \(a str.*got list$"):
        make_method(["kenyon"])


def test_a_filter_trained_on_the_references_says_so_when_they_are_too_few():
    ref = np.random.default_rng(0).random((1, 32, 64), dtype=np.float32)
    with pytest.raises(ValueError, match=r"^method 'kenyon\+rnn': its filter learns from the re"):
        make_method("kenyon+rnn", 0).fit(ref)
