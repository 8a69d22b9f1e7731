"""`RunStateHooks` in a LightningModule of a user's own: the epochs of the weights a test scores,
and a checkpoint loaded outside a trainer."""

from __future__ import annotations

import lightning.pytorch as pl
import pytest
import torch
from torch.utils.data import DataLoader, TensorDataset

from rotlearn.checkpoint import UnsafeCheckpointError
from rotlearn.lit.state import RunStateHooks, rng_states


class Tiny(RunStateHooks, pl.LightningModule):
    def __init__(self, width: int = 2) -> None:
        super().__init__()
        self.save_hyperparameters()
        self.layer = torch.nn.Linear(width, 1)

    def training_step(self, batch, batch_idx):
        return self.layer(batch[0]).pow(2).mean()

    def test_step(self, batch, batch_idx):
        self.log("test/value", self.layer(batch[0]).mean())

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


def _trainer(tmp_path, epochs: int) -> pl.Trainer:
    return pl.Trainer(max_epochs=epochs, default_root_dir=tmp_path, logger=False,
                      enable_progress_bar=False, enable_model_summary=False,
                      callbacks=[pl.callbacks.ModelCheckpoint(tmp_path, "e{epoch}",
                                                              save_top_k=-1)])  # fmt: skip


def test_the_tested_epochs_are_the_loaded_checkpoints_until_the_weights_train_again(tmp_path):
    """A test of an earlier checkpoint is drawn at its epoch; a fit after it trains the weights
    on (the loaded epoch went stale: a test after it still said 1); a checkpoint loaded outside
    a trainer (`load_from_checkpoint`) loads (the hook read `self.trainer`, which raised)."""
    data = DataLoader(TensorDataset(torch.randn(8, 2)), batch_size=4)
    model = Tiny()
    _trainer(tmp_path, 3).fit(model, data)
    assert model.tested_epochs == 3  # the weights in memory: the last epoch's
    first = tmp_path / "eepoch=0.ckpt"
    tester = _trainer(tmp_path, 3)
    tester.test(model, data, ckpt_path=first, verbose=False, weights_only=True)
    assert model.tested_epochs == 1
    _trainer(tmp_path / "more", 5).fit(model, data)
    assert model.tested_epochs == 5
    loaded = Tiny.load_from_checkpoint(first, weights_only=True)
    assert loaded.tested_epochs == 0 and loaded.hparams.width == 2


def test_random_states_that_cannot_be_restored_are_refused_and_none_is_set(tmp_path):
    """Lightning calls the module's hook before any callback's, so the hook checks what it sets:
    a checkpoint whose numpy state is malformed set torch's and python's states from it before
    numpy's own error (a traceback, where no resume check ran first); now it is refused, naming
    the checkpoint, and no state changes."""
    data = DataLoader(TensorDataset(torch.randn(8, 2)), batch_size=4)
    model = Tiny()
    _trainer(tmp_path, 1).fit(model, data)
    path = tmp_path / "eepoch=0.ckpt"
    checkpoint = torch.load(path, weights_only=True)
    checkpoint["rng_states"]["numpy"][0] = "not a generator"  # torch's and python's restore
    bad = tmp_path / "bad.ckpt"
    torch.save(checkpoint, bad)
    resumed, trainer = Tiny(), _trainer(tmp_path / "again", 2)
    before = rng_states(cuda=False)
    with pytest.raises(UnsafeCheckpointError, match=r"bad\.ckpt: rng_states cannot be restored"):
        trainer.fit(resumed, data, ckpt_path=bad, weights_only=True)
    after = rng_states(cuda=False)
    assert torch.equal(after["torch"], before["torch"]) and after["python"] == before["python"]
    assert torch.equal(after["numpy"][1], before["numpy"][1])
