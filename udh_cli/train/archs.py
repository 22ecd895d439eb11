"""Network architectures, created by name. Each maps two stacked patches to the 4-point offsets.

Every architecture takes ``(N, 2, S, S)`` standardised grey patches (channel 0 = A, channel 1 = B, S = the
patch size, 128) and returns ``(N, 4, 2)`` offsets in pixels of the S x S patch, in udh's convention:
``b_from_a`` maps corner i of A to ``corners[i] + offsets[i]`` (see :mod:`udh_cli.geometry`).
"""

from __future__ import annotations

from functools import partial
from typing import Callable

import torch
from torch import nn
import torch.nn.functional as F

OFFSET_SCALE = 32.0  # the heads predict offsets / 32 px, so initial outputs sit in a sensible range


def _conv(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class PaperVGG(nn.Module):
    """The paper's network (DeTone et al.'s HomographyNet): 8 conv3x3+BN+ReLU layers with
    64,64,64,64,128,128,128,128 channels, max-pooling after each of the first three pairs, dropout,
    FC 1024 and FC 8. About 34 M parameters at 128x128."""

    def __init__(self, patch_size: int = 128, dropout: float = 0.5):
        super().__init__()
        widths = [64, 64, 64, 64, 128, 128, 128, 128]
        layers: list[nn.Module] = []
        cin = 2
        for i, cout in enumerate(widths):
            layers.append(_conv(cin, cout))
            if i in (1, 3, 5):
                layers.append(nn.MaxPool2d(2))
            cin = cout
        self.features = nn.Sequential(*layers)
        side = patch_size // 8
        self.head = nn.Sequential(
            nn.Flatten(), nn.Dropout(dropout), nn.Linear(128 * side * side, 1024), nn.ReLU(inplace=True),
            nn.Dropout(dropout), nn.Linear(1024, 8),
        )

    def forward(self, patches: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(patches)).view(-1, 4, 2) * OFFSET_SCALE


class CorrelationNet(nn.Module):
    """udh's CPU-friendly default: a Siamese encoder, a local correlation (cost) volume, a small regressor.

    Why: a plain regressor must discover from scratch that it is comparing two images; a cost volume gives
    it the displacement evidence directly, which is what makes it learn far more per CPU-second.

    Three settings of the same network:

    - ``corr`` (``fine=False``, radius 4): the patches are average-pooled to half resolution, the encoder
      reaches 1/8 of the patch (16x16 cells of 8 px at 128) and compares shifts up to 32 px (the regressor
      extrapolates beyond). The coarse stage: large motion, a few px of precision.
    - ``corr-lite``: ``corr`` with a slimmer encoder (16, 24, 32, 32 channels) and a 1x1 first regressor
      layer over the volume. Those two layers were 0.8 ms of corr's 2 ms batch-1 pass on one core; the
      lite network takes about 0.7 ms.
    - ``corr-fine`` (``fine=True``, radius 3, width 32): full resolution with a stride-2 first layer (a
      3x3 conv at 128x128 cost more than everything else), 32x32 cells of 4 px, shifts up to 12 px. A
      refinement stage, run on A pre-warped by the coarse stage, for the residual motion; about 3x the
      training compute of ``corr``.

    The regressor pools the (2r+1)^2-channel volume down to 1/32 of the patch (4x4 cells at 128), so each
    corner's evidence stays apart for the head, which turns it into 8 numbers.

    Args:
        patch_size: input side S, a multiple of 32. radius: largest compared shift, in cells.
        encoder_widths: channels of the encoder's four conv layers.
        regressor_widths: channels of the regressor's conv layers; the first one sees the volume, every
            later one follows a 2x max-pool (one more 128-channel layer is added while cells remain).
        volume_kernel: kernel side of the first regressor layer (3, or 1 for speed).
        fine: full-resolution input with a stride-2 first layer, 4-px cells (see corr-fine).
    """

    def __init__(self, patch_size: int = 128, radius: int = 4, encoder_widths: tuple[int, ...] = (16, 32, 64, 64),
                 regressor_widths: tuple[int, ...] = (64, 128, 128), volume_kernel: int = 3, fine: bool = False):
        super().__init__()
        self.radius = radius
        self.fine = fine
        e1, e2, e3, e4 = encoder_widths
        self.encoder = nn.Sequential(
            _conv(1, e1, stride=2 if fine else 1), nn.Identity() if fine else nn.MaxPool2d(2),
            _conv(e1, e2), nn.MaxPool2d(2), _conv(e2, e3), _conv(e3, e4),
        )
        shifts = (2 * radius + 1) ** 2
        cells = patch_size // (4 if fine else 8)
        first = regressor_widths[0]
        regressor: list[nn.Module] = [nn.Sequential(nn.Conv2d(shifts, first, volume_kernel, padding=volume_kernel // 2, bias=False),
                                                    nn.BatchNorm2d(first), nn.ReLU(inplace=True))]
        channels, later = first, list(regressor_widths[1:])
        while cells > patch_size // 32:  # 4x4 cells at 128
            out = later.pop(0) if later else 128
            regressor += [nn.MaxPool2d(2), _conv(channels, out)]
            channels, cells = out, cells // 2
        self.regressor = nn.Sequential(*regressor)
        self.head = nn.Sequential(nn.Flatten(), nn.Linear(channels * cells * cells, 256), nn.ReLU(inplace=True), nn.Linear(256, 8))
        # Fixed for the patch size, so they are buffers: the exported graph holds them as constants instead
        # of recomputing them with a dozen small ops per call (about a tenth of a batch-1 pass).
        feature_side = patch_size // (4 if fine else 8)
        index, inside = self._window_index(feature_side, feature_side)
        self.register_buffer("window_index", index, persistent=False)
        self.register_buffer("window_inside", inside, persistent=False)

    def _window_index(self, h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
        """For every A cell and shift: the flat index of the B cell, and whether it lies inside."""
        r = self.radius
        ys, xs = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
        dy, dx = torch.meshgrid(torch.arange(-r, r + 1), torch.arange(-r, r + 1), indexing="ij")
        qy = ys.reshape(-1, 1) + dy.reshape(1, -1)  # h*w, k*k
        qx = xs.reshape(-1, 1) + dx.reshape(1, -1)
        inside = ((qy >= 0) & (qy < h) & (qx >= 0) & (qx < w)).float()
        return qy.clamp(0, h - 1) * w + qx.clamp(0, w - 1), inside

    def correlation(self, feat_a: torch.Tensor, feat_b: torch.Tensor) -> torch.Tensor:
        """(N, C, h, w) x2 -> (N, (2r+1)^2, h, w): cosine similarity of each A cell with shifted B cells.

        All-pairs similarity is one batched matmul, then each cell's window is gathered from it. This
        was 30x faster to train on the CPU than unfold, and 300x faster than a loop of slices.
        """
        n, c, h, w = feat_a.shape
        index, inside = self.window_index, self.window_inside  # the head's size fixes h and w anyway
        all_pairs = torch.bmm(feat_a.flatten(2).transpose(1, 2), feat_b.flatten(2))  # N, hw, hw
        local = all_pairs.gather(2, index.unsqueeze(0).expand(n, -1, -1)) * inside  # N, hw, k*k
        return local.transpose(1, 2).reshape(n, -1, h, w)

    def forward(self, patches: torch.Tensor) -> torch.Tensor:
        n = patches.shape[0]
        pooled = patches if self.fine else F.avg_pool2d(patches, 2)
        both = torch.cat([pooled[:, 0:1], pooled[:, 1:2]], 0)  # 2N images: one pass, shared weights
        features = F.normalize(self.encoder(both), dim=1)
        volume = self.correlation(features[:n], features[n:])
        return self.head(self.regressor(volume)).view(-1, 4, 2) * OFFSET_SCALE


ARCHS: dict[str, Callable[..., nn.Module]] = {
    "corr": CorrelationNet,
    "corr-lite": partial(CorrelationNet, encoder_widths=(16, 24, 32, 32), regressor_widths=(64, 96, 128), volume_kernel=1),
    "corr-fine": partial(CorrelationNet, fine=True, radius=3, encoder_widths=(16, 32, 32, 32), regressor_widths=(64, 128, 128, 128)),
    "vgg-paper": PaperVGG,
}
DEFAULT_ARCH = "corr"


def create_model(arch: str, patch_size: int = 128) -> nn.Module:
    """Build the architecture registered as ``arch`` for ``patch_size`` x ``patch_size`` patches."""
    from udh_cli.errors import UdhError

    if arch not in ARCHS:
        raise UdhError(f"unknown architecture '{arch}'; choose one of: {', '.join(ARCHS)}")
    if patch_size % 32:
        raise UdhError(f"patch size {patch_size} must be a multiple of 32")
    return ARCHS[arch](patch_size=patch_size)
