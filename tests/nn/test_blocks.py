import copy

import pytest
import torch
from torch import nn

from dagr_lite.nn.blocks import Residual, conv_bn_act, fold_batch_norms
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
