"""The place-velocity layer's kernels (``cann/_layer.py``) against slow, obviously right references.

Each kernel runs both ways (plain Python and, where numba is importable, compiled) and is
checked against a loop or NumPy reference written here from its docstring, plus tiny cases
worked by hand.  ``advance`` is checked in parts as well as whole: its move alone (the
evidence all ones) against ``ref_propagate``, and its evidence alone (no move, no mixing, no
floor: the prior is the activity as given) against ``ref_observe``.  Written to kill mutants
(see CONTRIBUTING, mutation testing): each test pins a number that a small change of the code
would move.
"""

import itertools
import math
import warnings

import numpy as np
import pytest

from flyvpr.temporal.cann import CANN, _kernels


@pytest.fixture
def kernels(cann_kernel_mode):
    """The layer's kernels, compiled and not (see conftest's cann_kernel_mode)."""
    found, compiled = _kernels.get_kernels(table="layer")
    assert compiled == (cann_kernel_mode == "compiled")
    return found


# -- references ------------------------------------------------------------------------------
def ref_propagate(p, shifts, stay, neighbour, jump, redraw, prior, floor_rate):
    """The prior of ``advance`` (the move, velocity mixing, redraw and re-seed, before the
    evidence) as float64 loops: (the new activity, the mass left after the move)."""
    n_v, n = p.shape
    moved = np.zeros((n_v, n))
    for j in range(n_v):
        for i in range(n):
            if 0 <= i - shifts[j] < n:
                moved[j, i] = p[j, i - shifts[j]]
    total = moved.sum()
    if total == 0.0:
        return np.tile(np.asarray(prior, np.float64)[:, None] / n, (1, n)), 0.0
    mixed = np.zeros((n_v, n))
    for j in range(n_v):
        mixed[j] += stay * moved[j]
        for to in (j - 1, j + 1):  # half of the change to each side; the ends keep theirs
            mixed[to if 0 <= to < n_v else j] += neighbour / 2 * moved[j]
        mixed[j] += jump * redraw[j] * moved.sum(axis=0)
    out = mixed * (1.0 - floor_rate) / total
    out += floor_rate * np.asarray(prior, np.float64)[:, None] / n
    return out, total


def ref_observe(p, x, gain):
    """The evidence step of ``advance``: the activity weighed by ``exp(gain * x)`` and
    normalised.  (new activity, place marginal, log of the normaliser), float64."""
    q = p.astype(np.float64) * np.exp(gain * x.astype(np.float64))
    z = q.sum()
    return q / z, (q / z).sum(axis=0), math.log(z)


def ref_advance(p, shifts, stay, neighbour, jump, redraw, prior, floor_rate, weight):
    """(out, predicted, marginal, row_mass, z): the moved layer weighed by the evidence; where
    that leaves nothing, the prior ``prior[j] / n`` weighed by the evidence alone."""
    moved, _ = ref_propagate(p, shifts, stay, neighbour, jump, redraw, prior, floor_rate)
    out = moved * weight.astype(np.float64)
    z = out.sum()
    if z == 0.0:
        n = p.shape[1]
        out = np.asarray(prior, np.float64)[:, None] / n * weight.astype(np.float64)
        z = out.sum()
    return out, moved.sum(axis=0), out.sum(axis=0) / z, out.sum(axis=1) / z, z


def ref_window_sums(marginal, radius):
    n = marginal.size
    out = np.array(
        [marginal[max(i - radius, 0) : i + radius + 1].sum(dtype=np.float64) for i in range(n)]
    )
    return out, int(np.argmax(out))  # np.argmax: the first of equals


def ref_exceedance(x, place, stride):
    sampled = x[::stride]
    return max(int(np.sum(sampled >= x[place])), 1) / sampled.size


# -- running advance -------------------------------------------------------------------------
def _run_advance(kernels, p, shifts, stay, neighbour, jump, redraw, prior, floor_rate, weight):
    p = np.array(p, np.float32)
    n_v, n = p.shape
    out = np.full_like(p, np.nan)
    predicted = np.full(n, np.nan, np.float32)
    marginal = np.full(n, np.nan, np.float32)
    row_mass = np.full(n_v, np.nan)
    before = p.copy()
    z = kernels["advance"](
        p,
        out,
        np.asarray(shifts, np.int64),
        stay,
        neighbour,
        jump,
        np.asarray(redraw, np.float64),
        np.asarray(prior, np.float64),
        floor_rate,
        np.asarray(weight, np.float32),
        predicted,
        marginal,
        row_mass,
    )
    np.testing.assert_array_equal(p, before)  # the old activity is only read
    return out, predicted, marginal, row_mass, z


def _move(kernels, p, shifts, stay, neighbour, jump, redraw, prior, floor_rate):
    """``advance`` with the evidence all ones: (out normalised, predicted, row_mass, z).
    ``out`` is then the prior itself, and ``marginal`` equals ``predicted``."""
    n = np.shape(p)[1]
    args = (shifts, stay, neighbour, jump, redraw, prior, floor_rate, np.ones(n))
    out, predicted, marginal, row_mass, z = _run_advance(kernels, p, *args)
    np.testing.assert_allclose(marginal, predicted, rtol=2e-6, atol=1e-12)
    return out / z, predicted, row_mass, z


def _weight(x, gain):
    """The evidence as the filter passes it: ``exp(gain * (x - max x))`` in float32."""
    x = np.asarray(x, np.float32)
    return np.exp(np.float32(gain) * (x - x.max()))


def _observe(kernels, p, weight):
    """``advance`` with no move, no mixing and no floor (the prior is ``p`` as given,
    normalised), weighed by ``weight``: (out normalised, marginal, row_mass, z)."""
    p = np.asarray(p, np.float32)
    n_v, n = p.shape
    third = np.full(n_v, 1.0 / n_v)  # the velocity prior: unused without a floor
    args = (np.zeros(n_v, np.int64), 1.0, 0.0, 0.0, third, third, 0.0, weight)
    out, predicted, marginal, row_mass, z = _run_advance(kernels, p, *args)
    # the prior's marginal: the activity's, normalised
    np.testing.assert_allclose(predicted, p.sum(axis=0) / p.sum(dtype=np.float64), rtol=2e-6)
    return out / z, marginal, row_mass, z


# -- advance: the move (the evidence all ones) ------------------------------------------------
@pytest.mark.parametrize("floor_rate", [0.0, 0.05])
def test_move_against_reference(kernels, floor_rate):
    rng = np.random.default_rng(0)
    n = 9
    shifts = [0, 1, 2, -1, -3, 8, 9, 12, -9, -11]  # zero, forward, backward, beyond the route
    n_v = len(shifts)
    p = rng.random((n_v, n))
    p /= p.sum()
    redraw = rng.random(n_v)
    redraw /= redraw.sum()
    prior = rng.random(n_v)
    prior /= prior.sum()
    args = (shifts, 0.7, 0.2, 0.1, redraw, prior, floor_rate)
    got, predicted, row_mass, z = _move(kernels, p, *args)
    expected, _ = ref_propagate(p.astype(np.float32), *args)
    np.testing.assert_allclose(got, expected, rtol=2e-6, atol=1e-9)
    np.testing.assert_allclose(predicted, expected.sum(axis=0), rtol=2e-6)
    np.testing.assert_allclose(row_mass, expected.sum(axis=1), rtol=2e-6)
    assert z == pytest.approx(1.0, abs=1e-6)  # mass conserved


@pytest.mark.parametrize(
    ("shift", "expected", "total"),
    [
        (1, [0.0, 0.1, 0.2, 0.3], 0.6),  # what enters at the open end is 0; 0.4 leaves
        (0, [0.1, 0.2, 0.3, 0.4], 1.0),
        (-1, [0.2, 0.3, 0.4, 0.0], 0.9),
        (2, [0.0, 0.0, 0.1, 0.2], 0.3),
        (-3, [0.4, 0.0, 0.0, 0.0], 0.4),
    ],
)
def test_move_one_row_by_hand(kernels, shift, expected, total):
    row = [[0.1, 0.2, 0.3, 0.4]]
    p, predicted, row_mass, z = _move(kernels, row, [shift], 1.0, 0.0, 0.0, [1.0], [1.0], 0.0)
    np.testing.assert_allclose(p[0], np.array(expected) / total, rtol=1e-6)
    np.testing.assert_allclose(predicted, np.array(expected) / total, rtol=1e-6)
    assert z == pytest.approx(1.0, rel=1e-6)
    assert row_mass[0] == pytest.approx(1.0, rel=1e-12)
    # with a floor: normalised to 1 - 0.2, then 0.2 / 4 places added everywhere
    p, predicted, _, z = _move(kernels, row, [shift], 1.0, 0.0, 0.0, [1.0], [1.0], 0.2)
    np.testing.assert_allclose(p[0], 0.8 * np.array(expected) / total + 0.05, rtol=1e-6)
    np.testing.assert_allclose(predicted, 0.8 * np.array(expected) / total + 0.05, rtol=1e-6)
    assert z == pytest.approx(1.0, rel=1e-6)


@pytest.mark.parametrize("shift", [4, 5, -4, -7])
@pytest.mark.parametrize("floor_rate", [0.0, 0.3])
def test_move_beyond_the_route_restarts_from_the_prior(kernels, shift, floor_rate):
    # Everything leaves: the layer starts again from the prior (whatever the floor).
    p = [[0.1, 0.2, 0.3, 0.4], [0.0] * 4]
    mixing = (0.5, 0.25, 0.25, [0.5, 0.5], [0.25, 0.75])
    p, predicted, row_mass, z = _move(kernels, p, [shift, 0], *mixing, floor_rate)
    np.testing.assert_allclose(p, [[0.0625] * 4, [0.1875] * 4], rtol=1e-6)
    np.testing.assert_allclose(predicted, [0.25] * 4, rtol=1e-6)
    np.testing.assert_allclose(row_mass, [0.25, 0.75], rtol=1e-6)
    assert z == pytest.approx(1.0, rel=1e-6)


def test_move_velocity_mixing_keeps_the_share_at_the_bank_ends(kernels):
    # One place, three velocities: 0.8 stays, 0.1 to each neighbouring velocity, and the
    # ends keep the 0.1 that would leave the bank.
    third = [1 / 3] * 3
    p, predicted, row_mass, z = _move(
        kernels, [[0.5], [0.3], [0.2]], [0] * 3, 0.8, 0.2, 0.0, third, third, 0.0
    )
    np.testing.assert_allclose(p[:, 0], [0.48, 0.31, 0.21], rtol=1e-6)
    np.testing.assert_allclose(row_mass, [0.48, 0.31, 0.21], rtol=1e-6)
    assert predicted[0] == pytest.approx(1.0, rel=1e-6)
    assert z == pytest.approx(1.0, rel=1e-6)
    # a single velocity: the neighbours are the row itself, nothing is lost
    p, predicted, _, z = _move(kernels, [[0.25, 0.75]], [0], 0.6, 0.4, 0.0, [1.0], [1.0], 0.0)
    np.testing.assert_allclose(p, [[0.25, 0.75]], rtol=1e-6)
    np.testing.assert_allclose(predicted, [0.25, 0.75], rtol=1e-6)
    assert z == pytest.approx(1.0, rel=1e-6)


def test_move_jump_redraws_the_velocity_from_the_place_total(kernels):
    # marginal [0.4, 0.6]; half stays, half is redrawn as velocity 0 (1/4) or 1 (3/4)
    p, predicted, row_mass, z = _move(
        kernels, [[0.4, 0.0], [0.0, 0.6]], [0, 0], 0.5, 0.0, 0.5, [0.25, 0.75], [0.5, 0.5], 0.0
    )
    np.testing.assert_allclose(p, [[0.25, 0.075], [0.15, 0.525]], rtol=1e-6)
    np.testing.assert_allclose(predicted, [0.4, 0.6], rtol=1e-6)
    np.testing.assert_allclose(row_mass, [0.325, 0.675], rtol=1e-6)
    assert z == pytest.approx(1.0, rel=1e-6)


def test_move_floor_reseeds_by_the_prior(kernels):
    # the case above with a floor of 0.1: 0.9 of it plus 0.1 * prior[j] / 2 places
    p, predicted, row_mass, z = _move(
        kernels, [[0.4, 0.0], [0.0, 0.6]], [0, 0], 0.5, 0.0, 0.5, [0.25, 0.75], [0.2, 0.8], 0.1
    )
    expected = 0.9 * np.array([[0.25, 0.075], [0.15, 0.525]]) + np.array([[0.01], [0.04]])
    np.testing.assert_allclose(p, expected, rtol=1e-6)
    np.testing.assert_allclose(predicted, expected.sum(axis=0), rtol=1e-6)
    np.testing.assert_allclose(row_mass, expected.sum(axis=1), rtol=1e-6)
    assert z == pytest.approx(1.0, rel=1e-6)


def test_move_normalises_what_is_left(kernels):
    # total 2 (not a probability yet), shifted by 1 -> 1.5 left, normalised to 1 - 0.4
    p, predicted, _, z = _move(kernels, [[0.5, 1.0, 0.5]], [1], 1.0, 0.0, 0.0, [1.0], [1.0], 0.4)
    expected = 0.6 * np.array([0.0, 0.5, 1.0]) / 1.5 + 0.4 / 3
    np.testing.assert_allclose(p[0], expected, rtol=1e-6)
    np.testing.assert_allclose(predicted, expected, rtol=1e-6)
    assert z == pytest.approx(1.0, rel=1e-6)


# -- advance: the evidence (no move, no mixing, no floor) ------------------------------------
@pytest.mark.parametrize("gain", [0.4, 1.0, 3.0])
def test_evidence_against_reference(kernels, gain):
    rng = np.random.default_rng(1)
    p = rng.random((4, 11)).astype(np.float32)
    p /= p.sum()
    x = rng.normal(size=11).astype(np.float32) * 2.0
    expected_p, expected_m, expected_log = ref_observe(p, x, gain)
    got, marginal, row_mass, z = _observe(kernels, p, _weight(x, gain))
    np.testing.assert_allclose(got, expected_p, rtol=2e-6)
    np.testing.assert_allclose(marginal, expected_m, rtol=2e-6)
    np.testing.assert_allclose(row_mass, expected_p.sum(axis=1), rtol=2e-6)
    # the normaliser of exp(gain * x) is z times exp(gain * max x)
    assert math.log(z) + gain * float(x.max()) == pytest.approx(expected_log, rel=1e-6, abs=1e-6)


def test_evidence_by_hand(kernels):
    p = np.full((2, 2), 0.25, np.float32)
    got, marginal, row_mass, z = _observe(kernels, p, [1.0, 3.0])
    np.testing.assert_allclose(got, [[0.125, 0.375], [0.125, 0.375]], rtol=1e-6)
    np.testing.assert_allclose(marginal, [0.25, 0.75], rtol=1e-6)
    np.testing.assert_allclose(row_mass, [0.5, 0.5], rtol=1e-6)
    assert z == pytest.approx(2.0, rel=1e-6)  # 0.5 * 1 + 0.5 * 3


def test_evidence_relative_to_the_largest_input(kernels):
    # exp(5 * 150) overflows; relative to the largest input (not at an end) it does not, and
    # the two smallest weigh exactly 0 (underflow) where the layer has mass
    p = np.array([[0.1, 0.2, 0.3, 0.4]], np.float32)
    x = np.array([-50.0, -60.0, 150.0, 149.0], np.float32)
    weight = _weight(x, 5.0)
    assert weight[0] == 0.0 and weight[1] == 0.0 and weight[2] == 1.0
    got, marginal, row_mass, z = _observe(kernels, p, weight)
    w = np.exp(5.0 * (x.astype(np.float64) - 150.0)) * [0.1, 0.2, 0.3, 0.4]
    np.testing.assert_allclose(got[0], w / w.sum(), rtol=1e-6, atol=1e-30)
    np.testing.assert_allclose(marginal, w / w.sum(), rtol=1e-6, atol=1e-30)
    assert row_mass[0] == pytest.approx(1.0, rel=1e-12)
    assert z == pytest.approx(w.sum(), rel=1e-6)  # the normaliser over exp(5 * 150)


def test_evidence_one_place(kernels):
    p = np.array([[0.25], [0.5]], np.float32)
    got, marginal, row_mass, z = _observe(kernels, p, _weight([3.0], 2.0))
    np.testing.assert_allclose(got, [[1 / 3], [2 / 3]], rtol=1e-6)
    assert marginal[0] == pytest.approx(1.0, rel=1e-6)
    np.testing.assert_allclose(row_mass, [1 / 3, 2 / 3], rtol=1e-6)
    # the prior is normalised first: z is the old normaliser exp(6) * 0.75 over 0.75 and exp(6)
    assert z == pytest.approx(1.0, rel=1e-6)
    assert math.log(z * 0.75) + 6.0 == pytest.approx(ref_observe(p, np.float32([3.0]), 2.0)[2])


# -- advance: the whole frame ----------------------------------------------------------------
@pytest.mark.parametrize(
    "shifts",
    [
        [0, 1, 2, -1, -3, 8, 9, 12, -9, -11],  # zero, forward, backward, beyond the route
        [3, 3, 3, 3, 3, 3, 3, 3, 3, 3],  # odometry: all alike
        [0, 0, 1, 1, 1, 1, 2, 2, 3, 3],  # the default bank's pattern
        [-2, -2, -1, -1, 0, 0, 1, 1, 2, 2],  # bidirectional
    ],
)
@pytest.mark.parametrize("floor_rate", [0.0, 0.05])
def test_advance_against_reference(kernels, shifts, floor_rate):
    rng = np.random.default_rng(4)
    n = 9
    n_v = len(shifts)
    p = rng.random((n_v, n)) * 3.0  # any positive scale
    redraw = rng.random(n_v)
    redraw /= redraw.sum()
    prior = rng.random(n_v)
    prior /= prior.sum()
    weight = np.exp(rng.normal(size=n))
    args = (shifts, 0.7, 0.2, 0.1, redraw, prior, floor_rate, weight)
    got = _run_advance(kernels, p, *args)
    expected = ref_advance(p.astype(np.float32), *args)
    names = ["out", "predicted", "marginal", "row_mass"]
    for name, g, e in zip(names, got[:4], expected[:4], strict=True):
        np.testing.assert_allclose(g, e, rtol=3e-6, atol=1e-12, err_msg=name)
    assert got[4] == pytest.approx(expected[4], rel=2e-6)
    assert got[2].sum(dtype=np.float64) == pytest.approx(1.0, abs=1e-6)
    assert got[3].sum() == pytest.approx(1.0, abs=1e-12)
    assert got[1].sum(dtype=np.float64) == pytest.approx(1.0, abs=1e-6)  # the prior: mass kept


def test_advance_by_hand(kernels):
    # one row moved by 1 (0.4 leaves), normalised to 1 - 0.2 plus 0.05 a place, then weighed
    out, predicted, marginal, row_mass, z = _run_advance(
        kernels, [[0.1, 0.2, 0.3, 0.4]], [1], 1.0, 0.0, 0.0, [1.0], [1.0], 0.2, [1.0, 2.0, 0.5, 1.0]
    )
    moved = 0.8 * np.array([0.0, 0.1, 0.2, 0.3]) / 0.6 + 0.05
    np.testing.assert_allclose(predicted, moved, rtol=1e-6)
    np.testing.assert_allclose(out[0], moved * [1.0, 2.0, 0.5, 1.0], rtol=1e-6)
    assert z == pytest.approx((moved * [1.0, 2.0, 0.5, 1.0]).sum(), rel=1e-6)
    np.testing.assert_allclose(marginal, out[0] / z, rtol=1e-6)
    np.testing.assert_allclose(row_mass, [1.0], rtol=1e-12)


def test_advance_mixing_and_jump_by_hand(kernels):
    # the jump and floor case of the move above, weighed by [1, 3]
    mixing = (0.5, 0.0, 0.5, [0.25, 0.75], [0.2, 0.8])
    out, predicted, marginal, row_mass, z = _run_advance(
        kernels, [[0.4, 0.0], [0.0, 0.6]], [0, 0], *mixing, 0.1, [1.0, 3.0]
    )
    moved = 0.9 * np.array([[0.25, 0.075], [0.15, 0.525]]) + np.array([[0.01], [0.04]])
    np.testing.assert_allclose(out, moved * [1.0, 3.0], rtol=1e-6)
    np.testing.assert_allclose(predicted, moved.sum(axis=0), rtol=1e-6)
    assert z == pytest.approx((moved * [1.0, 3.0]).sum(), rel=1e-6)
    np.testing.assert_allclose(marginal, (moved * [1.0, 3.0]).sum(axis=0) / z, rtol=1e-6)
    np.testing.assert_allclose(row_mass, (moved * [1.0, 3.0]).sum(axis=1) / z, rtol=1e-6)


@pytest.mark.parametrize("shift", [-4, -9, 4, 6])
def test_advance_restarts_from_the_prior_when_nothing_is_left(kernels, shift):
    mixing = (0.5, 0.25, 0.25, [0.5, 0.5], [0.25, 0.75], 0.3, [1.0, 1.0, 2.0, 1.0])
    p = [[0.1, 0.2, 0.3, 0.4], [0.5, 0.5, 0.5, 0.5]]
    out, predicted, marginal, row_mass, z = _run_advance(kernels, p, [shift, shift], *mixing)
    moved = np.array([[0.0625] * 4, [0.1875] * 4])
    np.testing.assert_allclose(out, moved * [1.0, 1.0, 2.0, 1.0], rtol=1e-6)
    np.testing.assert_allclose(predicted, [0.25] * 4, rtol=1e-6)
    assert z == pytest.approx(1.25, rel=1e-6)
    np.testing.assert_allclose(marginal, [0.2, 0.2, 0.4, 0.2], rtol=1e-6)
    np.testing.assert_allclose(row_mass, [0.25, 0.75], rtol=1e-6)
    # every unit at 0: the same
    got = _run_advance(kernels, np.zeros((2, 4)), [0, 0], *mixing)
    np.testing.assert_allclose(got[0], moved * [1.0, 1.0, 2.0, 1.0], rtol=1e-6)


@pytest.mark.parametrize(
    ("p", "shifts", "mixing", "weight", "moved"),
    [
        # mass only at place 0, no move and no mixing (the evidence tests' setting)
        (
            [[0.3, 0.0, 0.0, 0.0], [0.7, 0.0, 0.0, 0.0]],
            [0, 0],
            (1.0, 0.0, 0.0),
            [0.0, 1.0, 1.0, 1.0],
            [1.0, 0.0, 0.0, 0.0],
        ),
        # mass moved to places 0 and 1 and mixed; the evidence is 0 at both
        (
            [[0.0, 0.5, 0.0, 0.0], [0.0, 0.0, 0.0, 0.5]],
            [-1, -2],
            (0.5, 0.25, 0.25),
            [0.0, 0.0, 0.5, 1.0],
            [0.5, 0.5, 0.0, 0.0],
        ),
    ],
)
def test_advance_restarts_from_the_prior_when_the_evidence_underflows(
    kernels, p, shifts, mixing, weight, moved
):
    # the evidence is 0 wherever the prior (floor 0) holds mass: the layer starts again from
    # prior[j] / n weighed by the evidence alone; predicted keeps the prior before that
    weight = np.array(weight, np.float32)
    args = (shifts, *mixing, [0.5, 0.5], [0.25, 0.75], 0.0, weight)
    out, predicted, marginal, row_mass, z = _run_advance(kernels, p, *args)
    np.testing.assert_allclose(out, np.array([[0.25], [0.75]]) / 4 * weight, rtol=1e-6)
    assert z == pytest.approx(weight.sum() / 4, rel=1e-6)
    np.testing.assert_allclose(marginal, weight / weight.sum(), rtol=1e-6)
    np.testing.assert_allclose(row_mass, [0.25, 0.75], rtol=1e-6)
    np.testing.assert_allclose(predicted, moved, rtol=1e-6)
    expected = ref_advance(np.array(p, np.float32), *args)
    for g, e in zip((out, predicted, marginal, row_mass, z), expected, strict=True):
        np.testing.assert_allclose(g, e, rtol=1e-6)


def test_advance_is_scale_free(kernels):
    rng = np.random.default_rng(5)
    p = rng.random((3, 7))
    weight = np.exp(rng.normal(size=7))
    args = ([0, 1, 2], 0.6, 0.3, 0.1, [0.2, 0.3, 0.5], [0.3, 0.3, 0.4], 0.02, weight)
    one = _run_advance(kernels, p, *args)
    many = _run_advance(kernels, p * 1000.0, *args)
    for a, b in zip(one, many, strict=True):
        np.testing.assert_allclose(a, b, rtol=2e-6)


# -- window_sums -----------------------------------------------------------------------------
@pytest.mark.parametrize("radius", [0, 1, 2, 5, 11, 14])
def test_window_sums_against_reference(kernels, radius):
    marginal = np.random.default_rng(2).random(11).astype(np.float32)
    out = np.full(11, np.nan)
    best = kernels["window_sums"](marginal, radius, out)
    expected, expected_best = ref_window_sums(marginal, radius)
    np.testing.assert_allclose(out, expected, rtol=1e-12)
    assert best == expected_best


@pytest.mark.parametrize(
    ("marginal", "radius", "expected", "best"),
    [
        ([1, 2, 3, 4], 0, [1, 2, 3, 4], 3),
        ([1, 2, 3, 4], 1, [3, 6, 9, 7], 2),  # clipped at both ends
        ([1, 2, 3, 4], 2, [6, 10, 10, 9], 1),  # a tie: the first of equals
        ([1, 2, 3, 4], 3, [10, 10, 10, 10], 0),
        ([1, 2, 3, 4], 9, [10, 10, 10, 10], 0),  # radius beyond the route
        ([1, 0, 1, 0], 0, [1, 0, 1, 0], 0),
        ([0, 1, 0, 1], 0, [0, 1, 0, 1], 1),
        ([1, 1, 1, 1, 1], 1, [2, 3, 3, 3, 2], 1),
        ([0, 0, 0], 1, [0, 0, 0], 0),  # nothing anywhere: place 0
        ([5], 0, [5], 0),
    ],
)
def test_window_sums_by_hand(kernels, marginal, radius, expected, best):
    out = np.full(len(marginal), np.nan)
    assert kernels["window_sums"](np.array(marginal, np.float32), radius, out) == best
    np.testing.assert_array_equal(out, expected)


def test_window_sums_have_no_cancellation(kernels):
    # Each window is its own sum: a huge neighbour does not swallow the small values after it
    # (a running sum would lose 0.3 and 0.1 beside 1e17 and end below 0).
    out = np.empty(4)
    marginal = np.array([0.1, 1e17, 0.3, 0.1], np.float32)
    best = kernels["window_sums"](marginal, 0, out)
    assert best == 1
    np.testing.assert_array_equal(out, marginal.astype(np.float64))
    kernels["window_sums"](marginal, 1, out)
    assert out[3] == float(marginal[2]) + float(marginal[3])


# -- exceedance ------------------------------------------------------------------------------
@pytest.mark.parametrize("stride", [1, 2, 3, 7])
def test_exceedance_against_reference(kernels, stride):
    x = np.round(np.random.default_rng(3).normal(size=23), 1).astype(np.float32)  # with ties
    for place in range(23):
        assert kernels["exceedance"](x, place, stride) == ref_exceedance(x, place, stride)


@pytest.mark.parametrize(
    ("place", "stride", "expected"),
    [
        (0, 1, 1 / 5),  # the best: only itself
        (2, 1, 3 / 5),  # ties count
        (3, 1, 3 / 5),
        (1, 1, 4 / 5),
        (4, 1, 5 / 5),  # the worst: every place
        (0, 2, 1 / 3),  # places 0, 2, 4 are sampled: 3, 2, 0
        (3, 2, 2 / 3),  # place 3 is not sampled; its level 2 is reached by 3 and 2
        (1, 2, 2 / 3),
        (4, 2, 3 / 3),
        (0, 3, 1 / 2),  # places 0, 3: 3, 2
        (2, 3, 2 / 2),
        (4, 5, 1 / 1),
    ],
)
def test_exceedance_by_hand(kernels, place, stride, expected):
    x = np.array([3.0, 1.0, 2.0, 2.0, 0.0], np.float32)
    assert kernels["exceedance"](x, place, stride) == expected


def test_exceedance_counts_at_least_one(kernels):
    # place 1 is not sampled and beats every sampled place: count 0 -> 1 of 2
    x = np.array([0.0, 5.0, 0.0, 0.0], np.float32)
    assert kernels["exceedance"](x, 1, 2) == 0.5
    assert kernels["exceedance"](x, 1, 1) == 0.25


# -- likeness and repeats ----------------------------------------------------------------------
def test_likeness_against_numpy(kernels):
    rng = np.random.default_rng(3)
    row, last = rng.normal(size=50).astype(np.float32), rng.normal(size=50)
    keep = last.copy()
    r = kernels["likeness"](row, last)
    assert r == pytest.approx(np.corrcoef(row.astype(np.float64), keep)[0, 1], abs=1e-7)
    assert np.array_equal(last, row.astype(np.float64))  # the row is kept for the next frame
    assert kernels["likeness"](np.ones(50, np.float32), last) == 0.0  # a constant row
    # a constant last row (and no division by its zero spread)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert kernels["likeness"](row, np.full(50, 2.0)) == 0.0


@pytest.mark.parametrize("offset, scale", [(1e8, 1.0), (0.0, 1e-3), (-3.0, 10.0)])
def test_likeness_of_large_close_or_small_scores(kernels, offset, scale):
    # scores of 1e8 +- 1 (no cancellation of the sums: each row less its first value), and
    # rows whose variances are far below 1 (still correlated, not "constant")
    rng = np.random.default_rng(8)
    base = rng.normal(size=60)
    row = offset + scale * (base + 0.5 * rng.normal(size=60))
    last = offset + scale * base
    expected = np.corrcoef(row - offset, last - offset)[0, 1]
    assert 0.5 < expected < 0.99
    assert kernels["likeness"](row, last.copy()) == pytest.approx(expected, abs=1e-9)


def ref_variation(row, lo, hi):
    diffs = np.abs(np.diff(np.asarray(row, np.float64)))
    whole = diffs.mean() if diffs.size else 0.0
    near = diffs[lo:hi].mean() if hi > lo else 0.0
    return whole, near


@pytest.mark.parametrize(
    ("row", "lo", "hi", "expected"),
    [
        ([0, 1, 3, 6], 1, 3, (2.0, 2.5)),  # |3 - 1| and |6 - 3| near; 1, 2, 3 over the row
        ([0, 1, 3, 6], 0, 1, (2.0, 1.0)),
        ([5, 1, 1, 4], 1, 2, (7 / 3, 0.0)),  # absolute differences; a flat pair
        ([2, 2], 0, 0, (0.0, 0.0)),  # no pair near
        ([2, 5], 0, 1, (3.0, 3.0)),  # a route of two places has one pair
        ([7], 0, 0, (0.0, 0.0)),  # no pair at all
    ],
)
def test_variation_by_hand(kernels, row, lo, hi, expected):
    whole, near = kernels["variation"](np.array(row, np.float32), lo, hi)
    assert (whole, near) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize(("lo", "hi"), [(0, 29), (3, 9), (10, 11), (28, 29), (5, 5)])
def test_variation_against_reference(kernels, lo, hi):
    row = np.random.default_rng(6).normal(size=30)
    whole, near = kernels["variation"](row, lo, hi)
    expected = ref_variation(row, lo, hi)
    assert whole == pytest.approx(expected[0], rel=1e-12)
    assert near == pytest.approx(expected[1], rel=1e-12)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_repeats_is_exact(kernels, dtype):
    last = np.linspace(0.0, 1.0, 30)
    row = last.astype(dtype)
    assert kernels["repeats"](row, row.astype(np.float64))
    for i in (0, 17, 29):
        other = row.copy()
        other[i] = np.nextafter(other[i], dtype(2.0))
        assert not kernels["repeats"](other, row.astype(np.float64))


# -- shifts: fractions accumulate --------------------------------------------------------------
def test_shifts_accumulate_fractions():
    vel = (0.0, 0.125, 0.5, 1.0, 2.25, 2.5, 3.0)
    f = CANN(velocities=vel, bidirectional=True, odometry="exact")
    f.step(np.zeros(12))  # allocates the state
    rows = f._params["velocities"]
    np.testing.assert_array_equal(rows, sorted({*vel, *(-v for v in vel)}))
    moved = np.zeros(rows.size, np.int64)
    odometry = 0
    for t in range(1, 33):
        k = f._shifts(None)
        assert k.dtype == np.int64 and k.shape == rows.shape
        moved += k
        # position after t frames: t * v rounded, halves up (binary fractions: exact)
        np.testing.assert_array_equal(moved, np.floor(t * rows + 0.5))
        # odometry accumulates on its own, and leaves the bank's offsets alone
        k = f._shifts(0.75)
        assert k.dtype == np.int64
        np.testing.assert_array_equal(k, np.full(rows.size, k[0]))
        odometry += int(k[0])
        assert odometry == math.floor(0.75 * t + 0.5)


def test_scaled_odometry_shifts_accumulate_with_the_rows_own():
    # Scaled odometry moves each row the odometry times its velocity, on the row's own
    # fractional position: frames with and without odometry add up.
    vel = (0.0, 0.125, 0.5, 1.0, 2.25, 2.5, 3.0)
    f = CANN(velocities=vel, bidirectional=True)
    f.step(np.zeros(12))
    rows = f._params["velocities"]
    moved = np.zeros(rows.size, np.int64)
    for t in range(1, 33):
        moved += f._shifts(None)
        moved += f._shifts(0.75)
        # t frames at each row's velocity and t at 0.75 times it (binary fractions: exact)
        np.testing.assert_array_equal(moved, np.floor(1.75 * t * rows + 0.5))


@pytest.mark.parametrize(
    ("velocity", "expected"),
    [
        (0.5, [1, 0, 1, 0, 1, 0]),
        (-0.5, [0, -1, 0, -1, 0, -1]),
        (0.25, [0, 1, 0, 0, 0, 1]),
        (1.5, [2, 1, 2, 1, 2, 1]),
        (0.0, [0, 0, 0, 0, 0, 0]),
        (-2.75, [-3, -2, -3, -3, -3, -2]),
    ],
)
def test_shifts_by_hand(velocity, expected):
    f = CANN(velocities=(velocity,))
    f.step(np.zeros(5))
    assert [int(f._shifts(None)[0]) for _ in expected] == expected
    f = CANN(velocities=(1.0,))
    f.step(np.zeros(5))
    assert [int(f._shifts(velocity)[0]) for _ in expected] == expected


# -- jitter ----------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("row", "share", "expected"),
    [
        ([0, 0, 4, 0, 0], 0.5, [0, 1, 2, 1, 0]),  # a quarter of it each way
        ([4, 0, 0, 0], 0.5, [2, 1, 0, 0]),  # what leaves at the route's start is lost
        ([0, 0, 0, 4], 0.5, [0, 0, 1, 2]),  # and at its end
        ([2, 4, 6], 0.0, [2, 4, 6]),  # no share: unchanged
        ([8], 0.5, [4]),  # one place: half of it leaves
        ([1, 3], 0.25, [1.125, 2.375]),  # two places: each is the other's neighbour
    ],
)
def test_jitter_by_hand(kernels, row, share, expected):
    p = np.array([row], np.float32)
    out = np.full_like(p, np.nan)
    kernels["jitter"](p, out, np.array([share]), _NO_BREAKS)
    np.testing.assert_allclose(out[0], expected, rtol=1e-6)
    np.testing.assert_array_equal(p, [row])  # only read


_NO_BREAKS = np.zeros(0, np.int64)


@pytest.mark.parametrize(
    ("row", "breaks", "expected"),
    [
        # a break before place 3: the halves that would cross it are lost, as at an end
        ([0, 0, 4, 0, 0, 0], [3], [0, 1, 2, 0, 0, 0]),
        ([0, 0, 0, 4, 0, 0], [3], [0, 0, 0, 2, 1, 0]),
        ([0, 0, 4, 4, 0, 0], [3], [0, 1, 2, 2, 1, 0]),
        # two breaks side by side: place 3 a stretch of its own, nothing comes in or out
        ([0, 0, 4, 4, 4, 0], [3, 4], [0, 1, 2, 2, 2, 1]),
        ([0, 4, 0, 0, 0, 4], [1, 5], [0, 2, 1, 0, 0, 2]),  # next to the ends
        ([4, 4, 4, 4, 4, 4], [2], [3, 3, 3, 4, 4, 3]),
    ],
)
def test_jitter_stops_at_a_break(kernels, row, breaks, expected):
    p = np.array([row], np.float32)
    out = np.full_like(p, np.nan)
    kernels["jitter"](p, out, np.array([0.5]), np.array(breaks, np.int64))
    np.testing.assert_allclose(out[0], expected, rtol=1e-6)


def test_jitter_with_every_set_of_breaks_on_short_routes(kernels):
    # every set of breaks on routes of 1-7 places (consecutive ones, at 1 and at n - 1): each
    # stretch jitters as a route of its own; the places away from the breaks as without them
    rng = np.random.default_rng(8)
    shares = np.array([0.0, 0.3, 1.0])
    for n in range(1, 8):
        for k in range(n):
            for cut in itertools.combinations(range(1, n), k):
                p = rng.random((3, n)).astype(np.float32)
                out = np.full_like(p, np.nan)
                kernels["jitter"](p, out, shares, np.array(cut, np.int64))
                edges = [0, *cut, n]
                for lo, hi in zip(edges[:-1], edges[1:], strict=True):
                    part = np.pad(p[:, lo:hi].astype(np.float64), ((0, 0), (1, 1)))
                    s = shares[:, None]
                    own = (1 - s) * p[:, lo:hi] + s / 2 * (part[:, :-2] + part[:, 2:])
                    np.testing.assert_allclose(out[:, lo:hi], own, rtol=1e-6, err_msg=str(cut))
                plain = np.empty_like(p)
                kernels["jitter"](p, plain, shares, _NO_BREAKS)
                far = [i for i in range(n) if i not in {x for c in cut for x in (c - 1, c)}]
                np.testing.assert_array_equal(out[:, far], plain[:, far])


def test_jitter_each_row_by_its_share(kernels):
    rng = np.random.default_rng(4)
    p = rng.random((3, 9)).astype(np.float32)
    shares = np.array([0.0, 0.1, 2.0 / 3.0])
    out = np.empty_like(p)
    kernels["jitter"](p, out, shares, _NO_BREAKS)
    padded = np.pad(p.astype(np.float64), ((0, 0), (1, 1)))
    s = shares[:, None]
    expected = (1 - s) * p + s / 2 * (padded[:, :-2] + padded[:, 2:])
    np.testing.assert_allclose(out, expected, rtol=1e-6)
    np.testing.assert_array_equal(out[0], p[0])
    # inside the route the mass is kept; at the ends, half a share of the end places leaves
    lost = shares / 2 * (p[:, 0] + p[:, -1])
    np.testing.assert_allclose(out.sum(axis=1), p.sum(axis=1) - lost, rtol=1e-6)
    # with breaks, each stretch as a route of its own: the same, stretch by stretch
    breaks = np.array([3, 4, 8], np.int64)
    kernels["jitter"](p, out, shares, breaks)
    for lo, hi in ((0, 3), (3, 4), (4, 8), (8, 9)):
        part = np.pad(p[:, lo:hi].astype(np.float64), ((0, 0), (1, 1)))
        own = (1 - s) * p[:, lo:hi] + s / 2 * (part[:, :-2] + part[:, 2:])
        np.testing.assert_allclose(out[:, lo:hi], own, rtol=1e-6)
    # the same bits as without breaks away from them
    plain = np.empty_like(p)
    kernels["jitter"](p, plain, shares, _NO_BREAKS)
    np.testing.assert_array_equal(out[:, :2], plain[:, :2])
    np.testing.assert_array_equal(out[:, 5:7], plain[:, 5:7])


# -- leave_at_breaks -------------------------------------------------------------------------
def ref_leave_at_breaks(p, shifts, breaks):
    """float64 loops from the docstring: unit i of a row moving k crosses when a break lies in
    (i, i + k] or (i + k, i]; what crossed goes equally to the row's units that land (0 <=
    i + k < n) without crossing; the crossing units end empty."""
    out = np.asarray(p, np.float64).copy()
    n = out.shape[1]
    for j, k in enumerate(shifts):
        crosses = [any(i < b <= i + k or i + k < b <= i for b in breaks) for i in range(n)]
        gone = sum(out[j, i] for i in range(n) if crosses[i])
        land = [i for i in range(n) if 0 <= i + k < n and not crosses[i]]
        for i in range(n):
            if crosses[i]:
                out[j, i] = 0.0
        for i in land:
            out[j, i] += gone / len(land)
    return out


@pytest.mark.parametrize("seed", range(6))
def test_leave_at_breaks_against_reference(kernels, seed):
    # random rows, moves of -4 .. 4 places (some longer than the route), breaks anywhere on
    # it, close together or not
    rng = np.random.default_rng(seed)
    n = int(rng.integers(3, 16))
    shifts = rng.integers(-4, 5, size=6).astype(np.int64)
    if seed == 5:
        shifts[0] = n + 2  # (every unit leaves: nothing lands)
        shifts[1] = -n - 3
    breaks = np.unique(rng.integers(1, n, size=int(rng.integers(1, 4)))).astype(np.int64)
    p = rng.uniform(0.1, 1.0, (6, n)).astype(np.float32)
    expected = ref_leave_at_breaks(p, shifts, breaks)
    got = p.copy()
    kernels["leave_at_breaks"](got, shifts, breaks)
    np.testing.assert_allclose(got, expected, rtol=2e-6, atol=1e-7)
    # (a row keeps its whole mass, but where every unit crosses or leaves the route)
    for j, k in enumerate(shifts):
        crosses = [any(i < b <= i + k or i + k < b <= i for b in breaks) for i in range(n)]
        if any(0 <= i + k < n and not crosses[i] for i in range(n)):
            assert got[j].sum(dtype=np.float64) == pytest.approx(p[j].sum(dtype=np.float64))
        else:
            assert got[j][crosses].sum() == 0.0


def test_leave_at_breaks_where_every_unit_that_lands_crosses(kernels):
    # 3 places, breaks before 1 and 2, one ahead: 0 and 1 cross, 2 leaves the route; nothing
    # lands, so what crossed is not shared (the move would lose it anyway)
    p = np.array([[0.25, 0.5, 0.75]], np.float32)
    with warnings.catch_warnings():  # (and nothing is divided by the none that land)
        warnings.simplefilter("error")
        kernels["leave_at_breaks"](p, np.array([1], np.int64), np.array([1, 2], np.int64))
    np.testing.assert_array_equal(p, [[0.0, 0.0, 0.75]])


def test_leave_at_breaks_by_hand(kernels):
    # 8 places, breaks before 3 and 4: a row 2 ahead loses 1, 2 and 3 (place 2 would cross
    # both breaks: counted once); a row 1 back loses 3 and 4; the standing row keeps all.
    p = np.array([[1, 2, 3, 4, 5, 6, 7, 8], [1] * 8, [1, 2, 3, 4, 5, 6, 7, 8]], np.float32)
    kernels["leave_at_breaks"](p, np.array([2, 0, -1], np.int64), np.array([3, 4], np.int64))
    # row 0: 2 + 3 + 4 = 9 over the units that land and stay, 0 and 4-5 (6, 7 leave the route)
    np.testing.assert_allclose(p[0], [1 + 3, 0, 0, 0, 5 + 3, 6 + 3, 7, 8])
    np.testing.assert_array_equal(p[1], np.ones(8, np.float32))
    # row 2: 4 + 5 = 9 over 1, 2, 5, 6, 7 (0 leaves the route)
    np.testing.assert_allclose(p[2], [1, 2 + 1.8, 3 + 1.8, 0, 0, 6 + 1.8, 7 + 1.8, 8 + 1.8])
