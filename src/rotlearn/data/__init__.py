"""Floor 2: LightningDataModules, dataset readers and demo-data writers."""

from rotlearn.data.synthetic import SyntheticWahbaDataModule, draw_seed, wahba_batch

__all__ = ["SyntheticWahbaDataModule", "draw_seed", "wahba_batch"]
