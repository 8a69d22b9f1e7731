"""What a test of the regressor logs about its uncertainty: the belief's calibration (tempered and
untempered), every OOD score's rank correlation with the error and AUROC at flagging the noisiest
samples, and the reliability diagram in TensorBoard."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch

from rotlearn.bingham import CREDIBLE_LEVELS
from rotlearn.cli.train import build
from rotlearn.lit.regressor import noisiest
from rotlearn.ood.scores import SCORES, Score, register_score
from tests.conftest import FAST, tensorboard_events

COVERAGE = [f"test/coverage_{a:g}" for a in CREDIBLE_LEVELS]
BELIEF_KEYS = ["test/nll", "test/ece", *COVERAGE]


def with_difficulty(model) -> None:
    """Test batches carry a per-sample "difficulty" (the heteroscedastic data of issue 17 will):
    here the sample's index in the test set, enough for the keys to appear."""
    test_step = model.test_step

    def step(batch, batch_idx):
        index = torch.arange(len(batch["R"]), dtype=torch.float64) + 1000 * batch_idx
        return test_step({**batch, "difficulty": index}, batch_idx)

    model.test_step = step


def read(run: Path) -> dict:
    return json.loads((run / "metrics.json").read_text())


def test_a_head_reports_its_calibration_and_the_untempered_one_when_tempered(make_cfg):
    cfg = make_cfg(["rep=a", *FAST, "trainer.max_epochs=1", "model.belief_samples=64"])
    run = Path(cfg.paths.output_dir)
    model, datamodule, trainer = build(cfg)
    trainer.fit(model, datamodule=datamodule)
    trainer.test(model, datamodule=datamodule, verbose=False)
    plain = read(run)
    for key in BELIEF_KEYS:
        assert math.isfinite(plain[key]), key
    assert all(0.0 <= plain[k] <= 1.0 for k in COVERAGE)
    assert [plain[k] for k in COVERAGE] == sorted(plain[k] for k in COVERAGE)
    assert 0.0 <= plain["test/ece"] <= 0.9
    for score in ("dt", "eigengap", "raw_norm"):
        assert -1.0 <= plain[f"test/{score}_spearman"] <= 1.0
    assert not any("uncalibrated" in k or "auroc_noisiest" in k for k in plain)
    assert "test/temperature" not in plain
    (acc,) = [e for name, e in tensorboard_events(run).items() if name.endswith("/test")]
    assert "test/reliability" in acc.Tags()["images"]

    model.belief_temperature = 2.0
    with_difficulty(model)
    trainer.test(model, datamodule=datamodule, verbose=False)
    tempered = read(run)
    assert tempered["test/temperature"] == 2.0
    # the untempered belief is the one tested before, scored with the same draws
    for key in BELIEF_KEYS:
        assert tempered[key.replace("test/", "test/uncalibrated_")] == pytest.approx(plain[key])
    assert tempered["test/nll"] != pytest.approx(plain["test/nll"])
    assert tempered["test/err_mean"] == pytest.approx(plain["test/err_mean"])  # same rotations
    for score in ("dt", "eigengap", "raw_norm"):  # rank statistics: tempering changes no rank
        assert tempered[f"test/{score}_spearman"] == pytest.approx(plain[f"test/{score}_spearman"])
        assert 0.0 <= tempered[f"test/{score}_auroc_noisiest"] <= 1.0


def test_a_head_without_belief_ranks_its_errors_by_the_raw_norm_only(make_cfg):
    cfg = make_cfg(["rep=sixd", *FAST, "trainer.fast_dev_run=true"])
    model, datamodule, trainer = build(cfg)
    with_difficulty(model)
    trainer.fit(model, datamodule=datamodule)
    trainer.test(model, datamodule=datamodule, verbose=False)
    metrics = read(Path(cfg.paths.output_dir))
    assert -1.0 <= metrics["test/raw_norm_spearman"] <= 1.0
    assert 0.0 <= metrics["test/raw_norm_auroc_noisiest"] <= 1.0
    assert not any(k.startswith(("test/dt", "test/eigengap", "test/nll", "test/ece",
                                 "test/coverage")) for k in metrics)  # fmt: skip


def test_a_score_registered_before_the_model_is_ranked_too(make_cfg):
    def spread(prediction):
        return prediction.eigenvalues[..., 3] - prediction.eigenvalues[..., 0]

    register_score(Score("spread", keep_below=False, fn=spread, needs_eigenvalues=True))
    try:
        model, datamodule, trainer = build(make_cfg(["rep=a", *FAST, "trainer.fast_dev_run=true",
                                                     "model.belief_samples=8"]))  # fmt: skip
    finally:
        del SCORES["spread"]
    with_difficulty(model)
    trainer.test(model, datamodule=datamodule, verbose=False)
    assert {"test/spread_spearman", "test/spread_auroc_noisiest"} <= set(trainer.callback_metrics)


def test_the_noisiest_decile_is_the_top_tenth_of_difficulty_ties_included():
    difficulty = torch.arange(20, dtype=torch.float64)
    assert noisiest(difficulty).nonzero().flatten().tolist() == [18, 19]
    assert noisiest(torch.tensor([0.0, 1.0, 1.0, 1.0])).tolist() == [False, True, True, True]
