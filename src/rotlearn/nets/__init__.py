"""Floor 2: backbones, plain `nn.Module`s that map an input batch to the head's raw numbers."""

from rotlearn.nets.pointnet import PointNet, mlp
from rotlearn.nets.pooling import LinearMaxPool, linear_max

__all__ = ["LinearMaxPool", "PointNet", "linear_max", "mlp"]
