"""The epoch-level metrics of beliefs and per-sample values (rotlearn.metrics): BeliefCalibration
against the functions it is made of, its determinism, and SampleValues' alignment."""

from __future__ import annotations

import math

import pytest
import torch

from rotlearn import bingham as bh
from rotlearn.metrics import BeliefCalibration, SampleValues
from tests.conftest import gen

F32, F64 = torch.float32, torch.float64


def beliefs(seed: int, m: int, dtype: torch.dtype = F32) -> torch.Tensor:
    B = torch.randn(m, 4, 4, generator=gen(seed), dtype=F64)
    return (B @ B.mT * 20.0).to(dtype)


def test_belief_calibration_is_the_nll_and_coverage_of_its_samples_over_batches():
    A = beliefs(0, 60)
    q = bh.sample(A, 1, gen(1))[:, 0]
    metric = BeliefCalibration(num_samples=64, seed=3)
    for part in (slice(0, 25), slice(25, 60)):  # two batches, one of shape (5, 7)
        metric.update(A[part].reshape(-1, 5, 4, 4) if part.start else A[part], q[part])
    values = metric.values()
    torch.testing.assert_close(values["nll"], bh.nll(A.double(), q.double()))
    levels = bh.hpd_level(A.double(), q.double(), 64, torch.Generator().manual_seed(3))
    torch.testing.assert_close(values["level"], levels, rtol=0, atol=0)
    out = metric.compute()
    assert list(out) == ["nll", "ece", *[f"coverage_{a:g}" for a in bh.CREDIBLE_LEVELS]]
    assert "coverage_0.1" in out and "coverage_0.9" in out
    torch.testing.assert_close(out["nll"], values["nll"].mean())
    torch.testing.assert_close(out["ece"], bh.expected_calibration_error(levels))
    torch.testing.assert_close(out["coverage_0.3"], bh.coverage(levels)[2])


def test_belief_calibration_reruns_give_the_same_numbers_and_reset_forgets():
    A, q = beliefs(4, 20), bh.sample(beliefs(4, 20), 1, gen(5))[:, 0]
    first, second = BeliefCalibration(num_samples=32), BeliefCalibration(num_samples=32)
    first.update(A, q)
    second.update(A, q)
    a, b = first.compute(), second.compute()
    assert all(torch.equal(a[k], b[k]) for k in a)
    torch.testing.assert_close(first.values()["level"], second.values()["level"], rtol=0, atol=0)
    first.reset()
    first.update(A[:3], q[:3])
    assert first.values()["nll"].shape == (3,)


def test_belief_beyond_the_supported_dispersion_gets_a_nan_nll_and_is_still_scored(caplog):
    A = beliefs(6, 4, F64)
    A[1] = 2 * bh.MAX_DISPERSION * torch.diag(torch.tensor([1.0, 1.0, 1.0, 0.0], dtype=F64))
    q = torch.tensor([[0.0, 0.0, 0.0, 1.0]] * 4, dtype=F64)
    metric = BeliefCalibration(num_samples=16)
    metric.update(A, q)
    values = metric.values()
    assert math.isnan(values["nll"][1]) and torch.isfinite(values["nll"][[0, 2, 3]]).all()
    assert values["level"][1] == 0.0  # q is that belief's mode
    assert "1 of 4 beliefs" in caplog.text


def test_belief_calibration_needs_a_draw():
    with pytest.raises(ValueError, match="num_samples"):
        BeliefCalibration(num_samples=0)


def test_sample_values_stay_aligned_and_name_what_they_do_not_know():
    values = SampleValues(("error", "dt", "difficulty"))
    values.update(error=torch.tensor([1.0, 2.0]), dt=torch.tensor([[3.0], [4.0]], dtype=F32))
    values.update(error=torch.tensor([5.0]), dt=torch.tensor([6.0]))
    out = values.compute()
    assert set(out) == {"error", "dt"}  # difficulty was never given
    torch.testing.assert_close(out["dt"], torch.tensor([3.0, 4.0, 6.0], dtype=F64))
    assert out["error"].dtype == F64
    with pytest.raises(ValueError, match=r"unknown per-sample value\(s\) \['eigen'\]"):
        values.update(eigen=torch.ones(1))
    values.reset()
    assert values.values() == {}


def _gather_with_an_idle_process(tensor, group=None):
    """What DDP's all-gather returns when a second process saw no test data: an empty state."""
    return [tensor, torch.tensor([], dtype=tensor.dtype)]


def test_states_sync_across_processes_where_one_saw_nothing():
    A = beliefs(12, 6)
    q = bh.sample(A, 1, gen(13))[:, 0]
    calibration = BeliefCalibration(num_samples=16)
    calibration.update(A, q)
    alone = calibration.values()
    calibration._sync_dist(_gather_with_an_idle_process)  # torchmetrics' sync, gather faked
    synced = calibration.values()
    torch.testing.assert_close(synced["nll"], alone["nll"])
    samples = SampleValues(("error", "dt"))
    samples.update(error=torch.tensor([1.0, 2.0]))  # "dt" never given (a head without belief)
    samples._sync_dist(_gather_with_an_idle_process)
    assert set(samples.values()) == {"error"}
