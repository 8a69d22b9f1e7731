"""Floor 2: backbones, plain `nn.Module`s that map an input batch to the head's raw numbers."""

from rotlearn.nets.autoencoder import ConvAutoEncoder
from rotlearn.nets.ensemble import EnsembleNet
from rotlearn.nets.pair_cnn import PairCNN, conv_encoder, encoded_size
from rotlearn.nets.pair_corr import PairCorrelationNet, correlation
from rotlearn.nets.pointnet import PointNet, mlp
from rotlearn.nets.pooling import LinearMaxPool, linear_max

__all__ = [
    "ConvAutoEncoder",
    "EnsembleNet",
    "LinearMaxPool",
    "PairCNN",
    "PairCorrelationNet",
    "PointNet",
    "conv_encoder",
    "correlation",
    "encoded_size",
    "linear_max",
    "mlp",
]
