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
    assert set(result) == {"auc", "recall_at_1", "front_auc", "front_recall_at_1"}
    assert 0.5 < result["auc"] <= 1.0  # the route is easy: every stage finds most places
    assert 0.0 < result["front_auc"] <= 1.0


def test_a_stage_is_scored_with_the_filter_and_alone(sliding_world):
    from flyvpr.metrics import pr_auc, recall_at_k
    from flyvpr.temporal import FILTERS

    ref, qry = sliding_world
    # noise enough that the front end alone misses places the filter finds
    noise = np.random.default_rng(1).normal(0, 0.3, qry.shape)
    qry = np.clip(qry + noise, 0, 1).astype(np.float32)
    gt = np.abs(np.arange(40)[:, None] - np.arange(40)[None, :]) <= 1
    result = fly_ablation.run_stage(fly_ablation.STAGES["kenyon"][0](3), ref, qry, gt)
    front = fly_ablation.STAGES["kenyon"][0](3).fit(ref)
    alone = front.score(qry)
    filtered = FILTERS["cann"]().filter(alone)
    assert result["front_auc"] == pr_auc(alone, gt)
    assert result["front_recall_at_1"] == recall_at_k(alone, gt, 1)
    assert result["auc"] == pr_auc(filtered, gt)
    assert result["recall_at_1"] == recall_at_k(filtered, gt, 1)
    assert result["auc"] > result["front_auc"] + 0.3
    assert result["recall_at_1"] > result["front_recall_at_1"]


def _document(with_alone: bool) -> dict:
    def row(mean, seeded):
        out = {"seeds": [0, 1] if seeded else None, "auc_mean": mean, "auc_min": mean - 0.01,
               "auc_max": mean + 0.01}  # fmt: skip
        if with_alone:
            out.update(front_auc_mean=mean / 4, front_auc_min=mean / 5, front_auc_max=mean / 3)
        return out

    stages = {"pixels": row(0.9, False), "kenyon": row(0.8, True), "kenyon-pool2": row(0.6, True)}
    return {"results": {"nordland 0-999": {"stages": stages}}}


def test_table_gives_the_stages_with_the_filter_then_alone():
    table = fly_ablation.render_table(_document(True)).splitlines()
    assert table[0] == "| stage (+cann) | Nordland 0-999 |"
    assert "| `pixels` (bar) | 0.900 |" in table
    assert "| + centring (`kenyon`, shipped) | 0.800 [0.790, 0.810] |" in table
    assert "| `kenyon`, 2x2 pooling (2048 features) | 0.600 [0.590, 0.610] |" in table
    assert "| optic lobe, cosine | - |" in table  # a stage the document lacks
    alone = table.index("| stage alone (no filter) | Nordland 0-999 |")
    assert table.index("| `pixels` (bar) | 0.900 |") < alone
    assert table[alone + 2] == "| `pixels` (bar) | 0.225 |"
    assert "| + centring (`kenyon`, shipped) | 0.200 [0.160, 0.267] |" in table[alone:]
    # a document from before the stages were scored alone: the first table only
    older = fly_ablation.render_table(_document(False))
    assert "alone" not in older and "| `pixels` (bar) | 0.900 |" in older


def test_every_stage_has_a_row_in_both_tables():
    assert set(fly_ablation.LABELS) == set(fly_ablation.STAGES)
    table = fly_ablation.render_table(_document(True)).splitlines()
    alone = table.index("| stage alone (no filter) | Nordland 0-999 |")
    first, second = table[2 : alone - 1], table[alone + 2 :]
    assert len(first) == len(second) == len(fly_ablation.LABELS)
    assert "| `kenyon`, 2x2 pooling (2048 features) | 0.150 [0.120, 0.200] |" in second
    assert "| optic lobe, cosine | - |" in second
    # a document where one stage was not scored alone: the first table only
    partial = _document(True)
    stages = partial["results"]["nordland 0-999"]["stages"]
    del stages["kenyon"]["front_auc_mean"]
    assert "alone" not in fly_ablation.render_table(partial)


def test_the_committed_document_summarises_its_own_runs():
    import json

    data = json.loads((ROOT / "benchmarks" / "fly-ablation.json").read_text())
    assert data["seeds"] == list(fly_ablation.SEEDS)
    assert set(data["results"]) == set(fly_ablation.DATASETS)
    for key, result in data["results"].items():
        assert set(result["stages"]) == set(fly_ablation.STAGES), key
        for stage, row in result["stages"].items():
            seeded = fly_ablation.STAGES[stage][1]
            assert row["seeds"] == (list(fly_ablation.SEEDS) if seeded else None)
            for prefix in ("", "front_"):
                aucs = [r[f"{prefix}auc"] for r in row["runs"].values()]
                assert len(aucs) == (len(fly_ablation.SEEDS) if seeded else 1)
                assert row[f"{prefix}auc_mean"] == pytest.approx(np.mean(aucs))
                assert row[f"{prefix}auc_min"] == min(aucs)
                assert row[f"{prefix}auc_max"] == max(aucs)
