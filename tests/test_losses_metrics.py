"""Losses (paper eqs. 17-18, the likelihoods) and the epoch-level angular error metric."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from rotlearn import bingham, fisher
from rotlearn.cli.train import train
from rotlearn.errors import ConfigError
from rotlearn.geometry import quat_chordal_distance, quat_to_rotmat, rotmat_to_quat
from rotlearn.heads import HEADS, make_head
from rotlearn.losses import AngularLoss, BinghamNLLLoss, ChordalLoss, FisherNLLLoss
from rotlearn.metrics import AngularError
from tests.conftest import FAST, gen

F64 = torch.float64


def scipy_rotmats(seed: int, shape: tuple[int, ...]) -> torch.Tensor:
    n = math.prod(shape)
    mats = Rotation.random(n, random_state=seed).as_matrix()
    return torch.from_numpy(mats).reshape(*shape, 3, 3)


def scipy_angle(R1: torch.Tensor, R2: torch.Tensor) -> np.ndarray:
    """|Log(R1^T R2)| in radians from scipy (independent reference), flattened, float64."""
    r1 = Rotation.from_matrix(R1.detach().double().reshape(-1, 3, 3).numpy())
    r2 = Rotation.from_matrix(R2.detach().double().reshape(-1, 3, 3).numpy())
    return (r1.inv() * r2).magnitude()


def predict(name: str, shape: tuple[int, ...], seed: int):
    head = make_head(name)
    raw = torch.randn((*shape, head.out_dim), generator=gen(seed), dtype=F64)
    return head(raw.requires_grad_())


@pytest.mark.parametrize("shape", [(8,), (2, 5)], ids=str)
@pytest.mark.parametrize("name", sorted(HEADS))
def test_chordal_loss_is_mean_squared_frobenius(name, shape):
    pred = predict(name, shape, seed=len(name))
    R_true = scipy_rotmats(1, shape)
    loss = ChordalLoss()(pred, {"R": R_true})
    assert loss.shape == ()
    expected = ((pred.R - R_true) ** 2).sum((-1, -2)).mean()
    torch.testing.assert_close(loss, expected, atol=1e-12, rtol=0)
    # 8 sin^2(t/2) with scipy's angles
    t = scipy_angle(pred.R, R_true)
    assert abs(loss.item() - np.mean(8 * np.sin(t / 2) ** 2)) < 1e-10
    loss.backward()
    assert torch.isfinite(pred.raw.grad).all() and pred.raw.grad.abs().sum() > 0


@pytest.mark.parametrize("name", ["quat", "a"])
def test_chordal_loss_equals_quaternion_chordal_form(name):
    # for quaternion heads: 2 d^2 (4 - d^2), d = min(|q - q*|, |q + q*|) (paper footnote 3)
    pred = predict(name, (64,), seed=3)
    R_true = scipy_rotmats(4, (64,))
    d = quat_chordal_distance(pred.q, rotmat_to_quat(R_true))
    expected = (2 * d**2 * (4 - d**2)).mean()
    torch.testing.assert_close(ChordalLoss()(pred, {"R": R_true}), expected, atol=1e-12, rtol=0)


@pytest.mark.parametrize("shape", [(8,), (2, 5)], ids=str)
@pytest.mark.parametrize("name", sorted(HEADS))
def test_angular_loss_is_mean_squared_angle(name, shape):
    pred = predict(name, shape, seed=5 + len(name))
    R_true = scipy_rotmats(6, shape)
    loss = AngularLoss()(pred, {"R": R_true})
    assert loss.shape == ()
    assert abs(loss.item() - np.mean(scipy_angle(pred.R, R_true) ** 2)) < 1e-10
    loss.backward()
    assert torch.isfinite(pred.raw.grad).all()


def test_losses_vanish_at_the_target_and_know_the_angle():
    R = scipy_rotmats(7, (16,))
    pred = make_head("svd9d")(R.reshape(16, 9))
    assert ChordalLoss()(pred, {"R": R}).item() < 1e-20
    assert AngularLoss()(pred, {"R": R}).item() < 1e-20
    # rotate the target by known angles about known axes
    theta = torch.linspace(0.0, math.pi, 16, dtype=F64)
    axis = torch.nn.functional.normalize(torch.randn(16, 3, generator=gen(8), dtype=F64), dim=-1)
    delta = torch.from_numpy(Rotation.from_rotvec((theta[:, None] * axis).numpy()).as_matrix())
    target = {"R": R @ delta}
    assert abs(AngularLoss()(pred, target).item() - theta.square().mean().item()) < 1e-9
    chordal = (8 * torch.sin(theta / 2) ** 2).mean().item()
    assert abs(ChordalLoss()(pred, target).item() - chordal) < 1e-12


def reference_stats(deg: np.ndarray) -> dict[str, float]:
    return {
        "err_mean": float(np.mean(deg)),
        "err_median": float(np.median(deg)),
        "err_p10": float(np.percentile(deg, 10, method="linear")),
        "err_p90": float(np.percentile(deg, 90, method="linear")),
    }


def assert_stats(result: dict[str, torch.Tensor], expected: dict[str, float], atol: float):
    assert set(result) == set(expected)
    for key, value in expected.items():
        assert result[key].shape == ()
        assert abs(result[key].item() - value) <= atol, (key, result[key].item(), value)


def test_angular_error_metric_matches_numpy():
    metric = AngularError()
    angles = []
    # several batches of different sizes and shapes; 2 + 7 + 6 = 15 samples, so the percentiles
    # fall between samples and the interpolation rule matters
    for seed, shape in [(10, (2,)), (11, (7,)), (12, (2, 3))]:
        R_pred, R_true = scipy_rotmats(seed, shape), scipy_rotmats(seed + 100, shape)
        metric.update(R_pred, R_true)
        angles.append(np.degrees(scipy_angle(R_pred, R_true)))
    deg = np.concatenate(angles)
    assert deg.size == 15
    expected = reference_stats(deg)
    # the interpolated percentiles are not just the nearest samples
    assert not np.isclose(expected["err_p10"], deg).any()
    assert_stats(metric.compute(), expected, atol=1e-8)


def test_angular_error_metric_float32_inputs():
    metric = AngularError()
    R_pred, R_true = scipy_rotmats(13, (50,)), scipy_rotmats(14, (50,))
    metric.update(R_pred.float(), R_true.float())
    deg = np.degrees(scipy_angle(R_pred, R_true))
    # float32 angle: ~1e-6 rad of rounding, i.e. ~1e-4 degrees
    result = metric.compute()
    assert all(v.dtype == F64 for v in result.values())
    assert_stats(result, reference_stats(deg), atol=1e-3)


def test_angular_error_metric_reset():
    metric = AngularError()
    metric.update(scipy_rotmats(15, (10,)), scipy_rotmats(16, (10,)))
    first = metric.compute()
    metric.reset()
    assert len(metric.errors) == 0
    R_pred, R_true = scipy_rotmats(17, (9,)), scipy_rotmats(18, (9,))
    metric.update(R_pred, R_true)
    expected = reference_stats(np.degrees(scipy_angle(R_pred, R_true)))
    result = metric.compute()
    assert_stats(result, expected, atol=1e-8)
    assert result["err_mean"].item() != pytest.approx(first["err_mean"].item())


# ------------------------------------------------------------------- the likelihood losses


def test_fisher_nll_is_the_bingham_nll_on_the_fisher_head():
    """loss=fisher_nll and loss=bingham score the same density on rep=fisher (A = -K(F)): the
    same number and the same gradient, from the 3 x 3 SVD and from the 4 x 4 eigensolver."""
    raw = torch.randn(32, 9, generator=gen(20), dtype=F64)
    R_true = scipy_rotmats(21, (32,))
    values, grads = [], []
    for loss in (FisherNLLLoss(rep="fisher"), BinghamNLLLoss(rep="fisher")):
        x = raw.clone().requires_grad_()
        value = loss(make_head("fisher")(x), {"R": R_true})
        values.append(value)
        grads.append(torch.autograd.grad(value, x)[0])
    assert values[0].shape == ()
    torch.testing.assert_close(values[0], values[1], atol=1e-10, rtol=0)
    torch.testing.assert_close(grads[0], grads[1], atol=1e-9, rtol=0)
    pred = make_head("fisher")(raw)
    torch.testing.assert_close(values[0], fisher.nll(pred.F, R_true).mean(), atol=0, rtol=0)


@pytest.mark.parametrize("rep", ["quat", "sixd", "svd9d", "a"])
def test_fisher_nll_refuses_heads_without_f(rep):
    message = (
        f"loss=fisher_nll needs a head that gives a matrix Fisher parameter (rep=fisher); "
        f"rep={rep} does not"
    )
    with pytest.raises(ConfigError) as info:
        FisherNLLLoss(rep=rep)
    assert info.value.key == "rep" and info.value.message == message
    pred = predict(rep, (3,), seed=22)
    with pytest.raises(ValueError) as info:
        FisherNLLLoss()(pred, {"R": pred.R.detach()})
    assert str(info.value) == message
    assert "rep='fisher'" in repr(FisherNLLLoss(rep="fisher"))


def test_fisher_head_trains_end_to_end_with_fisher_nll(make_cfg):
    """`rotlearn-train rep=fisher loss=fisher_nll`: one epoch on tiny data, the DT score (from
    F's singular values) ranks the errors like the A head's."""
    metrics = train(make_cfg(["rep=fisher", "loss=fisher_nll", *FAST, "trainer.max_epochs=1"]))
    assert metrics["rep"] == "fisher" and math.isfinite(metrics["train/loss"])
    assert 0.0 <= metrics["test/err_median"] <= 180.0
    assert -1.0 <= metrics["test/dt_spearman"] <= 1.0


# The likelihood losses score beliefs without host syncs (check=False): a training step never waits
# for the device; the checks they skip are the public functions' (tests/bingham, tests/fisher).


def _beliefs(shape: tuple[int, ...], dtype: torch.dtype, seed: int):
    """(A, q, F, R): random symmetric A, unit quaternions, F and the rotations of q."""
    A = torch.randn(*shape, 4, 4, generator=gen(seed), dtype=dtype)
    q = torch.nn.functional.normalize(torch.randn(*shape, 4, generator=gen(seed + 1)), dim=-1)
    F = torch.randn(*shape, 3, 3, generator=gen(seed + 2), dtype=dtype)
    q = q.to(dtype)
    return A + A.transpose(-1, -2), q, F, quat_to_rotmat(q)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
@pytest.mark.parametrize("shape", [(), (7,), (2, 3)])
def test_unchecked_likelihoods_equal_the_checked_ones_in_range(dtype, shape):
    A, q, F, R = _beliefs(shape, dtype, seed=30)
    for fn, args in ((bingham.nll, (A, q)), (fisher.nll, (F, R))):
        results = []
        for check in (True, False):
            inputs = [a.clone().requires_grad_() for a in args]
            value = fn(*inputs, check=check)
            results.append((value, *torch.autograd.grad(value.sum(), inputs)))
        assert results[1][0].shape == shape and results[1][0].dtype == dtype
        for checked, unchecked in zip(*results, strict=True):  # values, then each gradient
            torch.testing.assert_close(unchecked, checked, rtol=0, atol=0)
    A, q, F, R = _beliefs((3,), F64, seed=31)
    symmetric = lambda a: bingham.nll(a + a.transpose(-1, -2), q, check=False)  # noqa: E731
    assert torch.autograd.gradcheck(symmetric, (A.requires_grad_(),))
    assert torch.autograd.gradcheck(lambda f: fisher.nll(f, R, check=False), (F.requires_grad_(),))
    # the gradient in q is that of the value, off the sphere too, whatever multiple of I A holds
    for c in (0.0, 100.0):
        shifted = (A + A.transpose(-1, -2) + c * torch.eye(4, dtype=F64)).detach()
        nll = lambda x, a=shifted: bingham.nll(a, x)  # noqa: E731
        assert torch.autograd.gradcheck(nll, (q.requires_grad_(),))


def test_a_belief_sharper_than_the_supported_range_is_not_sharpened_further():
    """A training belief that passed MAX_DISPERSION failed the run (the checked NLL refuses it);
    unchecked, its dispersion is taken at the bound, so the loss grows with the belief's scale."""
    A, q, F, R = _beliefs((), F64, seed=32)
    cases = (
        (bingham.nll, A / A.norm(), q, 4 * bingham.MAX_DISPERSION),
        (fisher.nll, F / F.norm(), R, 4 * fisher.MAX_SINGULAR_SUM),
    )
    for fn, unit, target, scale in cases:
        with pytest.raises(ValueError, match=r"above MAX_(DISPERSION|SINGULAR_SUM)"):
            fn(scale * unit, target)
        s = torch.tensor(scale, dtype=F64, requires_grad=True)
        value = fn(s * unit, target, check=False)
        (slope,) = torch.autograd.grad(value, s)
        assert torch.isfinite(value) and slope > 0


@pytest.mark.parametrize("loss", [BinghamNLLLoss(rep="fisher"), FisherNLLLoss(rep="fisher")])
def test_the_likelihood_losses_trace_without_a_graph_break(loss):
    """torch.compile(fullgraph=True) fails on any host sync (a bool() of a tensor); the checked
    functions do not trace (the control shows the test can fail)."""
    pred = make_head("fisher")(torch.randn(6, 9, generator=gen(33)))
    batch = {"R": scipy_rotmats(34, (6,)).float()}
    loss(pred, batch)  # caches filled eagerly (the Talbot nodes)
    compiled = torch.compile(lambda p, b: loss(p, b), backend="eager", fullgraph=True)
    torch.testing.assert_close(compiled(pred, batch), loss(pred, batch))
    checked = torch.compile(lambda A, q: bingham.nll(A, q), backend="eager", fullgraph=True)
    with pytest.raises(Exception, match=r"(?i)graph break|data-dependent|Unsupported"):
        checked(pred.A, rotmat_to_quat(batch["R"]))
