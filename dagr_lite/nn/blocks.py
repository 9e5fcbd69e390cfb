"""Small convolutional building blocks shared by the branches and the head."""
from __future__ import annotations

import torch
from torch import nn


def conv_bn_act(c_in: int, c_out: int, *, stride: int = 1, k: int = 3) -> nn.Sequential:
    """``k x k`` convolution (no bias), batch norm, SiLU.

    Odd ``k``: "same" padding, ``(B, c_in, H, W) -> (B, c_out, ceil(H / stride), ceil(W / stride))``.
    Even ``k`` (patches, ``k = stride``): no padding, ``H / stride`` for ``H`` a multiple of ``stride``.
    Submodules ``0`` (conv), ``1`` (batch norm), ``2`` (SiLU): state_dict keys ``0.weight``, ``1.weight``, ...
    """
    padding = k // 2 if k % 2 else 0
    return nn.Sequential(nn.Conv2d(c_in, c_out, k, stride, padding, bias=False), nn.BatchNorm2d(c_out), nn.SiLU())


class Residual(nn.Module):
    """``x + conv3x3(conv1x1(x))``, each a :func:`conv_bn_act`; shape-preserving."""

    def __init__(self, channels: int):
        super().__init__()
        self.body = nn.Sequential(conv_bn_act(channels, channels, k=1), conv_bn_act(channels, channels))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.body(x)
