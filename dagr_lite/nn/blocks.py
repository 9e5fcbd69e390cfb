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


def fold_batch_norms(module: nn.Module) -> nn.Module:
    """``module`` with every convolution that a batch norm follows in an ``nn.Sequential`` (each
    :func:`conv_bn_act` block) made one convolution with a bias, in place, and returned: the batch
    norm's evaluation-mode map ``(y - mean) gamma / sqrt(var + eps) + beta`` is folded into the
    convolution's weight and bias (computed in float64, stored in the weight's dtype and memory
    layout) and the batch norm replaced by ``nn.Identity``. In evaluation mode the output is the
    unfolded module's up to rounding, with one operation less per block; for inference only (a
    module in training mode, whose batch norms read the batch's statistics, is refused)."""
    if module.training:
        raise ValueError("fold_batch_norms folds evaluation-mode batch norms: call module.eval() first")
    pairs = [block for block in module.modules() if isinstance(block, nn.Sequential) and len(block) >= 2
             and isinstance(block[0], nn.Conv2d) and isinstance(block[1], nn.BatchNorm2d)]
    for block in pairs:
        conv, bn = block[0], block[1]
        weight = conv.weight.detach()
        gamma = bn.weight.detach().double() if bn.weight is not None else torch.ones_like(bn.running_var, dtype=torch.float64)
        beta = bn.bias.detach().double() if bn.bias is not None else torch.zeros_like(gamma)
        scale = gamma / torch.sqrt(bn.running_var.double() + bn.eps)  # (C_out,)
        bias = beta - bn.running_mean.double() * scale
        if conv.bias is not None:
            bias = bias + conv.bias.detach().double() * scale
        folded = nn.Conv2d(conv.in_channels, conv.out_channels, conv.kernel_size, conv.stride, conv.padding,
                           conv.dilation, conv.groups, bias=True, padding_mode=conv.padding_mode,
                           device=weight.device, dtype=weight.dtype)
        layout = (torch.channels_last if weight.is_contiguous(memory_format=torch.channels_last)
                  and not weight.is_contiguous() else torch.contiguous_format)
        folded.weight.data = (weight.double() * scale.view(-1, 1, 1, 1)).to(weight.dtype).contiguous(memory_format=layout)
        folded.bias.data = bias.to(weight.dtype)
        block[0], block[1] = folded, nn.Identity()
    return module


class Residual(nn.Module):
    """``x + conv3x3(conv1x1(x))``, each a :func:`conv_bn_act`; shape-preserving."""

    def __init__(self, channels: int):
        super().__init__()
        self.body = nn.Sequential(conv_bn_act(channels, channels, k=1), conv_bn_act(channels, channels))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.body(x)
