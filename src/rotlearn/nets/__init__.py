"""Floor 2: backbones, plain `nn.Module`s that map an input batch to the head's raw numbers."""

from rotlearn.nets.pointnet import PointNet, mlp

__all__ = ["PointNet", "mlp"]
