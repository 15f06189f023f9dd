"""Network parts of SGDE: prior encoding, prior-channel stem, prior losses, reference depth net."""

from .depthnet import DepthDecoder, DepthNet, ResNet18Encoder, load_resnet18, sigmoid_to_depth
from .encoding import PriorEncoding
from .losses import (
    DEFAULT_WEIGHT,
    PriorL1Loss,
    PriorLoss,
    PriorRankingLoss,
    PriorVirtualNormalLoss,
    depth_rays,
    pinhole_rays,
)
from .stem import PriorChannelStem, find_first_conv, widen_first_conv, widened_conv

__all__ = [
    "DEFAULT_WEIGHT",
    "DepthDecoder",
    "DepthNet",
    "PriorChannelStem",
    "PriorEncoding",
    "PriorL1Loss",
    "PriorLoss",
    "PriorRankingLoss",
    "PriorVirtualNormalLoss",
    "ResNet18Encoder",
    "depth_rays",
    "find_first_conv",
    "load_resnet18",
    "pinhole_rays",
    "sigmoid_to_depth",
    "widen_first_conv",
    "widened_conv",
]
