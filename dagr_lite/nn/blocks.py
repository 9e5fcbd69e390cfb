"""Small convolutional building blocks shared by the branches and the head."""
from __future__ import annotations

from torch import nn


def conv_bn_act(c_in: int, c_out: int, *, stride: int = 1, k: int = 3) -> nn.Sequential:
    """``k x k`` convolution (no bias, "same" padding for odd ``k``), batch norm, SiLU.

    Submodules ``0`` (conv), ``1`` (batch norm), ``2`` (SiLU): state_dict keys ``0.weight``, ``1.weight``, ...
    ``(B, c_in, H, W) -> (B, c_out, ceil(H / stride), ceil(W / stride))``.
    """
    return nn.Sequential(nn.Conv2d(c_in, c_out, k, stride, k // 2, bias=False), nn.BatchNorm2d(c_out), nn.SiLU())
