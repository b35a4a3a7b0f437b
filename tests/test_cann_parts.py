"""The CANN's parts against slow, obviously correct references: kernels, readout, speed bank.

Written to kill mutants (see CONTRIBUTING, mutation testing): each test pins a number that a
small change of the code would move.  The kernels run both ways (plain numpy and, where numba
is importable, compiled).
"""

import numpy as np
import pytest

from flyvpr.temporal.cann import _kernels, _readout
from flyvpr.temporal.cann._kernels import excitation_kernel
from flyvpr.temporal.cann._speed import SpeedBank, tie_winner


@pytest.fixture
def kernels(cann_kernel_mode):
    """The attractor's kernels, compiled and not (see conftest's cann_kernel_mode)."""
    found, compiled = _kernels.get_kernels()
    assert compiled == (cann_kernel_mode == "compiled")
    return found


# -- excitation kernel ----------------------------------------------------------------------
@pytest.mark.parametrize(("width", "radius"), [(0.2, 1), (0.34, 2), (1.0, 3), (1.5, 5), (2.0, 6)])
def test_kernel_taps_and_normalisation(width, radius):
    k = excitation_kernel(15.0, width).astype(np.float64)
    assert k.shape == (2 * radius + 1,)
    d = np.arange(-radius, radius + 1)
    expected = 15.0 * np.exp(-(d**2) / (2 * width**2)) / (np.sqrt(2 * np.pi) * width)
    np.testing.assert_allclose(k, expected, rtol=1e-6)
    if width >= 1.0:  # the discrete Gaussian out to 3 widths sums to the strength
        assert k.sum() == pytest.approx(15.0, rel=3e-3)
    assert np.argmax(k) == radius and k[0] == k[-1]


# -- shift, traces ---------------------------------------------------------------------------
@pytest.mark.parametrize("k", [0, 1, 3, -2, 7, -7, 9, -9, -12])
def test_shift(kernels, k):
    a = np.arange(7, dtype=np.float32)
    expected = np.full(7, -1.0, np.float32)
    for i in range(7):
        if 0 <= i - k < 7:
            expected[i] = i - k
    kernels["shift"](a, k, np.float32(-1.0))
    np.testing.assert_array_equal(a, expected)


def test_update_traces_against_a_loop(kernels):
    rng = np.random.default_rng(0)
    n = 9
    old = rng.normal(size=(2, 5, n)).astype(np.float32)
    new = np.full_like(old, np.nan)
    shifts = np.array([0, 2, -3, 9, -12], np.int64)
    keeps = np.array([0.9, 0.5], np.float32)
    coefs = np.array([0.1, 0.25], np.float32)
    x = rng.normal(size=n).astype(np.float32)
    kernels["update_traces"](old, new, shifts, keeps, coefs, x)
    for c in range(2):
        for j, k in enumerate(shifts):
            for i in range(n):
                moved = old[c, j, i - k] * keeps[c] if 0 <= i - k < n else 0.0
                assert new[c, j, i] == pytest.approx(moved + x[i] * coefs[c], abs=1e-6)


@pytest.mark.parametrize("n_cur", [1, 2])
@pytest.mark.parametrize("stride", [1, 2, 3])
def test_evidence_stats_against_numpy(kernels, n_cur, stride):
    rng = np.random.default_rng(10 * n_cur + stride)
    traces = rng.normal(size=(n_cur, 3, 11)).astype(np.float32)
    evidence = traces[0] if n_cur == 1 else np.full((3, 11), np.nan, np.float32)
    centre, spread = np.empty(3), np.empty(3)
    kernels["evidence_stats"](traces, evidence, stride, centre, spread)
    total = traces.sum(axis=0)
    np.testing.assert_allclose(evidence, total, rtol=1e-6)
    sample = total[:, ::stride].astype(np.float64)
    np.testing.assert_allclose(centre, sample.mean(axis=1), rtol=1e-6)
    np.testing.assert_allclose(spread, sample.std(axis=1), rtol=1e-6)


# -- input normalisation ---------------------------------------------------------------------
def _normalise(kernels, row, mean, var, **kw):
    args = {"take_log": False, "rate": 0.5, "var_rate": 0.25, "adapt": True, "adapt_var": True}
    args.update(kw)
    x = np.asarray(row, np.float32).copy()
    kernels["normalise"](
        x,
        mean,
        var,
        args["take_log"],
        np.float32(1e-30),
        args["rate"],
        args["var_rate"],
        args["adapt"],
        args["adapt_var"],
        args.get("prior_var", False),
        0.1,
        args.get("clip", np.inf),
        args.get("gain", 1.0),
        args.get("mix", 0.0),
        args.get("read", np.empty(0)),
    )
    return x


def test_normalise_against_a_reference(kernels):
    row = np.array([1.0, 2.0, 4.0, 7.0, 1.0])
    mean = np.array([0.0, 0.5, -0.5, 1.0, 0.0], np.float32)
    var = np.ones(5, np.float32)
    z = (row - row.mean()) / row.std()
    m = 0.5 * np.array([0.0, 0.5, -0.5, 1.0, 0.0]) + 0.5 * z
    v = z - m
    q = 0.75 * 1.0 + 0.25 * v * v
    # clip 0.45: the values are -0.463, -0.493, 0.493, 0.401, -0.463, clipped on both sides
    expected = 3.0 * np.clip(v / np.sqrt(q + 0.1), -0.45, 0.45)
    assert (expected == -1.35).sum() == 3 and (expected == 1.35).sum() == 1
    out = _normalise(kernels, row, mean, var, clip=0.45, gain=3.0)
    np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(mean, m, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(var, q, rtol=1e-5)
    # Divided by the spread of the frames before this one: a peak does not damp itself.
    before = np.array([1.0, 2.0, 0.5, 1.0, 4.0], np.float32)
    mean2, var2 = np.array([0.0, 0.5, -0.5, 1.0, 0.0], np.float32), before.copy()
    out = _normalise(kernels, row, mean2, var2, prior_var=True)
    np.testing.assert_allclose(out, v / np.sqrt(before + 0.1), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(mean2, m, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(var2, 0.75 * before + 0.25 * v * v, rtol=1e-5)
    # Without variance adaptation, and without adaptation at all.
    plain = _normalise(kernels, row, np.zeros(5, np.float32), var.copy(), adapt_var=False)
    np.testing.assert_allclose(plain, z - 0.5 * z, rtol=1e-5, atol=1e-6)
    none = _normalise(kernels, row, np.zeros(5, np.float32), var.copy(), adapt=False)
    np.testing.assert_allclose(none, z, rtol=1e-5, atol=1e-6)


def test_normalise_log_and_constant_rows(kernels):
    p = np.array([0.1, 0.2, 0.3, 0.4])
    out = _normalise(kernels, p, np.zeros(4, np.float32), np.ones(4, np.float32), adapt=False)
    lg = np.log(p)
    assert not np.allclose(out, (lg - lg.mean()) / lg.std(), atol=1e-3)  # linear: the row
    out = _normalise(
        kernels, p, np.zeros(4, np.float32), np.ones(4, np.float32), adapt=False, take_log=True
    )
    np.testing.assert_allclose(out, (lg - lg.mean()) / lg.std(), rtol=1e-5)
    # A constant row, and one that differs by float32 rounding (spread < 1e-6), give nothing.
    for row in (np.full(6, 3.0), 5.0 + 1e-7 * np.arange(6)):
        mean = np.zeros(6, np.float32)
        out = _normalise(kernels, row, mean, np.ones(6, np.float32))
        assert np.all(out == 0.0) and np.all(mean == 0.0)


def test_normalise_blends_a_read_row(kernels):
    # ``read``: mix times the adapted, clipped, gained input plus 1 - mix times the plain
    # z-score; the adaptation and the input as without it; a constant row reads as zeros
    row = np.array([1.0, 2.0, 4.0, 7.0, 1.0])
    z = (row - row.mean()) / row.std()
    mean, var = np.array([0.0, 0.5, -0.5, 1.0, 0.0], np.float32), np.ones(5, np.float32)
    alone = _normalise(kernels, row, mean.copy(), var.copy(), clip=0.45, gain=3.0)
    read = np.full(5, np.nan)
    out = _normalise(kernels, row, mean, var, clip=0.45, gain=3.0, mix=0.25, read=read)
    np.testing.assert_array_equal(out, alone)
    np.testing.assert_allclose(read, 0.25 * out + 0.75 * z, rtol=1e-5, atol=1e-6)
    read[:] = np.nan
    _normalise(kernels, np.full(5, 2.0), mean, var, mix=0.25, read=read)
    assert np.all(read == 0.0)
    # an empty read leaves everything else as it was
    again = _normalise(kernels, row, mean.copy(), var.copy(), mix=0.25, read=np.empty(0))
    np.testing.assert_array_equal(again, _normalise(kernels, row, mean.copy(), var.copy()))


# -- integration -----------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("n", "firing", "steps"),
    [
        (40, [5, 6, 7, 20, 38], 2),  # one unit near the end
        # Candidates a block or more apart (blocks of 512 places): one just before a block's
        # end, whose excitation lifts a unit of the next block above threshold in step 1 (so
        # it fires in step 2), one at the route's end; a quiet block between.
        (1400, [3, 510, 511, 1100, 1399], 3),
        # A route of 4 blocks and one place (the last block holds only the route's end, which
        # fires), and a unit that input alone lifts above threshold in step 1 in a block
        # where nothing else is above it (1536-2047): it fires in step 2.
        (2049, [3, 510, 511, 1100, 2048], 3),
    ],
)
def test_integrate_against_a_loop(kernels, n, firing, steps):
    rng = np.random.default_rng(1)
    theta, tonic = 1.0, 1.0
    u = rng.uniform(-3.0, 0.5, n).astype(np.float32)
    u[firing] = np.linspace(1.2, 3.0, len(firing))
    s = rng.normal(size=n).astype(np.float32)
    if n > 512:
        # Just below threshold, and kept below it by the inhibition unless the excitation
        # from 510-511 lifts it.
        u[512], s[512] = 0.9, 12.0
    if n > 2048:
        u[1700], s[1700] = 0.9, 15.0
    hk = excitation_kernel(15.0, 1.0) / np.float32(3.0)
    h, hw = 1 / 3, 3.2 / 3
    ref = u.astype(np.float64)
    for step in range(steps):
        r = np.clip(ref - theta, 0.0, 1.0) * (ref > theta)
        g = max(r.sum(), tonic)
        exc = np.array([sum(hk[d + 3] * r[i + d] for d in range(-3, 4) if 0 <= i + d < n)
                        for i in range(n)])  # fmt: skip
        ref = ref * (1 - h) + s * h - hw * g + exc
        if n > 512 and step == 0:
            assert ref[512] - exc[512] < theta < ref[512]  # it fires in step 2
        if n > 2048 and step == 0:
            assert exc[1700] == 0 and ref[1700] > theta
            assert (ref[1536:2048] > theta).sum() == 1
    out = u.copy()
    g_out = kernels["integrate"](
        out, s, np.float32(h), np.float32(1 - h), np.float32(theta), tonic, hw, hk, steps
    )
    np.testing.assert_allclose(out, ref, rtol=1e-5, atol=1e-5)
    assert g_out == pytest.approx(g, rel=1e-6)
    # Nothing fires: the tonic inhibition alone.
    quiet = np.zeros(n, np.float32)
    assert kernels["integrate"](quiet, s, h, 1 - h, theta, tonic, hw, hk, 1) == tonic
    np.testing.assert_allclose(quiet, s * h - hw * tonic, rtol=1e-6, atol=1e-6)


# -- readout ---------------------------------------------------------------------------------
def test_evidence_contrast_of_a_known_packet():
    u = np.full(50, -3.0, np.float32)
    u[20:23] = [1.2, 2.0, 1.5]
    s = np.zeros(50, np.float32)
    s[::5] = 1.0
    s[18] = 6.0  # within the radius (3) of the peak (21): the packet's own evidence
    s[25] = 9.0  # outside it
    peak, c = _readout.evidence_contrast(u, s, 1.0, 3, 1, 1e-6)
    assert peak == 21
    assert c == pytest.approx((6.0 - s.mean(dtype=np.float64)) / s.std(dtype=np.float64))
    # Every second place sampled: that sample's mean and spread.
    sample = s[::2].astype(np.float64)
    _, c2 = _readout.evidence_contrast(u, s, 1.0, 3, 2, 1e-6)
    assert c2 == pytest.approx((6.0 - sample.mean()) / sample.std())
    assert _readout.evidence_contrast(u, s, 1.0, 2, 1, 1e-6)[1] < c  # 18 is 3 away
    assert _readout.evidence_contrast(u, s, 2.0, 3, 1, 1e-6) == (21, 0.0)  # not above theta
    assert _readout.evidence_contrast(u, s, 1.0, 3, 1, 10.0)[1] == 0.0  # spread is "noise"
    low = s.copy()
    low[18:25] = -5.0
    assert _readout.evidence_contrast(u, low, 1.0, 3, 1, 1e-6)[1] == 0.0  # clipped at 0


@pytest.mark.parametrize(
    ("contrast", "support", "level", "t", "tier"),
    [
        (0.0, 9.0, 2.5, 500, "none"),
        (3.0, 2.5, 2.5, 500, "packet"),
        (3.0, 2.4, None, 500, "packet"),
        (3.0, 2.4, 2.5, 99, "tentative"),
        (3.0, 2.4, 2.5, 100, "front"),
    ],
)
def test_choose_tier(contrast, support, level, t, tier):
    assert _readout.choose_tier(contrast, support, level, t, 200.0) == tier


def test_readout_rows():
    u = np.array([-3.0, 1.5, 2.5, 1.0, -3.0], np.float32)
    s = np.array([0.5, 1.0, 3.0, 2.99995, -1.0], np.float32)
    row = np.array([0.0, -2.0, 1.0, 3.0, -0.5])
    out = _readout.readout(u, s, row, 2, 4.0, "packet", 1e-4)
    np.testing.assert_allclose(out, u - 2.5 + 6.0)
    assert out[2] == np.float32(6.0)
    out = _readout.readout(u, s, row, 2, 4.0, "tentative", 1e-4)
    assert out.max() == np.float32(0.8) and out.argmax() == 2
    out = _readout.readout(u, s, row, 2, 4.0, "front", 1e-4)
    np.testing.assert_allclose(out, 1.5 + 0.5 * row / (1 + np.abs(row)), rtol=1e-6)
    assert out.argmax() == 3 and 1.0 < out.min() and out.max() < 2.0
    out = _readout.readout(u, s, row, 2, 4.0, "none", 1e-4)
    # 3.0 and 2.99995 tie at 0 (within the noise): the lowest index, 2, answers.
    np.testing.assert_allclose(out, [-2.5, -2.0, 0.0, 0.0, -4.0])
    assert out.argmax() == 2


# -- speed bank ------------------------------------------------------------------------------
def _bank(velocities, n=300, memory=100.0, contrast=4.0):
    return SpeedBank(
        np.asarray(velocities, np.float64),
        1,
        n,
        np.array([0.96], np.float32),
        np.array([0.04], np.float32),
        memory,
        contrast,
        1,
        1e-6,
    )


def test_fractional_shifts_accumulate():
    bank = _bank([0.5, 1.25, -0.75])
    assert bank.shifts(first=True).tolist() == [0, 0, 0]
    moves = np.array([bank.shifts(first=False) for _ in range(4)])
    # halves round up: 0.5 -> 1, 0, 1, 0; 1.25 -> 1, 2, 1, 1; -0.75 -> -1, 0, -1, -1
    assert moves.T.tolist() == [[1, 0, 1, 0], [1, 2, 1, 1], [-1, 0, -1, -1]]


@pytest.mark.parametrize("speed", [0.875, 1.25, 1.75])
def test_bank_estimates_the_speed_of_a_synthetic_drift(kernels, speed):
    bank = _bank([0.75, 0.875, 1.0, 1.125, 1.25, 1.5, 1.75, 2.0], n=400)
    rng = np.random.default_rng(2)
    assert bank.estimate == 1.0  # before any vote: the candidate nearest 1
    for t in range(150):
        x = rng.normal(size=400).astype(np.float32)
        x[int(round(10 + speed * t))] += 6.0
        bank.update(x * np.float32(10.0), t == 0, kernels["update_traces"])
    assert bank.estimate == speed
    j = list(bank.velocities).index(speed)
    assert bank.contrast[j] == bank.contrast.max() >= 4.0
    assert abs(int(bank.peaks[j]) - round(10 + speed * 149)) <= 1
    # The votes: each voting frame adds 1 - exp(-1 / memory), all decay by exp(-1 / memory).
    assert bank.votes.sum() <= 1.0 + 1e-6 and bank.votes[j] > 0.5 * bank.votes.sum()


def test_bank_votes_decay_and_ties_prefer_one(kernels):
    bank = _bank([0.5, 1.0, 1.5], memory=10.0)
    assert bank.decay == pytest.approx(1 - np.exp(-0.1))
    # Constant input: every row ties, nothing stands out, the spread is zero: no vote.
    for t in range(5):
        bank.update(np.zeros(300, np.float32), t == 0, kernels["update_traces"])
    assert bank.index == 1 and bank.votes[0] == bank.votes[2] == 0.0
    assert bank.votes[1] == pytest.approx(1e-6 * np.exp(-0.5))


@pytest.mark.parametrize(
    ("values", "winner"),
    [
        ([0.5, 0.5 + 0.7e-5, 0.2], 0),  # within 1e-5 (the floor of the tolerance): a tie
        ([0.5, 0.5 + 1.5e-5, 0.2], 1),  # beyond it
        ([100.0, 100.0 + 0.9e-3, 3.0], 0),  # relative to the highest: 1e-5 x 100
        ([100.0, 100.0 + 1.1e-3, 3.0], 1),
        ([0.5, 0.505, -1000.0], 0),  # relative to the largest magnitude: 1e-5 x 1000
        ([0.5, 0.515, -1000.0], 1),
        ([1.0 - 1e-5 * 1.0, 1.0, 0.0], 0),  # exactly at the edge: still a tie
    ],
)
def test_tie_winner_tolerance(values, winner):
    # candidate 0 is preferred (nearest 1 place per frame), then 1, then 2
    assert tie_winner(values, [0, 1, 2]) == winner
    assert tie_winner(values, [2, 1, 0]) == 1  # 2 is never within reach of the highest


def test_get_kernels_chooses_by_flag(monkeypatch):
    monkeypatch.setattr(_kernels, "USE_NUMBA", False)
    assert _kernels.get_kernels(10) == (_kernels._PLAIN, False)
    monkeypatch.setattr(_kernels, "USE_NUMBA", True)
    monkeypatch.setattr(_kernels, "_compiled", {})
    found, compiled = _kernels.get_kernels(35_768)  # compiled at every route length
    assert compiled and set(found) == set(_kernels._PLAIN) and found is not _kernels._PLAIN
    assert all(hasattr(f, "py_func") for f in found.values())  # numba's dispatchers
    assert _kernels.get_kernels(1)[0] is found  # compiled once, then reused
    layer, compiled = _kernels.get_kernels(table="layer")
    assert compiled and layer is not found
    assert layer["normalise"].py_func is found["normalise"].py_func is _kernels.normalise


@pytest.mark.parametrize("firing", [[1, 2], [20, 21, 22], [37, 39]])
def test_integrate_at_the_route_ends(kernels, firing):
    # Firing units next to the start, in the middle, next to the end: the excitation is
    # spread over exactly the units within the kernel's radius that exist.
    n, theta = 40, 1.0
    u = np.full(n, -2.0, np.float32)
    u[firing] = 1.4
    s = np.zeros(n, np.float32)
    hk = excitation_kernel(15.0, 1.0)
    out = u.copy()
    kernels["integrate"](out, s, np.float32(1.0), np.float32(0.0), theta, 0.0, 0.0, hk, 1)
    expected = np.zeros(n)
    for i in firing:
        for d in range(-3, 4):
            if 0 <= i + d < n:
                expected[i + d] += hk[d + 3] * 0.4
    np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-6)


def test_relocation_boundaries_and_clipped_packets(kernels):
    relocate = kernels["relocate"]

    def case(p, q, own=1.0, sq=6.0, values=(1.1, 1.2, 1.5, 2.0, 1.5, 1.2, 1.1)):
        u = np.full(120, -3.2, np.float32)
        lo = p - 3
        for i, v in enumerate(values):
            if 0 <= lo + i < 120:
                u[lo + i] = v
        s = np.zeros(120, np.float32)
        s[min(p + 3, 119)] = own  # the packet's own evidence, at the edge of its window
        s[q] = sq
        return relocate(u, s, p, q, 3, 5.5, 0.5, np.float32(-3.2)), u

    moved, u = case(50, 100)
    assert moved
    np.testing.assert_array_equal(u[97:104], np.float32([1.1, 1.2, 1.5, 2.0, 1.5, 1.2, 1.1]))
    assert np.all(u[47:54] == np.float32(-3.2))
    # The own evidence sits at p + 3, inside the window: it must count.
    assert not case(50, 100, own=5.8)[0]
    # At the floor or exactly the margin ahead: no move.
    assert not case(50, 100, sq=5.5)[0]
    assert not case(50, 100, own=5.5, sq=6.0)[0]
    # A packet clipped at the route's start (peak at 1) moves whole, rest where it was cut.
    moved, u = case(1, 60)
    assert moved
    np.testing.assert_array_equal(u[57:64], np.float32([-3.2, -3.2, 1.5, 2.0, 1.5, 1.2, 1.1]))
    assert np.all(u[:5] == np.float32(-3.2))
    # Moved next to the start: clipped there.
    moved, u = case(60, 1)
    assert moved
    np.testing.assert_array_equal(u[:5], np.float32([1.5, 2.0, 1.5, 1.2, 1.1]))


def test_evidence_contrast_window_edges():
    u = np.full(30, -3.0, np.float32)
    s = np.linspace(0.0, 1.0, 30).astype(np.float32)
    u[1] = 2.0  # a packet at the route's start: its window is 0..4
    s[0] = 8.0
    _, c = _readout.evidence_contrast(u, s, 1.0, 3, 1, 1e-6)
    assert c == pytest.approx((8.0 - s.mean(dtype=np.float64)) / s.std(dtype=np.float64))
    u[1], u[10] = -3.0, 2.0  # peak at 10, window 7..13; the most evidence at 13
    s[0], s[13] = 0.0, 7.0
    _, c = _readout.evidence_contrast(u, s, 1.0, 3, 1, 1e-6)
    assert c == pytest.approx((7.0 - s.mean(dtype=np.float64)) / s.std(dtype=np.float64))


def _reference_bank(velocities, traces, x_rows, keeps, coefs, memory, min_contrast):
    """The speed bank, slowly: integer shifts, traces, contrasts, votes."""
    n_v, n = len(velocities), x_rows.shape[1]
    offsets = np.zeros(n_v)
    votes = np.zeros(n_v)
    pref = sorted(range(n_v), key=lambda j: (abs(velocities[j] - 1.0), j))
    votes[pref[0]] = 1e-6
    decay = 1 - np.exp(-1 / memory)
    history = []
    for t, x in enumerate(x_rows):
        for j, v in enumerate(velocities):
            k = 0
            if t:
                k = int(np.floor(offsets[j] + v + 0.5))
                offsets[j] += v - k
            for c in range(traces.shape[0]):
                old = traces[c, j].copy()
                for i in range(n):
                    moved = old[i - k] if 0 <= i - k < n else 0.0
                    traces[c, j, i] = moved * keeps[c] + x[i] * coefs[c]
        evidence = traces.sum(axis=0)
        contrast = (evidence.max(axis=1) - evidence.mean(axis=1)) / evidence.std(axis=1)
        votes *= 1 - decay
        best = max(range(n_v), key=lambda j: (contrast[j], -pref.index(j)))
        if contrast[best] >= min_contrast:
            votes[best] += decay
        history.append((contrast.copy(), votes.copy(), int(np.argmax(votes))))
    return history


def test_two_current_bank_against_a_reference(kernels):
    velocities = np.array([0.5, 1.0, 1.5])
    rng = np.random.default_rng(3)
    n, frames = 60, 40
    x_rows = rng.normal(size=(frames, n)).astype(np.float32)
    x_rows[
        np.arange(frames), np.minimum(5 + np.round(1.5 * np.arange(frames)), n - 1).astype(int)
    ] += 5
    keeps = np.array([0.9, 0.99], np.float32)
    coefs = np.array([0.05, 0.01], np.float32)
    bank = SpeedBank(velocities, 2, n, keeps, coefs, 10.0, 3.0, 1, 1e-9)
    ref = _reference_bank(velocities, np.zeros((2, 3, n)), x_rows, keeps, coefs, 10.0, 3.0)
    for t, x in enumerate(x_rows):
        bank.update(x, t == 0, kernels["update_traces"])
        contrast, votes, index = ref[t]
        np.testing.assert_allclose(bank.contrast, contrast, rtol=1e-4)
        np.testing.assert_allclose(bank.votes, votes, rtol=1e-6, atol=1e-12)
        assert bank.index == index
    assert bank.estimate == 1.5 and bank.votes[2] > 0.5


@pytest.mark.parametrize(
    ("noise", "min_contrast", "votes"),
    [
        (1.0, 1.0, False),  # spread exactly at the noise level: rounding residue, no vote
        (0.5, 1.0, True),  # contrast exactly at velocity_contrast: a vote
        (0.5, 1.5, False),  # a spread above the noise but too little contrast: no vote
    ],
)
def test_bank_vote_thresholds(kernels, noise, min_contrast, votes):
    # keeps 0, coefs 1: every row's evidence is the frame itself, +-1 alternating, whose
    # mean is 0 and spread 1 exactly (float64 sums of small integers), so the contrast is 1
    n = 8
    bank = SpeedBank(
        np.array([1.0, 2.0]),
        1,
        n,
        np.array([0.0], np.float32),
        np.array([1.0], np.float32),
        10.0,
        min_contrast,
        1,
        noise,
    )
    x = np.tile(np.float32([1.0, -1.0]), n // 2)
    bank.update(x, True, kernels["update_traces"])
    assert bank.contrast.tolist() == [1.0, 1.0]
    keep = 1e-6 * np.exp(-0.1)  # the initial 1e-6 of the row nearest 1, decayed once
    expected = keep + (bank.decay if votes else 0.0)
    assert bank.votes.tolist() == pytest.approx([expected, 0.0], rel=1e-12, abs=0)


def test_evidence_contrast_at_the_noise_level():
    # +-1 alternating evidence: mean 0 and spread 1 exactly; the packet's window holds a 1
    u = np.full(20, -3.0, np.float32)
    u[9] = 2.0
    s = np.tile(np.float32([1.0, -1.0]), 10)
    assert _readout.evidence_contrast(u, s, 1.0, 2, 1, 1.0) == (9, 0.0)  # a spread of noise
    assert _readout.evidence_contrast(u, s, 1.0, 2, 1, 0.5) == (9, 1.0)  # just above it


def test_readout_without_an_answer_ties_only_within_the_noise():
    # exactly the noise below the most evidence is not a tie (the ties are closer than it)
    u = np.zeros(4, np.float32)
    s = np.float32([0.0, 3.0, 2.5, 2.75])
    out = _readout.readout(u, s, np.zeros(4), 0, 0.0, "none", 0.5)
    np.testing.assert_array_equal(out, [-3.0, 0.0, -0.5, 0.0])
