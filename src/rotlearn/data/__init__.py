"""Floor 2: LightningDataModules, dataset readers and demo-data writers."""

from rotlearn.data.draws import DrawDataModule, draw_seed
from rotlearn.data.shapenet import ShapeNetDataModule, read_point_file, sample_meshes
from rotlearn.data.synthetic import SyntheticWahbaDataModule, wahba_batch

__all__ = [
    "DrawDataModule",
    "ShapeNetDataModule",
    "SyntheticWahbaDataModule",
    "draw_seed",
    "read_point_file",
    "sample_meshes",
    "wahba_batch",
]
