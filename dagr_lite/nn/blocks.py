"""Small convolutional building blocks shared by the branches and the head."""
from __future__ import annotations

import torch
import torch.nn.functional as F
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


class PackedConv2d(nn.Conv2d):
    """A convolution whose weight is laid out once in oneDNN's blocked format for each input shape
    it sees, run on a channels-last input, with the activation that follows it (``act``: "swish",
    SiLU, or "none") applied in the same call (``torch.ops.mkldnn._convolution_pointwise``).

    The same parameters as the :class:`nn.Conv2d` it was made from, the same function up to the
    order of the sums. The packed path runs for float32 on a CPU outside autograd (a streaming
    answer); any other input (float64, gradients, another device) takes ``F.conv2d`` and the
    activation, as the original does. On the packed path a 1x1 convolution of stride 1 without
    padding or groups is one matrix product of the channels-last pixels ``(N H W, C_in)`` by the
    weight as it is stored (``F.linear``: the bias added in the call, the SiLU in place), its output
    channels last: on an answer's maps a oneDNN primitive, or torch's own 1x1 path, costs up to 40 us
    more per call.
    An eager convolution reorders its weight and its input at every call, which on the small maps
    of a streaming answer costs as much as the arithmetic (``benchmarks/packed_convolutions.py``).
    """

    def __init__(self, conv: nn.Conv2d, act: str = "none"):
        if act not in ("none", "swish"):
            raise ValueError(f"act must be 'none' or 'swish', got {act!r}")
        if not isinstance(conv.padding, tuple) or conv.padding_mode != "zeros":
            raise ValueError(f"a packed convolution needs numeric zero padding, got padding={conv.padding!r}, "
                             f"padding_mode={conv.padding_mode!r}")
        weight = conv.weight
        super().__init__(conv.in_channels, conv.out_channels, conv.kernel_size, conv.stride, conv.padding,
                         conv.dilation, conv.groups, bias=conv.bias is not None, device=weight.device,
                         dtype=weight.dtype)
        self.weight, self.bias = conv.weight, conv.bias
        self.act = act
        self._packed: dict[tuple[int, ...], torch.Tensor] = {}
        self.pointwise = (self.kernel_size == (1, 1) and self.stride == (1, 1) and self.padding == (0, 0)
                          and self.dilation == (1, 1) and self.groups == 1)

    def packs(self, x: torch.Tensor) -> bool:
        """Whether ``x`` takes the packed path."""
        return (x.dtype == torch.float32 and x.device.type == "cpu" and x.dim() == 4 and PACKED_AVAILABLE
                and not (torch.is_grad_enabled() and (x.requires_grad or self.weight.requires_grad)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.packs(x):
            y = F.conv2d(x, self.weight, self.bias, self.stride, self.padding, self.dilation, self.groups)
            return F.silu(y) if self.act == "swish" else y
        if self.pointwise:
            return self._pointwise(x)
        shape = tuple(x.shape)
        packed = self._packed.get(shape)
        if packed is None:
            packed = self._packed[shape] = torch._C._nn.mkldnn_reorder_conv2d_weight(
                self.weight.detach().to_mkldnn(), list(self.padding), list(self.stride), list(self.dilation),
                self.groups, list(shape))
        bias = None if self.bias is None else self.bias.detach()
        return torch.ops.mkldnn._convolution_pointwise(
            x.contiguous(memory_format=torch.channels_last), packed, bias, list(self.padding), list(self.stride),
            list(self.dilation), self.groups, self.act, [], "")

    def _pointwise(self, x: torch.Tensor) -> torch.Tensor:
        """The 1x1 convolution as ``(N H W, C_in) @ weight (C_out, C_in)^T + bias``, output channels last."""
        n, c, h, w = x.shape
        rows = x.permute(0, 2, 3, 1).reshape(n * h * w, c)  # a view of a channels-last input
        y = F.linear(rows, self.weight.reshape(self.out_channels, c), self.bias)
        if self.act == "swish":
            F.silu(y, inplace=True)
        return y.view(n, h, w, self.out_channels).permute(0, 3, 1, 2)

    def extra_repr(self) -> str:
        return super().extra_repr() + f", act={self.act}"


PACKED_AVAILABLE = torch.backends.mkldnn.is_available() and hasattr(torch.ops.mkldnn, "_convolution_pointwise")


def pack_convolutions(module: nn.Module, fuse_activations: bool = True) -> nn.Module:
    """``module`` with every ``nn.Conv2d`` made a :class:`PackedConv2d`, in place, and returned;
    with ``fuse_activations`` a SiLU that follows a convolution in an ``nn.Sequential`` (a
    :func:`conv_bn_act` block whose batch norm :func:`fold_batch_norms` folded) is applied by the
    convolution and replaced by ``nn.Identity``. Without it (a model whose head computes its
    blocks' rows by hand, :class:`~dagr_lite.nn.head.TowerCache`), every activation stays. For
    inference: the packed weights are a copy, made from the weights at the first call per shape."""
    if fuse_activations:
        for block in [m for m in module.modules() if isinstance(m, nn.Sequential)]:
            layers = list(block)
            for i, layer in enumerate(layers):
                if type(layer) is not nn.Conv2d:
                    continue
                after = next((j for j in range(i + 1, len(layers)) if not isinstance(layers[j], nn.Identity)), None)
                if after is not None and isinstance(layers[after], nn.SiLU):
                    block[i], block[after] = PackedConv2d(layer, "swish"), nn.Identity()
    for parent in list(module.modules()):
        for name, child in list(parent.named_children()):
            if type(child) is nn.Conv2d:
                setattr(parent, name, PackedConv2d(child))
    return module


class Residual(nn.Module):
    """``x + conv3x3(conv1x1(x))``, each a :func:`conv_bn_act`; shape-preserving."""

    def __init__(self, channels: int):
        super().__init__()
        self.body = nn.Sequential(conv_bn_act(channels, channels, k=1), conv_bn_act(channels, channels))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.body(x)
