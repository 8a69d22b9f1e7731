"""Floor 2: LightningDataModules, dataset readers and demo-data writers."""

from rotlearn.extras import require

require("train", "rotlearn.data (Lightning DataModules)")

from rotlearn.data.corruption import corrupted_flags, draw_erasing_boxes, erase_boxes
from rotlearn.data.draws import DrawDataModule, draw_seed
from rotlearn.data.kitti import KittiOdometryDataModule, read_kitti_poses
from rotlearn.data.mav import (
    MAVDataModule,
    match_poses,
    read_frame_list,
    read_pair_file,
    read_pose_file,
)
from rotlearn.data.pairs import ImagePairDataModule, ImagePairs, PairIndex
from rotlearn.data.shapenet import ShapeNetDataModule, read_point_file, sample_meshes
from rotlearn.data.splits import hold_out_tail
from rotlearn.data.synthetic import SyntheticWahbaDataModule, wahba_batch

__all__ = [
    "DrawDataModule",
    "ImagePairDataModule",
    "ImagePairs",
    "KittiOdometryDataModule",
    "MAVDataModule",
    "PairIndex",
    "ShapeNetDataModule",
    "SyntheticWahbaDataModule",
    "corrupted_flags",
    "draw_erasing_boxes",
    "draw_seed",
    "erase_boxes",
    "hold_out_tail",
    "match_poses",
    "read_frame_list",
    "read_kitti_poses",
    "read_pair_file",
    "read_point_file",
    "read_pose_file",
    "sample_meshes",
    "wahba_batch",
]
