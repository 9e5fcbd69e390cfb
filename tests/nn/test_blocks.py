import copy

import pytest
import torch
from torch import nn

from dagr_lite.nn.blocks import (PACKED_AVAILABLE, PackedConv2d, Residual, conv_bn_act,
                                 fold_batch_norms, pack_convolutions)
from dagr_lite.nn.head import block_rows, conv_rows, norm_act_rows


def with_random_statistics(module: nn.Module, seed: int = 0) -> nn.Module:
    """``module`` in float64, evaluation mode, each batch norm given random statistics and affine weights
    (a fresh one's are the identity map, which folding would leave unchecked)."""
    generator = torch.Generator().manual_seed(seed)
    module = module.double().eval()
    for bn in (m for m in module.modules() if isinstance(m, nn.BatchNorm2d)):
        c = bn.num_features
        bn.running_mean.copy_(torch.randn(c, generator=generator, dtype=torch.float64))
        bn.running_var.copy_(torch.rand(c, generator=generator, dtype=torch.float64) * 2 + 0.1)
        bn.weight.data.copy_(torch.randn(c, generator=generator, dtype=torch.float64))
        bn.bias.data.copy_(torch.randn(c, generator=generator, dtype=torch.float64))
    return module


def test_folded_batch_norms_answer_as_the_blocks_they_replace():
    blocks = with_random_statistics(nn.Sequential(conv_bn_act(3, 8, stride=4, k=4), Residual(8),
                                                  conv_bn_act(8, 16, stride=2), conv_bn_act(16, 4, k=1)))
    folded = fold_batch_norms(copy.deepcopy(blocks))
    assert not any(isinstance(m, nn.BatchNorm2d) for m in folded.modules())
    assert sum(isinstance(m, nn.Identity) for m in folded.modules()) == 5  # every block's batch norm
    x = torch.randn(2, 3, 24, 40, dtype=torch.float64)
    with torch.no_grad():
        expected, got = blocks(x), folded(x)
    assert got.shape == expected.shape == (2, 4, 3, 5)
    torch.testing.assert_close(got, expected, rtol=1e-12, atol=1e-12)


def test_folding_keeps_a_convolutions_layout_and_dtype():
    block = with_random_statistics(conv_bn_act(8, 8)).float()
    block[0].weight.data = block[0].weight.data.contiguous(memory_format=torch.channels_last)
    plain = with_random_statistics(conv_bn_act(8, 8)).float()
    fold_batch_norms(block), fold_batch_norms(plain)
    assert block[0].weight.is_contiguous(memory_format=torch.channels_last) and not block[0].weight.is_contiguous()
    assert plain[0].weight.is_contiguous()
    assert block[0].weight.dtype == block[0].bias.dtype == torch.float32


def test_rows_of_a_folded_block_equal_the_unfolded_blocks():
    """The tower cache's row form (a 1x1 block on rows; a block's norm and activation after its
    convolution's product) reads a folded block's bias."""
    block = with_random_statistics(conv_bn_act(6, 5, k=1), seed=1)
    folded = fold_batch_norms(copy.deepcopy(block))
    rows = torch.randn(7, 6, dtype=torch.float64)
    torch.testing.assert_close(block_rows(folded, rows), block_rows(block, rows), rtol=1e-12, atol=1e-12)
    y = rows @ conv_rows(folded[0]).T
    by_hand = nn.functional.silu(y + folded[0].bias)
    torch.testing.assert_close(norm_act_rows(folded, y), by_hand, rtol=0, atol=0)


def test_folding_refuses_a_module_in_training_mode():
    with pytest.raises(ValueError, match="eval"):
        fold_batch_norms(conv_bn_act(3, 4).train())


@pytest.mark.skipif(not PACKED_AVAILABLE, reason="this torch has no oneDNN convolution with fused activations")
@pytest.mark.parametrize(("c_in", "c_out", "k", "stride", "size", "act", "bias"), [
    (3, 8, 4, 4, (24, 40), "swish", True),     # a patch stem
    (8, 16, 3, 1, (23, 40), "swish", True),
    (16, 16, 3, 2, (23, 40), "none", False),   # odd map, stride 2, no bias
    (64, 4, 1, 1, (23, 40), "none", True),     # a 1x1: one matrix product
    (64, 1, 1, 1, (12, 20), "none", True),     # a small 1x1
    (16, 32, 1, 1, (45, 80), "swish", False),  # a 1x1 with its SiLU, no bias
    (8, 8, 1, 2, (23, 40), "swish", True),     # a 1x1 of stride 2: oneDNN's
])
def test_a_packed_convolution_answers_as_the_convolution_and_activation_it_replaces(c_in, c_out, k, stride, size,
                                                                                    act, bias):
    torch.manual_seed(0)
    conv = nn.Conv2d(c_in, c_out, k, stride, k // 2 if k % 2 else 0, bias=bias).eval()
    packed = PackedConv2d(conv, act)
    assert packed.weight is conv.weight and packed.bias is conv.bias  # the same parameters
    x = torch.randn(1, c_in, *size)  # batch 1, as a streaming answer
    with torch.inference_mode():
        expected = conv(x)
        expected = nn.functional.silu(expected) if act == "swish" else expected
        for layout in (torch.contiguous_format, torch.channels_last):
            got = packed(x.contiguous(memory_format=layout))
            assert got.shape == expected.shape
            torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-5)
        assert packed.packs(x)
        assert packed.pointwise == (k == 1 and stride == 1)
        assert len(packed._packed) == int(not packed.pointwise)  # one weight layout for the one input shape
        if packed.pointwise:
            assert got.is_contiguous(memory_format=torch.channels_last)  # the product's rows are the pixels
            with torch.no_grad():
                conv.weight.mul_(2)  # the product reads the weight as it is now
            torch.testing.assert_close(packed(x), conv(x) if act == "none" else nn.functional.silu(conv(x)),
                                       rtol=1e-5, atol=1e-5)
    assert not packed.packs(x)  # outside inference, with weights that take gradients: torch's own


def test_a_packed_convolution_keeps_torchs_own_path_for_float64_and_gradients():
    conv = nn.Conv2d(4, 6, 3, padding=1).double()
    packed = PackedConv2d(conv, "swish")
    x = torch.randn(1, 4, 30, 30, dtype=torch.float64)
    assert not packed.packs(x)
    torch.testing.assert_close(packed(x), nn.functional.silu(conv(x)), rtol=0, atol=0)  # the very same operations
    conv32 = nn.Conv2d(4, 6, 3, padding=1)
    packed32 = PackedConv2d(conv32)
    x32 = torch.randn(1, 4, 30, 30, requires_grad=True)
    assert not packed32.packs(x32)  # training: autograd needs torch's own convolution
    packed32(x32).sum().backward()
    assert x32.grad is not None and conv32.weight.grad is not None
    with pytest.raises(ValueError, match="act must be"):
        PackedConv2d(conv32, "relu")


def test_packing_a_folded_model_fuses_its_activations_and_answers_as_before():
    blocks = with_random_statistics(nn.Sequential(conv_bn_act(3, 8, stride=4, k=4), Residual(8),
                                                  conv_bn_act(8, 16, stride=2), conv_bn_act(16, 4, k=1),
                                                  nn.Conv2d(4, 2, 1))).float()
    folded = fold_batch_norms(copy.deepcopy(blocks))
    packed = pack_convolutions(copy.deepcopy(folded))
    convs = [m for m in packed.modules() if isinstance(m, nn.Conv2d)]
    assert len(convs) == 6 and all(isinstance(m, PackedConv2d) for m in convs)
    assert [m.act for m in convs] == ["swish"] * 5 + ["none"]  # every block's SiLU; the last has none
    assert not any(isinstance(m, nn.SiLU) for m in packed.modules())
    x = torch.randn(2, 3, 96, 160)
    with torch.inference_mode():
        torch.testing.assert_close(packed(x), blocks(x), rtol=1e-5, atol=1e-5)
    kept = pack_convolutions(copy.deepcopy(folded), fuse_activations=False)
    assert sum(isinstance(m, nn.SiLU) for m in kept.modules()) == 5  # the tower cache's rows apply them by hand
    assert all(m.act == "none" for m in kept.modules() if isinstance(m, PackedConv2d))
    with torch.inference_mode():
        torch.testing.assert_close(kept(x), blocks(x), rtol=1e-5, atol=1e-5)
    double = pack_convolutions(fold_batch_norms(copy.deepcopy(blocks).double()))
    with torch.no_grad():  # float64 takes torch's own path: the folded model's answer to the bit
        torch.testing.assert_close(double(x.double()), fold_batch_norms(copy.deepcopy(blocks).double())(x.double()),
                                   rtol=0, atol=0)
