"""The on-device NaN/inf check (rotlearn.lit.finite): deferred reads, the first failure named,
no update after it, and its config key."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from rotlearn.cli.train import ConfigError, build
from rotlearn.errors import NonFiniteError
from rotlearn.lit.finite import FINITE_CHECK_EVERY, FiniteRecord
from tests.conftest import FAST


def test_the_record_keeps_the_first_failure_with_its_counts_until_read():
    record = FiniteRecord()
    record.observe(torch.ones(3), ("a",), None)
    record.observe(torch.tensor([1.0, math.nan, math.inf, math.nan]), ("b",), torch.tensor(False))
    record.observe(torch.tensor(math.inf), ("c",), torch.tensor(True))  # a later failure
    assert bool(record.failed())
    failure = record.read()
    assert failure == {"facts": ("b",), "shape": (4,), "nan": 2, "inf": 1, "inputs_bad": False}
    assert record.read() is None  # a read starts a new record
    record.observe(torch.zeros(2, 2), ("d",), None)
    assert not bool(record.failed()) and record.read() is None


def _poison_input_at(model, step: int) -> list[int]:
    """Make the input of training batch `step` (of the first epoch) NaN; returns the list of the
    batch indices that `training_step` is called with."""
    steps, training_step = [], model.training_step

    def poisoned(batch, batch_idx):
        steps.append(batch_idx)
        if len(steps) == step + 1:
            batch["input"][0, 0, 0] = math.nan
        return training_step(batch, batch_idx)

    model.training_step = poisoned
    return steps


def test_a_failure_is_read_later_names_its_own_step_and_no_update_follows_it(make_cfg):
    every = ["model.finite_check_every=5", "trainer.num_sanity_val_steps=0"]
    cfg = make_cfg([*FAST, "data.batches_per_epoch=12", *every])
    model, datamodule, trainer = build(cfg)
    steps = _poison_input_at(model, 2)
    with pytest.raises(NonFiniteError) as raised:
        trainer.fit(model, datamodule=datamodule)
    message = str(raised.value)
    assert "network output 'raw' at train step 2 (epoch 0, batch 2)" in message
    assert "input batch is itself non-finite" in message
    assert steps == [0, 1, 2, 3, 4]  # read once, after the fifth step: no sync per step
    # the NaN step's gradients (and those of the steps until the read) were zeroed on the device
    assert all(bool(p.isfinite().all()) for p in model.parameters())


def test_a_failure_in_the_last_batches_is_read_before_validation_and_checkpoints(make_cfg):
    cfg = make_cfg([*FAST, "data.batches_per_epoch=3", "trainer.num_sanity_val_steps=0"])
    model, datamodule, trainer = build(cfg)
    assert model.finite_check_every == FINITE_CHECK_EVERY > 3
    _poison_input_at(model, 1)
    with pytest.raises(NonFiniteError, match=r"train step 1 \(epoch 0, batch 1\)"):
        trainer.fit(model, datamodule=datamodule)
    assert not (Path(cfg.paths.output_dir) / "checkpoints").exists()


def test_the_loss_is_checked_too(make_cfg):
    model, datamodule, trainer = build(make_cfg([*FAST, "trainer.num_sanity_val_steps=0"]))
    forward = model.loss.forward
    model.loss.forward = lambda prediction, batch: forward(prediction, batch) * math.inf
    with pytest.raises(NonFiniteError, match=r"non-finite loss at train step 0 .*overflowed"):
        trainer.fit(model, datamodule=datamodule)


def test_validation_is_checked_at_its_end(make_cfg):
    model, datamodule, trainer = build(make_cfg([*FAST, "trainer.max_epochs=1"]))
    with torch.no_grad():
        model.net.head_mlp[-1].bias[0] = math.nan
    with pytest.raises(NonFiniteError, match=r"'raw' at val step 0 .*weights are not"):
        trainer.fit(model, datamodule=datamodule)  # the sanity check's validation


@pytest.mark.parametrize("value", [0, -3])
def test_finite_check_every_must_be_positive(make_cfg, value):
    with pytest.raises(ConfigError, match=r"model\.finite_check_every: should be greater than 0"):
        build(make_cfg([*FAST, f"model.finite_check_every={value}"]))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_observing_a_training_step_does_not_synchronise_with_the_gpu(make_cfg):
    """With CUDA's sync debug mode set to error, any host sync while a step is observed raises.

    The first step runs before the mode is set: it uploads the per-device constants once
    (`rotlearn.geometry.symmetric`'s index, a host-to-device copy that the mode counts as a
    sync) and loads the kernels; every later step must not synchronise."""
    model = build(make_cfg([*FAST, "trainer.accelerator=gpu"]))[0].cuda()
    batch = {
        "input": torch.randn(8, 16, 6, device="cuda"),
        "R": torch.eye(3, device="cuda").expand(8, 3, 3).contiguous(),
    }

    def step() -> None:
        prediction, inputs_bad = model._observed_step(batch, "train", 0)
        model._observe("loss", model.loss(prediction, batch), "train", 0, inputs_bad)
        model._finite.failed()

    step()
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        step()
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert model._finite.read() is None
