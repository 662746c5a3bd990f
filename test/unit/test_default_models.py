"""The rule that picks each mode's default (`benchmarks/analyses/default_models.py`), on
constructed rows and on the committed evaluations: it picks what `provider.DEFAULT_MODELS`
ships."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from helpers.benchmarks import load_analysis

from art_guidance.art.provider import DEFAULT_MODELS, shipped_defaults

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "benchmarks" / "results"


@pytest.fixture(scope="module")
def rule():
    return load_analysis("default_models")


def _row(model: str, saving: float, worse: int = 0, ms: float = 200.0) -> dict:
    return {"model": model, "mode": "chance", "sha256": model * 8, "eval": "out/e",
            "flown_saving_mean_mmps": saving, "flown_worse_by_1mm": worse,
            "proposal_ms_median": ms}


def _pair(a: str, b: str, mean: float, sem: float) -> dict:
    return {"eval": "out/e", "mode": "chance", "sha256_a": a * 8, "sha256_b": b * 8,
            "saving_a_minus_b_mmps": mean, "sem_mmps": sem}


def test_the_cheapest_proposal_within_the_paired_interval_of_the_best(rule):
    rows = [_row("best", 15.0, ms=240.0), _row("near", 14.4, ms=120.0),
            _row("far", 13.0, ms=100.0), _row("worse", 30.0, worse=1, ms=50.0),
            _row("unpaired", 14.9, ms=90.0)]
    pairs = [_pair("near", "best", -0.6, 0.67),  # recorded the other way round: flipped
             _pair("best", "far", 2.0, 0.5)]      # 2.0 > 1.96 x 0.5: outside
    decided = rule.decide(rows, pairs)["chance"]
    assert decided["best"] == "best" and decided["within"] == ["best", "near"]
    assert decided["choice"] == "near"  # "worse" saves more, but is not never worse
    assert decided["paired"]["near"]["mean_mmps"] == pytest.approx(0.6)
    assert not decided["paired"]["far"]["within"]
    assert decided["paired"]["unpaired"] == {"within": False,
                                             "why": "no paired figure against the best"}
    # without paired figures the rule keeps the most saving model
    assert rule.choose(rows) == {"chance": "best"}
    # a paired figure of another evaluation does not count
    assert rule.choose(rows, [dict(p, eval="out/other") for p in pairs]) == {"chance": "best"}
    # candidates of one mode from two evaluations are refused (the interval is paired)
    with pytest.raises(ValueError, match="one evaluation per mode"):
        rule.decide([_row("best", 15.0), dict(_row("near", 14.4), eval="out/f")])


def test_the_committed_evaluations_choose_the_shipped_defaults(rule, tmp_path, capsys):
    """The rule on the committed summaries (deterministic: the student with its teacher on
    1,000 fresh scenarios, paired figures in the summary; chance-constrained: the student with
    its teacher on 2,000 held-out scenarios and the recorded paired figures) picks the shipped
    defaults, and writes the committed choice."""
    out = tmp_path / "choice.json"
    argv = ["--eval", f"deterministic={RESULTS / 'slim' / 'eval_slim1e40_det_1000_summary.json'}",
            "--eval", f"chance={RESULTS / 'slim' / 'eval_slim1e40_s11s12_summary.json'}",
            "--paired", str(RESULTS / "default_models" / "paired.json"), "--json", str(out)]
    assert rule.main(argv) == 0
    assert "default, chance: art_slim1e40_chance_rtn.pt" in capsys.readouterr().out
    got = json.loads(out.read_text())
    assert got["choice"] == DEFAULT_MODELS
    assert {m: shipped_defaults()[m]["model"] for m in DEFAULT_MODELS} == DEFAULT_MODELS
    committed = json.loads((RESULTS / "default_models" / "choice.json").read_text())
    assert committed["choice"] == got["choice"] and committed["rule"] == got["rule"]
    assert committed["rows"] == got["rows"]
