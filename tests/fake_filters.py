"""Online filters with scripted answers, so that tests of the localizer and the CLI do not
depend on the CANN's numbers."""

from __future__ import annotations

from flyvpr.localization import LOCALIZED
from flyvpr.temporal.base import OnlineFilter


class Scripted(OnlineFilter):
    """Passes the row through, reports the next of ``states`` (cycling) as ``state_`` and
    records the ``velocity`` of every step in ``velocities``."""

    name = "scripted"

    def __init__(self, states=(LOCALIZED,)):
        self.states = states

    def reset(self):
        self.t = 0
        self.velocities = []

    def step(self, scores_row, velocity=None):
        self.velocities.append(velocity)
        return super().step(scores_row)

    def _step(self, row):
        self.state_ = self.states[self.t % len(self.states)]
        self.confidence_ = float(row.max())
        self.t += 1
        return row


class Stateless(OnlineFilter):
    """An online filter without a state and without odometry (its step takes no velocity);
    it doubles the row."""

    name = "stateless"

    def reset(self):
        self.n_steps = 0

    def _step(self, row):
        self.n_steps += 1
        return row * 2.0
