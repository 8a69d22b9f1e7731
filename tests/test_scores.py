"""Uncertainty scores (`rotlearn.scores`): directions, the quantile threshold and the rank
statistics (AUROC, Spearman through torchmetrics), checked by hand and against a reference."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from rotlearn.heads import EnsembleHead, make_head
from rotlearn.scores import (
    SCORES,
    auroc,
    available_scores,
    keep_mask,
    quantile_threshold,
    spearman,
)

# -- thresholds --------------------------------------------------------------------------------


def test_threshold_direction_and_quantile_semantics():
    train = torch.arange(1.0, 101.0)  # 1 .. 100
    dt = SCORES["dt"]  # keep below
    gap = SCORES["eigengap"]  # keep above
    assert quantile_threshold(train, 0.75, dt.keep_below) == pytest.approx(75.25)
    assert quantile_threshold(train, 0.75, gap.keep_below) == pytest.approx(25.75)
    test = torch.tensor([10.0, 50.0, 80.0, 100.0])
    assert keep_mask(test, 75.25, True).tolist() == [True, True, False, False]
    assert keep_mask(test, 25.75, False).tolist() == [False, True, True, True]
    # q = 1 keeps below the training maximum; q = 0 keeps nothing of the training set
    assert quantile_threshold(train, 1.0, True) == 100.0
    assert not keep_mask(train, quantile_threshold(train, 0.0, True), True).any()


@settings(max_examples=40, deadline=None)
@given(q=st.floats(0.05, 0.95), seed=st.integers(0, 1000), below=st.booleans())
def test_a_quantile_keeps_that_fraction_of_the_training_scores(q, seed, below):
    train = torch.randn(2001, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    kept = keep_mask(train, quantile_threshold(train, q, below), below).double().mean()
    assert abs(float(kept) - q) <= 1.0 / 2001 + 1e-12


def test_nan_scores_are_never_kept_and_ignored_by_the_threshold():
    train = torch.tensor([1.0, 2.0, math.nan, 3.0])
    assert quantile_threshold(train, 1.0, True) == 3.0
    assert not keep_mask(torch.tensor([math.nan]), 10.0, True).any()
    assert not keep_mask(torch.tensor([math.nan]), -10.0, False).any()
    with pytest.raises(ValueError, match="outside"):
        quantile_threshold(train, 1.5, True)


def test_auroc_and_spearman_by_hand():
    clean_low = torch.tensor([0.1, 0.2, 0.3, 0.9, 0.8, 0.7])
    corrupted = torch.tensor([False, False, False, True, True, True])
    assert auroc(clean_low, corrupted, keep_below=True) == 1.0
    assert auroc(clean_low, corrupted, keep_below=False) == 0.0
    ties = torch.tensor([0.5, 0.5, 0.5, 0.5])
    assert auroc(ties, torch.tensor([False, True, False, True]), True) == 0.5
    # one swapped pair out of 3 x 3
    swapped = torch.tensor([0.1, 0.2, 0.75, 0.9, 0.8, 0.7])
    assert auroc(swapped, corrupted, True) == pytest.approx(8 / 9)
    x = torch.tensor([1.0, 2.0, 3.0, 4.0])
    assert spearman(x, x**3) == pytest.approx(1.0)
    assert spearman(x, -x) == pytest.approx(-1.0)
    assert math.isnan(auroc(x, torch.zeros(4, dtype=torch.bool), True))


def test_scores_follow_the_head():
    names = ["dt", "eigengap", "raw_norm", "autoencoder"]
    assert [s.name for s in available_scores(names, True, False)] == ["dt", "eigengap", "raw_norm"]
    assert [s.name for s in available_scores(names, False, True)] == ["raw_norm", "autoencoder"]
    raw = torch.randn(5, 10, dtype=torch.float64)
    prediction = make_head("a")(raw)
    dt = SCORES["dt"].fn(prediction)
    ev = torch.linalg.eigvalsh(prediction.A)
    torch.testing.assert_close(dt, 3 * ev[:, 0] - ev[:, 1:].sum(-1))
    assert (dt <= 0).all()
    torch.testing.assert_close(SCORES["raw_norm"].fn(prediction), raw.norm(dim=-1))


@settings(max_examples=30, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    levels=st.integers(2, 6),
    scale=st.sampled_from([1.0, 1e-3, 1e5]),
    offset=st.sampled_from([0.0, -3e5, 50.0]),
)
def test_auroc_is_the_mann_whitney_probability_with_ties_half(seed, levels, scale, offset):
    """Against the definition, pair by pair: P(positive > negative) + P(equal) / 2, whatever
    the scores' scale and offset (DT values of a trained belief are about -1e5: no squashing)."""
    g = torch.Generator().manual_seed(seed)
    s = torch.randint(0, levels, (60,), generator=g).double() * scale + offset
    p = torch.rand(60, generator=g) < 0.4
    if not bool(p.any()) or bool(p.all()):
        return
    pos, neg = s[p][:, None], s[~p][None, :]
    expected = float(((pos > neg).double() + 0.5 * (pos == neg).double()).mean())
    assert auroc(s, p, keep_below=True) == pytest.approx(expected, abs=1e-6)
    assert auroc(s, p, keep_below=False) == pytest.approx(1 - expected, abs=1e-6)


def test_spearman_is_pearson_of_mean_ranks():
    g = torch.Generator().manual_seed(1)
    x = torch.randint(0, 4, (50,), generator=g).double()
    y = torch.randint(0, 7, (50,), generator=g).double()

    def mean_ranks(v):
        return torch.tensor([float((v < a).sum() + ((v == a).sum() + 1) / 2) for a in v])

    rx, ry = mean_ranks(x), mean_ranks(y)
    expected = float(torch.corrcoef(torch.stack([rx, ry]))[0, 1])
    assert spearman(x, y) == pytest.approx(expected, abs=1e-6)
    assert math.isnan(spearman(torch.ones(5), torch.arange(5.0)))
    assert math.isnan(spearman(torch.tensor([1.0, math.nan]), torch.tensor([1.0, 2.0])))


def test_an_ensemble_gives_its_disagreement_and_single_heads_do_not():
    raw = torch.randn(4, 2, 10, dtype=torch.float64)
    names = ["dt", "raw_norm", "disagreement"]
    assert [s.name for s in available_scores(names, True, False)] == ["dt", "raw_norm"]
    assert [s.name for s in available_scores(names, True, False, True)] == names
    prediction = EnsembleHead([make_head("a"), make_head("a")])(raw)
    values = SCORES["disagreement"].fn(prediction)
    assert values.shape == (4,) and bool((values >= 0).all())
