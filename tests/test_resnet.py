"""occkit's ResNet is torchvision's: for every depth, the same seed draws the same parameters under the same names,
leaves the generator in the same state, and gives the same outputs in training and in evaluation mode (that no module
imports torchvision at its top level: tests/test_layers.py)."""

from __future__ import annotations

import pytest
import torch
import torchvision

from occkit.models.resnet import DEPTHS, BasicBlock, resnet


@pytest.mark.parametrize("depth", sorted(DEPTHS))
def test_a_seed_gives_torchvisions_resnet(depth):
    torch.manual_seed(0)
    ours = resnet(depth)
    after_ours = torch.rand(4)
    torch.manual_seed(0)
    reference = getattr(torchvision.models, f"resnet{depth}")(weights=None)
    after_reference = torch.rand(4)
    assert torch.equal(after_ours, after_reference), "the generator was left in another state"
    ours_state, reference_state = ours.state_dict(), reference.state_dict()
    assert list(ours_state) == list(reference_state)
    for key, value in reference_state.items():
        assert torch.equal(ours_state[key], value), key
    images = torch.randn(2, 3, 64, 96, generator=torch.Generator().manual_seed(1))
    for mode in (True, False):
        ours.train(mode), reference.train(mode)
        assert torch.equal(ours(images), reference(images)), f"outputs differ in {'training' if mode else 'eval'} mode"


def test_a_block_with_a_given_shortcut_is_torchvisions():
    torch.manual_seed(0)
    ours = BasicBlock(8, 16, stride=2, downsample=torch.nn.Conv2d(8, 16, 3, 2, 1))
    torch.manual_seed(0)
    reference = torchvision.models.resnet.BasicBlock(8, 16, stride=2, downsample=torch.nn.Conv2d(8, 16, 3, 2, 1))
    x = torch.randn(1, 8, 20, 20)
    assert torch.equal(ours(x), reference(x))

