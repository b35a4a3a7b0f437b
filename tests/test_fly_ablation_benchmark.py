"""The fly front end's ablation benchmark: every stage fits, scores and filters a route."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks import fly_ablation  # noqa: E402


@pytest.mark.parametrize("stage", list(fly_ablation.STAGES))
@pytest.mark.parametrize("surround", [False, True])
def test_every_stage_runs_on_a_route(stage, surround, sliding_world):
    # (a stage set up without the map's pixel mask broke once the mask came, unseen: the
    # cosine stage read the encoder's mask before it had one)
    ref, qry = (x.copy() for x in sliding_world)
    if surround:  # a static border, as a fisheye's: masked out of the lobe's stages
        for x in (ref, qry):
            x[:, :4] = 0.05
    factory, _seeded = fly_ablation.STAGES[stage]
    gt = np.abs(np.arange(40)[:, None] - np.arange(40)[None, :]) <= 1
    result = fly_ablation.run_stage(factory(0), ref, qry, gt)
    assert set(result) == {"auc", "recall_at_1"}
    assert 0.5 < result["auc"] <= 1.0  # the route is easy: every stage finds most places
