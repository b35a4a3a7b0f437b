"""The CANN's readout: the packet's answer and its confidence, the front end's, or none.

See "Output" in the user guide's page on the paper's CANN (``docs/guide/cann-paper.md``).
Tiers of the confidence (the row's maximum): 0 no answer; below 1 a tentative answer of the
packet; 1 to 2 the front end's answer while the sequence is lost; ``2 + c`` the packet's
answer, ``c`` its evidence contrast.
"""

from __future__ import annotations

import numpy as np

from ._kernels import evidence_stats as plain_evidence_stats

#: confidence of an established packet's answer: this + its evidence contrast
ESTABLISHED = 2.0


def evidence_contrast(
    u, s, theta, radius: int, stride: int, noise: float, evidence_stats=None
) -> tuple[int, float]:
    """The packet's peak and its evidence contrast (0 without a packet or evidence spread).

    The contrast is ``(max(s over peak - radius .. peak + radius) - mean(s)) / std(s)``,
    clipped at 0, with the mean and spread over every ``stride``-th place (computed by the
    kernel ``evidence_stats``, by default the plain one); a spread at or below ``noise``
    (rounding residue) gives 0.
    """
    peak = int(np.argmax(u))
    if not u[peak] > theta:
        return peak, 0.0
    moments = np.empty((2, 1))
    (evidence_stats or plain_evidence_stats)(s[None, None], s[None], stride, *moments)
    centre, spread = float(moments[0, 0]), float(moments[1, 0])
    if not spread > noise:
        return peak, 0.0
    own = max(s[max(peak - radius, 0) : peak + radius + 1].tolist())
    return peak, max((own - centre) / spread, 0.0)


def front_end_row(row, out) -> None:
    """The front end's scores mapped monotonically into (1, 2): ``1.5 + 0.5 r / (1 + |r|)``.

    The argmax stays, and rows rank among themselves as the front end's maxima rank them.
    """
    r = row.astype(np.float64)
    scale = np.abs(r)
    scale += 1.0
    r *= 0.5
    r /= scale
    np.add(r, 1.5, out=out)


def readout(u, s, row, peak: int, contrast: float, tier: str, noise: float) -> np.ndarray:
    """The output row of one frame for ``tier`` in {"none", "tentative", "front", "packet"}."""
    out = np.empty_like(u)
    if tier == "none":
        # No answer.  Every place scores at most 0, ranked by its evidence; places within
        # rounding of the most evidence tie at 0 (the lowest index wins), so neither rounding
        # residue nor the zeros that enter at the route's end pick a place.
        np.subtract(s, s.max(), out=out)
        out[out > -noise] = 0.0
    elif tier == "front":
        front_end_row(row, out)
    else:
        # The packet's peak is the answer; the other places keep the potentials' order.
        np.subtract(u, u[peak], out=out)
        level = ESTABLISHED + contrast if tier == "packet" else contrast / (1.0 + contrast)
        out += np.float32(level)  # the peak: exactly the level
    return out


def choose_tier(contrast: float, support: float, level: float | None, t: int, memory: float):
    """Where frame ``t``'s answer comes from (see :func:`readout`).

    ``support`` is the packet's contrast averaged over recent frames, ``level`` the
    ``fallback_contrast`` (``None``: never fall back), ``memory`` the ``fallback_memory``.
    """
    if contrast == 0.0:
        return "none"
    if level is None or support >= level:
        return "packet"
    if t < 0.5 * memory:
        return "tentative"
    return "front"
