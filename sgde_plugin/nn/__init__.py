"""Network parts of SGDE: prior encoding, prior-channel stem, prior losses, reference depth net."""

from .encoding import PriorEncoding
from .stem import PriorChannelStem, find_first_conv, widen_first_conv, widened_conv

__all__ = ["PriorChannelStem", "PriorEncoding", "find_first_conv", "widen_first_conv", "widened_conv"]
