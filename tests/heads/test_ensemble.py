"""`EnsembleHead` and `EnsembleNet`: K belief heads as one prediction (the product belief)."""

from __future__ import annotations

import pytest
import torch

from rotlearn.heads import AHead, EnsembleHead, FisherHead, SixDHead
from rotlearn.nets import EnsembleNet
from tests.conftest import gen


def test_one_member_is_that_member_and_identical_members_multiply_the_belief():
    raw = torch.randn(5, 10, generator=gen(0), dtype=torch.float64)
    alone = AHead()(raw)
    one = EnsembleHead([AHead()])(raw[:, None])
    torch.testing.assert_close(one.A, alone.A)
    torch.testing.assert_close(one.R, alone.R)
    two = EnsembleHead([AHead(), AHead()])(torch.stack([raw, raw], dim=1))
    torch.testing.assert_close(two.A, 2 * alone.A)
    torch.testing.assert_close(two.R, alone.R)
    assert float(two.disagreement.max()) < 1e-3 and two.members.shape == (2, 5, 4)
    assert two.raw.shape == (5, 20)


def test_each_member_is_tempered_by_its_own_temperature_and_fisher_heads_mix_in():
    g = gen(1)
    a_raw, f_raw = torch.randn(4, 10, generator=g), torch.randn(4, 9, generator=g)
    raw = torch.stack([a_raw, torch.nn.functional.pad(f_raw, (0, 1))], dim=1)
    head = EnsembleHead([AHead(), FisherHead()], temperatures=[2.0, 0.5])
    prediction = head(raw)
    expected = AHead()(a_raw).A / 2.0 + FisherHead()(f_raw).A / 0.5
    torch.testing.assert_close(prediction.A, expected)


def test_members_without_a_belief_and_wrong_shapes_are_refused():
    with pytest.raises(ValueError, match="belief"):
        EnsembleHead([AHead(), SixDHead()])
    with pytest.raises(ValueError, match="temperature"):
        EnsembleHead([AHead()], temperatures=[0.0])
    with pytest.raises(ValueError, match=r"\(\.\.\., 2, d\)"):
        EnsembleHead([AHead(), AHead()])(torch.randn(3, 10))


def test_the_net_stacks_its_members_outputs_padded():
    nets = [torch.nn.Linear(6, 10), torch.nn.Linear(6, 9)]
    nets[0].in_channels = 6
    out = EnsembleNet(nets)(torch.randn(3, 6))
    assert out.shape == (3, 2, 10) and bool((out[:, 1, 9] == 0).all())
    assert EnsembleNet(nets).in_channels == 6
