"""Datamodules whose loaders yield draw requests; the data is made on the model's device.

A loader yields small dicts {"draw_split", "draw_index", "draw_size"}; after Lightning moves them
to the device, `on_after_batch_transfer` turns each into a batch with `draw(split, index, size)`,
from a generator seeded by (data seed, split, epoch, index). So a run is reproducible, a resumed
run sees the same data, and a learning-rate sweep sees the same data.
"""

from __future__ import annotations

from typing import Any

import lightning.pytorch as pl
import numpy as np
import torch
from torch import Tensor
from torch.utils.data import DataLoader

__all__ = ["SPLITS", "DrawDataModule", "draw_seed", "model_device_dtype"]

SPLITS = {"train": 0, "val": 1, "test": 2}


def draw_seed(*words: int) -> int:
    """A well-mixed 63-bit seed from a tuple of non-negative integers."""
    return int(np.random.SeedSequence(list(words)).generate_state(1, np.uint64)[0] >> 1)


def model_device_dtype(datamodule: pl.LightningDataModule) -> tuple[torch.device, torch.dtype]:
    """The device and dtype of the model the datamodule feeds (CPU, float32 without one)."""
    trainer = datamodule.trainer
    module = trainer.lightning_module if trainer is not None else None
    if module is None:
        return torch.device("cpu"), torch.float32
    return module.device, module.dtype


class DrawDataModule(pl.LightningDataModule):
    """Base class: subclasses set `seed` and `redraw_test` and implement `draw`."""

    seed: int = 0
    redraw_test: bool = False

    def requests(self, split: str, sizes: list[int]) -> DataLoader:
        """A loader of one draw request per batch size in `sizes`."""
        items = [
            {"draw_split": SPLITS[split], "draw_index": i, "draw_size": n}
            for i, n in enumerate(sizes)
        ]
        return DataLoader(items, batch_size=None, shuffle=False, num_workers=0)

    def on_after_batch_transfer(self, batch: Any, dataloader_idx: int) -> Any:
        if not (isinstance(batch, dict) and "draw_split" in batch):
            return batch
        return self.draw(
            int(batch["draw_split"]), int(batch["draw_index"]), int(batch["draw_size"])
        )

    def draw(self, split: int, index: int, size: int) -> dict[str, Tensor]:  # pragma: no cover
        raise NotImplementedError

    def generator(
        self, split: int, index: int
    ) -> tuple[torch.Generator, torch.device, torch.dtype]:
        """The seeded generator for a request, and the device and dtype of the data to make.

        Training draws are redrawn every epoch, on the model's device. Validation and test draws
        are fixed (unless `redraw_test`) and made on the CPU, so they are the same on every device.
        """
        trainer = self.trainer
        device, dtype = model_device_dtype(self)
        epoch = trainer.current_epoch if trainer is not None else 0
        fixed = split != SPLITS["train"] and not self.redraw_test
        seed = draw_seed(self.seed, split, 0 if fixed else epoch + 1, index)
        gen_device = torch.device("cpu") if fixed else device
        return torch.Generator(device=gen_device).manual_seed(seed), device, dtype
