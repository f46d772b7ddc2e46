"""scripts/ship_model.py without a run folder: re-shipping the default with changed guide
settings keeps the weights and the card's training part, and records the change."""

from __future__ import annotations

import json
import sys
from dataclasses import replace

import pytest
import torch

from ppmrecon.model import checkpoint as C
from ppmrecon.model.features import FeatureConfig
from ppmrecon.model.guard import DEFAULT_ON
from ppmrecon.model.guide import DEFAULT_GUIDE
from ppmrecon.model.kpn import build
from tests.conftest import load_script

CARD = """# Model card: `default.pt`

The model `ppmrecon-denoise` uses when `--model` is not given. Written by `scripts/ship_model.py runs/x` from the run's files.

| | |
|---|---|
| firefly guard | the guard it was trained with |
| denoiser guide | trained with it |
| shipped reconstruction | the old row |
| data set | `data/x`: 2 scenes |

| epoch | train loss (Eq. 8) | validation relMSE | best single input |
| 1 | 0.1 | 0.2 | 0.3 |

Held-out figures from `old.json`:

| old table |

Limits: trained on SPPM inputs only.
"""


@pytest.fixture
def ship_model(tmp_path, monkeypatch):
    module = load_script("scripts", "ship_model")
    monkeypatch.setattr(module, "DEFAULT_MODEL", tmp_path / "default.pt")
    model = build("tiny", FeatureConfig(scale_free=True), DEFAULT_ON, replace(DEFAULT_GUIDE, mode="envelope"))
    C.save_checkpoint(tmp_path / "default.pt", model, {"trained": True})
    (tmp_path / "default.md").write_text(CARD)
    return module


def _run(module, monkeypatch, *argv: str) -> None:
    monkeypatch.setattr(sys, "argv", ["ship_model.py", *argv])
    module.main()


def test_reship_changes_the_guide_keeps_the_weights_and_rewrites_the_card(ship_model, tmp_path, monkeypatch):
    before = C.load_checkpoint(tmp_path / "default.pt")
    bench = tmp_path / "guide.json"
    row = {"variant": "shipped", "images": 3, "geomean": 0.4, "worst": 0.9, "worse_than_best": 0,
           "at_most_half": 1, "geomean_8x8": 0.95, "block_not_worse": 2}
    bench.write_text(json.dumps({"models": {"shipped": "x"}, "summary_scenes": [row], "summary_validation": []}))
    _run(ship_model, monkeypatch, "--guide-y-weight", "2", "--bench", str(bench))
    after = C.load_checkpoint(tmp_path / "default.pt")
    assert after.model.guide == replace(before.model.guide, y_weight=2.0)
    for k, v in before.model.state_dict().items():
        assert torch.equal(v, after.model.state_dict()[k])
    assert after.meta["reshipped"] == [{"from": before.model.guide.to_dict(), "to": after.model.guide.to_dict()}]
    card = (tmp_path / "default.md").read_text()
    assert "Re-shipped by `scripts/ship_model.py --guide-y-weight 2 --bench" in card
    assert "the old row" not in card and card.count("| shipped reconstruction |") == 1
    assert "~y's times 2" in card
    assert "| 1 | 0.1 | 0.2 | 0.3 |" in card and "| denoiser guide | trained with it |" in card   # training part kept
    assert "old table" not in card and "| study scenes (3) | shipped | 0.400 |" in card
    assert card.rstrip().endswith("Limits: trained on SPPM inputs only.")
    # the same settings again: nothing to record, one "Re-shipped" sentence
    _run(ship_model, monkeypatch, "--guide-y-weight", "2")
    again = C.load_checkpoint(tmp_path / "default.pt")
    assert len(again.meta["reshipped"]) == 1
    assert (tmp_path / "default.md").read_text().count("Re-shipped by") == 1


def test_reship_with_two_bench_results_names_each_data_set(ship_model, tmp_path, monkeypatch):
    """--bench twice (the training data and a hold-out set): one table each, in that order,
    the data rows named by the folders the result records; y_empty goes into the shipped row."""
    row = {"variant": "shipped", "images": 5, "geomean": 0.5, "worst": 1.2, "worse_than_best": 1,
           "at_most_half": 2, "geomean_8x8": 0.9, "block_not_worse": 3}
    benches = []
    for name, images in (("train", 5), ("hold", 7)):
        path = tmp_path / f"{name}.json"
        path.write_text(json.dumps({"models": {"shipped": "x"}, "summary_scenes": [], "split": "all",
                                    "data": [f"data/{name}"], "summary_validation": [{**row, "images": images}]}))
        benches += ["--bench", str(path)]
    _run(ship_model, monkeypatch, "--guide-y-weight", "2", "--guide-y-empty", "3", *benches)
    card = (tmp_path / "default.md").read_text()
    assert C.load_checkpoint(tmp_path / "default.pt").model.guide.y_empty == 3.0
    assert card.index("| `data/train` all splits (5) | shipped | 0.500 |") \
        < card.index("| `data/hold` all splits (7) | shipped | 0.500 |")
    assert card.count("Held-out figures from") == 2 and f"--bench {tmp_path / 'hold.json'}" in card
    assert "where ~y did not read 0 while ~z^" in card
    # reshipped again with one result: the two tables are replaced by one
    _run(ship_model, monkeypatch, "--guide-y-empty", "3", "--bench", str(tmp_path / "hold.json"))
    card = (tmp_path / "default.md").read_text()
    assert card.count("Held-out figures from") == 1 and "data/train" not in card


def test_reship_refuses_a_bench_file_that_is_no_result_before_writing(ship_model, tmp_path, monkeypatch):
    before = (tmp_path / "default.md").read_text()
    (tmp_path / "other.json").write_text(json.dumps({"rows": []}))
    for path, why in ((tmp_path / "missing.json", "not a readable"), (tmp_path / "other.json", "no summary rows")):
        with pytest.raises(SystemExit, match=f"--bench {path}: .*{why}"):
            _run(ship_model, monkeypatch, "--guide-y-empty", "3", "--bench", str(path))
    assert (tmp_path / "default.md").read_text() == before


def test_reship_needs_a_setting_and_a_valid_one(ship_model, monkeypatch):
    with pytest.raises(SystemExit, match="guide setting to change"):
        _run(ship_model, monkeypatch)
    with pytest.raises(SystemExit, match="--guide-y-weight"):
        _run(ship_model, monkeypatch, "--guide-y-weight", "-1")


def test_reship_turns_the_cross_rule_off_and_labels_the_bench_split(ship_model, tmp_path, monkeypatch):
    before = C.load_checkpoint(tmp_path / "default.pt")
    bench = tmp_path / "guide.json"
    row = {"variant": "shipped", "images": 5, "geomean": 0.5, "worst": 1.2, "worse_than_best": 1,
           "at_most_half": 2, "geomean_8x8": 0.9, "block_not_worse": 3}
    bench.write_text(json.dumps({"models": {"shipped": "x"}, "summary_scenes": [], "summary_validation": [row],
                                 "split": "all"}))
    assert before.model.guide.cross == 2.0
    _run(ship_model, monkeypatch, "--guide-cross", "0", "--bench", str(bench))
    after = C.load_checkpoint(tmp_path / "default.pt")
    assert after.model.guide == replace(before.model.guide, cross=0.0)
    card = (tmp_path / "default.md").read_text()
    assert "Re-shipped by `scripts/ship_model.py --guide-cross 0 --bench" in card
    assert "| data set, all splits (5) | shipped | 0.500 | 1.20 | 1 |" in card
    with pytest.raises(SystemExit, match="--guide-cross"):
        _run(ship_model, monkeypatch, "--guide-cross", "1")
    _run(ship_model, monkeypatch, "--guide-y-spike", "16")
    spiked = C.load_checkpoint(tmp_path / "default.pt")
    assert spiked.model.guide == replace(after.model.guide, y_spike=16.0)
    assert "where ~y is a lone spike, 16x above them" in (tmp_path / "default.md").read_text()
    with pytest.raises(SystemExit, match="--guide-y-spike"):
        _run(ship_model, monkeypatch, "--guide-y-spike", "0.5")
    _run(ship_model, monkeypatch, "--guard-confirm", "4")
    confirmed = C.load_checkpoint(tmp_path / "default.pt")
    assert confirmed.model.guard == replace(spiked.model.guard, confirm=4.0)
    assert confirmed.model.guide == spiked.model.guide
    assert {"guard_from", "guard_to"} <= set(confirmed.meta["reshipped"][-1])
    assert "'confirm': 4.0" in (tmp_path / "default.md").read_text()
    # a second guard change: the card still names the guard the network was trained with
    _run(ship_model, monkeypatch, "--guard-edge", "1")
    edged = C.load_checkpoint(tmp_path / "default.pt")
    assert edged.model.guard == replace(confirmed.model.guard, edge=1.0)
    row = next(line for line in (tmp_path / "default.md").read_text().splitlines() if line.startswith("| firefly guard"))
    assert f"trained with {DEFAULT_ON.to_dict()}" in row and "'edge': 1.0" in row
    _run(ship_model, monkeypatch, "--guard-edge", "0")
    _run(ship_model, monkeypatch, "--guard-events", "4")
    assert C.load_checkpoint(tmp_path / "default.pt").model.guard == replace(confirmed.model.guard, events=4.0)
    with pytest.raises(SystemExit, match="--guard-events"):
        _run(ship_model, monkeypatch, "--guard-events", "2")
    _run(ship_model, monkeypatch, "--guard-events", "0")
    with pytest.raises(SystemExit, match="--guard-confirm"):
        _run(ship_model, monkeypatch, "--guard-confirm", "1")
    with pytest.raises(SystemExit, match="--guard-confirm changes a shipped default"):
        _run(ship_model, monkeypatch, str(tmp_path / "run"), "--guard-confirm", "4")
    _run(ship_model, monkeypatch, "--guide-anchor-settled", "0.9")
    settled = C.load_checkpoint(tmp_path / "default.pt")
    assert settled.model.guide == replace(confirmed.model.guide, anchor_settled=0.9)
    card = (tmp_path / "default.md").read_text()
    assert "where its low-pass is settled (standard deviation < 0.9 x its level)" in card
    assert "--guide-anchor-settled 0.9" in (tmp_path / "default.md").read_text()
    with pytest.raises(SystemExit, match="--guide-anchor-settled"):
        _run(ship_model, monkeypatch, "--guide-anchor-settled", "-1")


def test_reship_attaches_a_chooser_trained_on_this_default(ship_model, tmp_path, monkeypatch):
    from ppmrecon.model.chooser import Chooser, ChooserConfig

    base = C.load_checkpoint(tmp_path / "default.pt")
    trained = base.model
    trained.chooser = Chooser(ChooserConfig(width=4, layers=2))
    trained.guide = replace(trained.guide, mode="chooser")
    val = {"images": 4, "chooser": {"ratio": 0.5, "worst": 0.9, "worse": 0, "ratio_8x8": 0.9, "blocks_ok": 3},
           "envelope": {"ratio": 0.55, "worst": 0.95, "worse": 1, "ratio_8x8": 0.95, "blocks_ok": 2}}
    C.save_checkpoint(tmp_path / "chooser.pt", trained,
                      {"chooser": {"data": "data/x", "config": {"steps": 8, "batch": 2, "crop": 16},
                                   "train_images": 12, "seconds": 60.0, "validation": val}})
    _run(ship_model, monkeypatch, "--chooser", str(tmp_path / "chooser.pt"))
    after = C.load_checkpoint(tmp_path / "default.pt")
    assert after.model.guide == replace(base.model.guide, mode="chooser") and after.model.chooser is not None
    assert after.meta["chooser"]["train_images"] == 12
    card = (tmp_path / "default.md").read_text()
    assert card.count("| chooser |") == 1 and "0.500 of the best input (envelope 0.550)" in card
    assert "guide mode `chooser`" in card and f"--chooser {tmp_path / 'chooser.pt'}" in card
    # a chooser trained on another guide is refused
    other = C.load_checkpoint(tmp_path / "chooser.pt").model
    other.guide = replace(other.guide, y_weight=7.0)
    C.save_checkpoint(tmp_path / "other.pt", other)
    with pytest.raises(SystemExit, match="another guard or guide"):
        _run(ship_model, monkeypatch, "--chooser", str(tmp_path / "other.pt"))


def test_reship_aims_the_anchor_at_another_estimate(ship_model, tmp_path, monkeypatch):
    before = C.load_checkpoint(tmp_path / "default.pt")
    _run(ship_model, monkeypatch, "--guide-anchor-source", "4", "--guide-y-weight", "1")
    after = C.load_checkpoint(tmp_path / "default.pt")
    assert after.model.guide == replace(before.model.guide, anchor_source=4, y_weight=1.0)
    assert type(after.model.guide.anchor_source) is int           # an index of the ~z^j, not 4.0
    card = (tmp_path / "default.md").read_text()
    assert "anchored at low frequencies to ~z^4 where they differ by more than its noise" in card
    assert "--guide-anchor-source 4 --guide-y-weight 1" in card or "--guide-y-weight 1 --guide-anchor-source 4" in card
    _run(ship_model, monkeypatch, "--guide-anchor-source", "3", "--guide-anchor-select", "4")
    card = (tmp_path / "default.md").read_text()
    assert "to ~z^4 where its low-pass agrees with ~z^3's within 4 x the latter's noise, else to ~z^3" in card
    _run(ship_model, monkeypatch, "--guide-terms-passes", "16")
    assert C.load_checkpoint(tmp_path / "default.pt").model.guide.terms_passes == 16.0
    card = (tmp_path / "default.md").read_text()
    assert "widened towards the range of Eq. 6's terms over its 3 x 3 window by the share 1 / (1 + N / 16)" in card
    with pytest.raises(SystemExit, match="--guide-terms-passes"):
        _run(ship_model, monkeypatch, "--guide-terms-passes", "-1")
    _run(ship_model, monkeypatch, "--guide-anchor-spikes", "8")
    assert C.load_checkpoint(tmp_path / "default.pt").model.guide.anchor_spikes == 8.0
    assert "(8x above its 3 x 3 median) left out of its low-pass" in (tmp_path / "default.md").read_text()
    with pytest.raises(SystemExit, match="--guide-anchor-source"):
        _run(ship_model, monkeypatch, "--guide-anchor-source", "5")
    with pytest.raises(SystemExit):                               # not an index: argparse refuses it
        _run(ship_model, monkeypatch, "--guide-anchor-source", "2.5")


def test_reship_with_the_anchor_cascade(ship_model, tmp_path, monkeypatch):
    """--guide-cascade K: the checkpoint's guide says it, the card's shipped row describes it;
    a value the config refuses is one line naming the option."""
    _run(ship_model, monkeypatch, "--guide-cascade", "4")
    assert C.load_checkpoint(tmp_path / "default.pt").model.guide.cascade == 4.0
    card = (tmp_path / "default.md").read_text()
    assert "and on down to ~z^2..~z^1 where that aim's low-pass departs from the narrower estimate's by more " \
           "than 4 x the latter's noise" in card
    assert "OIDN given it in place of ~z^4" in card
    with pytest.raises(SystemExit, match="--guide-cascade"):
        _run(ship_model, monkeypatch, "--guide-cascade", "-1")
