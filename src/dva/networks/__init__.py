"""The networks, by family: :mod:`~dva.networks.conv` (the shared convolutions and pixel
encoder), :mod:`~dva.networks.actor_critic` (D.Va / SHAC), :mod:`~dva.networks.off_policy`
(DrQ-v2, CURL), :mod:`~dva.networks.dreamer` (DreamerV3)."""

from dva.networks.actor_critic import MLP, NETWORK_STYLES, Actor, Critic, NetworkStyle, RunningStats, dense
from dva.networks.conv import CONV_DIMENSIONS, Conv, PixelEncoder, conv_valid, scale_pixels
from dva.networks.dreamer import (
    RSSM,
    ConvDecoder,
    ConvEncoder,
    DreamerMLP,
    MLPEncoder,
    StridedConv4,
    norm_silu,
    strided_conv4,
    strided_conv4_transpose,
)
from dva.networks.off_policy import (
    DeterministicActor,
    Projection,
    ReluMLP,
    SquashedGaussianActor,
    TwinQ,
    feature_trunk,
)

__all__ = [
    "CONV_DIMENSIONS",
    "MLP",
    "NETWORK_STYLES",
    "RSSM",
    "Actor",
    "Conv",
    "ConvDecoder",
    "ConvEncoder",
    "Critic",
    "DeterministicActor",
    "DreamerMLP",
    "MLPEncoder",
    "NetworkStyle",
    "PixelEncoder",
    "Projection",
    "ReluMLP",
    "RunningStats",
    "SquashedGaussianActor",
    "StridedConv4",
    "TwinQ",
    "conv_valid",
    "dense",
    "feature_trunk",
    "norm_silu",
    "scale_pixels",
    "strided_conv4",
    "strided_conv4_transpose",
]
