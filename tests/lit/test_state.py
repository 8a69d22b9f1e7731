"""`RunStateHooks` in a LightningModule of a user's own: the epochs of the weights a test scores,
and a checkpoint loaded outside a trainer."""

from __future__ import annotations

import lightning.pytorch as pl
import torch
from torch.utils.data import DataLoader, TensorDataset

from rotlearn.lit.state import RunStateHooks


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
