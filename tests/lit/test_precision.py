"""Mixed precision: `trainer.precision=bf16-mixed` trains every head with every net on the CPU
(Lightning's autocast, as on a GPU), and `trainer=gpu` picks the precision of the machine's GPU."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from rotlearn.cli.train import build
from rotlearn.config.resolvers import gpu_precision
from tests.conftest import FAST, config_options, write_kitti, yaw_sequence

REPS = config_options("rep")
# pair_cnn on a small KITTI-format sequence pair: 16 x 16 images, two narrow conv layers
SMALL_PAIR_CNN = [
    "net.channels=[8,16]",
    "net.hidden=16",
    "data.image_size=16",
    "data.num_workers=0",
]


@pytest.fixture(scope="module")
def kitti_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("kitti")
    return write_kitti(root, {"00": yaw_sequence(4, 1.0), "02": yaw_sequence(6, 2.0)})


def overrides_for(net: str, kitti_root: Path) -> list[str]:
    if net == "pointnet":
        return [*FAST]  # synthetic point clouds
    return [
        "data=kitti",
        f"data.root={kitti_root}",
        "data.train_sequences=[02]",
        "data.test_sequences=[00]",
        "trainer=cpu",
        "trainer.enable_progress_bar=false",
        *SMALL_PAIR_CNN,
    ]


@pytest.mark.parametrize("net", ["pointnet", "pair_cnn"])
@pytest.mark.parametrize("rep", REPS)
def test_bf16_mixed_trains(make_cfg, kitti_root, rep, net):
    cfg = make_cfg(
        [
            f"rep={rep}",
            *overrides_for(net, kitti_root),
            "trainer.precision=bf16-mixed",
            "trainer.fast_dev_run=true",
            "logger=none",
        ]
    )
    assert cfg.net._target_.endswith({"pointnet": "PointNet", "pair_cnn": "PairCNN"}[net])
    model, datamodule, trainer = build(cfg)
    before = {name: p.detach().clone() for name, p in model.named_parameters()}
    seen: dict[str, list] = {"loss": [], "dtype": []}
    training_step, head = model.training_step, model.head.forward

    def spy_step(batch, batch_idx):
        loss = training_step(batch, batch_idx)
        seen["loss"].append(float(loss.detach()))
        return loss

    def spy_head(raw):
        seen["dtype"].append(raw.dtype)
        return head(raw)

    model.training_step, model.head.forward = spy_step, spy_head
    trainer.fit(model, datamodule=datamodule)
    assert seen["loss"] and all(math.isfinite(v) for v in seen["loss"])
    assert torch.bfloat16 in seen["dtype"]  # autocast was on: the net handed the head bf16
    changed = [n for n, p in model.named_parameters() if not torch.equal(p.detach(), before[n])]
    assert changed, "no parameter changed in a bf16-mixed training step"
    assert all(p.dtype == torch.float32 for p in model.parameters())  # master weights stay fp32


def test_gpu_trainer_picks_the_gpus_precision(make_cfg, monkeypatch):
    assert make_cfg(["trainer=gpu"]).trainer.precision == gpu_precision()
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda including_emulation=True: True)
    assert gpu_precision() == "bf16-mixed"
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda including_emulation=True: False)
    assert gpu_precision() == "16-mixed"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert gpu_precision() == "32-true"


@pytest.mark.parametrize(
    ("rep", "loss"),
    [("a", "bingham"), ("a", "angular"), ("fisher", "fisher_nll"), ("fisher", "bingham")],
)
def test_bf16_mixed_trains_belief_heads_with_other_losses(make_cfg, rep, loss):
    cfg = make_cfg(
        [
            f"rep={rep}",
            f"loss={loss}",
            *FAST,
            "trainer.precision=bf16-mixed",
            "trainer.fast_dev_run=true",
        ]
    )
    model, datamodule, trainer = build(cfg)
    before = [p.detach().clone() for p in model.parameters()]
    losses: list[torch.Tensor] = []
    training_step = model.training_step

    def spy_step(batch, batch_idx):
        losses.append(training_step(batch, batch_idx))
        return losses[-1]

    model.training_step = spy_step
    trainer.fit(model, datamodule=datamodule)
    assert losses[0].dtype == torch.float32 and bool(torch.isfinite(losses[0]))
    after = list(model.parameters())
    assert any(not torch.equal(p.detach(), b) for p, b in zip(after, before, strict=True))
