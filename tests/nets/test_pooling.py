"""LinearMaxPool equals nn.Linear followed by a max over points, in values and in gradients."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from rotlearn.nets import LinearMaxPool, PointNet
from tests.conftest import ATOL, DTYPES, gen

# values: a dot product of C_IN = 12 terms of size O(1); the two paths sum in different orders
C_IN, C_OUT = 12, 16


def make_pool(dtype: torch.dtype, chunk_points: int, seed: int = 0) -> LinearMaxPool:
    torch.manual_seed(seed)
    return LinearMaxPool(C_IN, C_OUT, chunk_points=chunk_points).to(dtype)


def naive(pool: LinearMaxPool, x: torch.Tensor) -> tuple[nn.Linear, torch.Tensor]:
    """The reference: an nn.Linear with the same weights, then max over the point axis."""
    linear = nn.Linear(C_IN, C_OUT).to(x.dtype)
    with torch.no_grad():
        linear.weight.copy_(pool.linear.weight)
        linear.bias.copy_(pool.linear.bias)
    return linear, linear(x).max(dim=-2).values


def assert_no_near_ties(pool: LinearMaxPool, x: torch.Tensor) -> None:
    """The gradient comparison needs a unique argmax well clear of rounding."""
    with torch.no_grad():
        top2 = (x @ pool.linear.weight.T).topk(2, dim=-2).values
    assert ((top2[..., 0, :] - top2[..., 1, :]) > 1e-4).all()


SHAPES = [(5, 20), (2, 5, 20), (1, 1), (3, 1)]  # lead + (N,); N = 1 is a trivial max
CHUNKS = [1, 7, 20, 10_000]  # one sample per chunk ... all samples in one chunk


@pytest.mark.parametrize("chunk_points", CHUNKS)
@pytest.mark.parametrize("shape", SHAPES, ids=str)
@pytest.mark.parametrize("dtype", DTYPES, ids=str)
def test_values_and_gradients_match_linear_then_max(dtype, shape, chunk_points):
    pool = make_pool(dtype, chunk_points)
    x = torch.randn((*shape, C_IN), generator=gen(1), dtype=dtype)
    if shape[-1] > 1:
        assert_no_near_ties(pool, x)
    linear, _ = naive(pool, x)

    xa = x.clone().requires_grad_()
    xb = x.clone().requires_grad_()
    out = pool(xa)
    ref = linear(xb).max(dim=-2).values
    assert out.shape == (*shape[:-1], C_OUT) and out.dtype == dtype
    torch.testing.assert_close(out, ref, atol=ATOL[dtype], rtol=0)

    g = torch.randn(out.shape, generator=gen(2), dtype=dtype)
    grads = torch.autograd.grad(out, (xa, pool.linear.weight, pool.linear.bias), g)
    grads_ref = torch.autograd.grad(ref, (xb, linear.weight, linear.bias), g)
    for got, want in zip(grads, grads_ref, strict=True):
        assert got.shape == want.shape
        torch.testing.assert_close(got, want, atol=10 * ATOL[dtype], rtol=0)
    # a plain .sum() hands the backward an expanded (stride-0) gradient
    (gx,) = torch.autograd.grad(pool(xa).sum(), xa)
    (rx,) = torch.autograd.grad(linear(xb).max(dim=-2).values.sum(), xb)
    torch.testing.assert_close(gx, rx, atol=10 * ATOL[dtype], rtol=0)


@pytest.mark.parametrize("dtype", DTYPES, ids=str)
def test_gradients_of_weights_only_and_of_input_only(dtype):
    pool = make_pool(dtype, 16)
    x = torch.randn((4, 9, C_IN), generator=gen(3), dtype=dtype)
    assert_no_near_ties(pool, x)
    linear, ref = naive(pool, x)
    g = torch.randn(ref.shape, generator=gen(4), dtype=dtype)
    # input without grad (the first layer): weight and bias gradients only
    gw, gb = torch.autograd.grad(pool(x), (pool.linear.weight, pool.linear.bias), g)
    rw, rb = torch.autograd.grad(linear(x).max(dim=-2).values, (linear.weight, linear.bias), g)
    torch.testing.assert_close(gw, rw, atol=10 * ATOL[dtype], rtol=0)
    torch.testing.assert_close(gb, rb, atol=10 * ATOL[dtype], rtol=0)
    # frozen layer: input gradient only
    pool.requires_grad_(False)
    linear.requires_grad_(False)
    xa, xb = x.clone().requires_grad_(), x.clone().requires_grad_()
    (gx,) = torch.autograd.grad(pool(xa), xa, g)
    (rx,) = torch.autograd.grad(linear(xb).max(dim=-2).values, xb, g)
    torch.testing.assert_close(gx, rx, atol=10 * ATOL[dtype], rtol=0)


@pytest.mark.parametrize("chunk_points", [1, 8, 10_000])
def test_gradcheck_float64(chunk_points):
    torch.manual_seed(5)
    pool = LinearMaxPool(5, 6, chunk_points=chunk_points).double()
    x = torch.randn((2, 2, 4, 5), generator=gen(6), dtype=torch.float64)
    assert_no_near_ties(pool, x)
    w0 = pool.linear.weight.detach().clone().requires_grad_()
    b0 = pool.linear.bias.detach().clone().requires_grad_()

    def f(x, w, b):
        # the module's forward, with its parameters replaced by the gradcheck inputs
        return torch.func.functional_call(pool, {"linear.weight": w, "linear.bias": b}, (x,))

    assert torch.autograd.gradcheck(f, (x.requires_grad_(), w0, b0))


@pytest.mark.parametrize("dtype", DTYPES, ids=str)
@pytest.mark.parametrize("chunk_points", [1, 50, 10_000])
def test_no_grad_eval_path(dtype, chunk_points):
    pool = make_pool(dtype, chunk_points)
    x = torch.randn((2, 4, 25, C_IN), generator=gen(7), dtype=dtype)
    _, ref = naive(pool, x)
    with_grad = pool(x.clone().requires_grad_())
    with torch.no_grad():
        out = pool(x)
    assert not out.requires_grad
    torch.testing.assert_close(out, ref, atol=ATOL[dtype], rtol=0)
    torch.testing.assert_close(out, with_grad.detach(), atol=0, rtol=0)
    pool.eval()
    with torch.inference_mode():
        torch.testing.assert_close(pool(x), out, atol=0, rtol=0)


def test_state_dict_keys_are_those_of_a_wrapped_linear():
    pool = LinearMaxPool(C_IN, C_OUT)
    assert set(pool.state_dict()) == {"linear.weight", "linear.bias"}


@pytest.mark.parametrize("lead", [(3,), (2, 3)], ids=str)
@pytest.mark.parametrize("out_dim", [4, 10])
def test_pointnet_output_shape_and_reference(lead, out_dim):
    torch.manual_seed(8)
    net = PointNet(out_dim, in_channels=6, point_channels=(8, 16, 32), head_channels=(16, 8))
    x = torch.randn((*lead, 11, 6), generator=gen(9))
    y = net(x)
    assert y.shape == (*lead, out_dim)
    # same function as the unfused composition point_mlp -> Linear -> max -> head_mlp
    ref = net.head_mlp(net.pool.linear(net.point_mlp(x)).amax(dim=-2))
    torch.testing.assert_close(y, ref, atol=1e-5, rtol=1e-5)
    # and it trains: every parameter gets a finite, nonzero gradient
    y.square().sum().backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    assert net.pool.linear.weight.grad.abs().sum() > 0


def test_pointnet_without_hidden_point_layers():
    net = PointNet(9, in_channels=6, point_channels=(16,), head_channels=(8,))
    assert net.point_mlp is None
    x = torch.randn((4, 7, 6), generator=gen(10))
    assert net(x).shape == (4, 9)
    torch.testing.assert_close(
        net(x), net.head_mlp(net.pool.linear(x).amax(dim=-2)), atol=1e-5, rtol=1e-5
    )


def _layer_outputs(net: PointNet, x: torch.Tensor) -> list[torch.Tensor]:
    """Every Linear's output (per point, pooled, hidden head layers), flattened to (rows, C)."""
    outs, h = [], x
    for layer in net.point_mlp or ():
        h = layer(h)
        if isinstance(layer, nn.Linear):
            outs.append(h.reshape(-1, h.shape[-1]))
    h = net.pool(h)
    outs.append(h)
    for layer in list(net.head_mlp)[:-1]:
        h = layer(h)
        if isinstance(layer, nn.Linear):
            outs.append(h)
    return outs


@pytest.mark.parametrize("point_channels", [(8, 16, 32), (16,)], ids=str)
def test_initialize_from_centres_every_hidden_layer_and_keeps_the_weights(point_channels):
    torch.manual_seed(3)
    net = PointNet(6, in_channels=6, point_channels=point_channels, head_channels=(16, 8))
    x = torch.randn((20, 11, 6), generator=gen(4)).double()
    net = net.double()
    before = {k: v.clone() for k, v in net.state_dict().items()}
    assert max(out.mean(0).abs().max() for out in _layer_outputs(net, x)) > 1e-2
    net.initialize_from(x)
    for out in _layer_outputs(net, x):
        torch.testing.assert_close(out.mean(0), torch.zeros_like(out[0]), atol=1e-12, rtol=0)
    after = net.state_dict()
    changed = {k for k in before if not torch.equal(before[k], after[k])}
    last = f"head_mlp.{len(net.head_mlp) - 1}"
    assert changed and all(k.endswith(".bias") and not k.startswith(last) for k in changed)


@pytest.mark.parametrize(("center_init", "batch"), [(False, 20), (True, 1)])
def test_initialize_from_is_a_no_op_when_off_or_given_one_sample(center_init, batch):
    net = PointNet(6, point_channels=(8, 16), head_channels=(8,), center_init=center_init)
    before = {k: v.clone() for k, v in net.state_dict().items()}
    net.initialize_from(torch.randn((batch, 5, 6), generator=gen(5)))
    assert all(torch.equal(before[k], v) for k, v in net.state_dict().items())


@pytest.mark.parametrize("reduced", [torch.bfloat16, torch.float16])
def test_under_autocast_it_computes_like_linear_then_max(reduced):
    # nn.Linear under autocast multiplies in the autocast dtype; so does the pool, whose backward
    # (sparse products, which have no bf16/fp16 kernels) runs in float32 and casts back
    pool = make_pool(torch.float32, chunk_points=64)
    x = torch.randn((4, 20, C_IN), generator=gen(3))
    linear, _ = naive(pool, x)
    xa, xb = x.clone().requires_grad_(), x.clone().requires_grad_()
    with torch.autocast("cpu", dtype=reduced):
        out = pool(xa)
        ref = linear(xb).max(dim=-2).values
    assert out.dtype == ref.dtype == reduced
    torch.testing.assert_close(out, ref, atol=2e-2, rtol=1e-2)  # rounding differs (bias, order)
    g = torch.randn(out.shape, generator=gen(4)).to(reduced)
    (out * g).sum().backward()
    (ref * g).sum().backward()
    for mine, theirs in ((pool.linear.weight, linear.weight), (pool.linear.bias, linear.bias)):
        assert mine.grad.dtype == torch.float32  # parameters stay float32
        torch.testing.assert_close(mine.grad, theirs.grad, atol=2e-2, rtol=2e-2)
    assert xa.grad.dtype == torch.float32
    torch.testing.assert_close(xa.grad, xb.grad, atol=2e-2, rtol=2e-2)
