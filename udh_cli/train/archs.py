"""Network architectures, created by name. Each maps two stacked patches to the 4-point offsets.

Every architecture takes ``(N, 2, S, S)`` standardised grey patches (channel 0 = A, channel 1 = B, S = the
patch size, 128) and returns ``(N, 4, 2)`` offsets in pixels of the S x S patch, in udh's convention:
``b_from_a`` maps corner i of A to ``corners[i] + offsets[i]`` (see :mod:`udh_cli.geometry`).
"""

from __future__ import annotations

import math
from functools import partial
from typing import Callable

import torch
from torch import nn
import torch.nn.functional as F


OFFSET_SCALE = 32.0  # the heads predict offsets / 32 px, so initial outputs sit in a sensible range
GLOBAL_CHANNELS = 3  # corr-global's extra volume channels: displacement x, y and the best match's weight


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
    - ``corr-global`` (``global_match=True``): ``corr`` plus three channels from a global correlation
      (:meth:`global_matches`), so that motion beyond the local window (turns, climbs, low overlap) has
      direct evidence. The first regressor layer is the only one whose shape differs from ``corr``'s, so a
      ``corr`` network initialises it exactly (:func:`widen_from`).
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
        global_match: add the global-correlation channels (see ``corr-global``).
    """

    def __init__(self, patch_size: int = 128, radius: int = 4, encoder_widths: tuple[int, ...] = (16, 32, 64, 64),
                 regressor_widths: tuple[int, ...] = (64, 128, 128), volume_kernel: int = 3, fine: bool = False,
                 global_match: bool = False):
        super().__init__()
        self.radius = radius
        self.fine = fine
        self.global_match = global_match
        e1, e2, e3, e4 = encoder_widths
        self.encoder = nn.Sequential(
            _conv(1, e1, stride=2 if fine else 1), nn.Identity() if fine else nn.MaxPool2d(2),
            _conv(e1, e2), nn.MaxPool2d(2), _conv(e2, e3), _conv(e3, e4),
        )
        shifts = (2 * radius + 1) ** 2 + (GLOBAL_CHANNELS if global_match else 0)
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
        if global_match:
            ys, xs = torch.meshgrid(torch.arange(feature_side), torch.arange(feature_side), indexing="ij")
            cells_xy = torch.stack([xs.flatten(), ys.flatten()], -1).float() / feature_side  # hw, 2 in [0, 1)
            self.register_buffer("cell_positions", cells_xy, persistent=False)
            # Softmax sharpness over cosine similarities; learnt, starting where one clear peak dominates.
            self.log_match_sharpness = nn.Parameter(torch.tensor(math.log(20.0)))

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
        all_pairs = torch.bmm(feat_a.flatten(2).transpose(1, 2), feat_b.flatten(2))  # N, hw, hw
        return self.local_volume(all_pairs, h, w)

    def local_volume(self, all_pairs: torch.Tensor, h: int, w: int) -> torch.Tensor:
        """(N, hw, hw) all-pairs similarities -> (N, (2r+1)^2, h, w): each A cell's window of shifts."""
        n = all_pairs.shape[0]
        index, inside = self.window_index, self.window_inside  # the head's size fixes h and w anyway
        local = all_pairs.gather(2, index.unsqueeze(0).expand(n, -1, -1)) * inside  # N, hw, k*k
        return local.transpose(1, 2).reshape(n, -1, h, w)

    def global_matches(self, all_pairs: torch.Tensor, h: int, w: int) -> torch.Tensor:
        """(N, hw_A, hw_B) similarities -> (N, 3, h, w): each A cell's expected B position minus its own
        (soft-argmax over every B cell, in patch widths) and the weight of its best match.

        Why: the local window sees shifts up to ``radius`` cells (32 px at 128); a turn or a climb moves
        corners by a whole patch. The soft-argmax over all cells reaches anywhere in B (IHN/RAFT's global
        correlation), at the cost of one softmax over the similarities the local volume already computed.
        """
        n = all_pairs.shape[0]
        weights = torch.softmax(all_pairs * self.log_match_sharpness.exp(), dim=2)  # N, hw, hw
        expected = weights @ self.cell_positions  # N, hw, 2
        displacement = expected - self.cell_positions
        peak = weights.amax(dim=2, keepdim=True)
        return torch.cat([displacement, peak], 2).transpose(1, 2).reshape(n, GLOBAL_CHANNELS, h, w)

    def forward(self, patches: torch.Tensor) -> torch.Tensor:
        n = patches.shape[0]
        pooled = patches if self.fine else F.avg_pool2d(patches, 2)
        both = torch.cat([pooled[:, 0:1], pooled[:, 1:2]], 0)  # 2N images: one pass, shared weights
        features = F.normalize(self.encoder(both), dim=1)
        feat_a, feat_b = features[:n], features[n:]
        _, c, h, w = feat_a.shape
        all_pairs = torch.bmm(feat_a.flatten(2).transpose(1, 2), feat_b.flatten(2))  # N, hw, hw
        volume = self.local_volume(all_pairs, h, w)
        if self.global_match:
            volume = torch.cat([volume, self.global_matches(all_pairs, h, w)], 1)
        return self.head(self.regressor(volume)).view(-1, 4, 2) * OFFSET_SCALE


class DenseMatcher(nn.Module):
    """``matcher``: dense descriptors for global matching, the learned pipeline's answer to large motion.

    The regressing networks see a whole frame squashed to 128x128 and predict 8 numbers; on real flights
    with low overlap or little texture at that scale (brighton-beach's trees and lawns) their first answer
    is 10-25 px off at 128 px, beyond what the tiles can pull in. This network instead describes every
    4-px cell of a frame kept at its aspect (a few hundred px wide), and the estimator matches every cell
    of A against every cell of B (mutual nearest neighbours, a robust fit): IHN/RAFT's global correlation
    taken to its end, which reaches any displacement inside the frame. Features are per frame, so a mosaic
    computes them once for every pair a frame is in.

    Layout: ``corr``'s encoder (same layer names, so a trained ``corr`` initialises it; 1/4 resolution,
    receptive field 26 px), then a residual context block of two dilated convolutions (dilation 2 and 4,
    receptive field about 74 px) whose last batch norm starts at zero, so the block starts as the identity.

    ``forward`` takes ``(N, 2, H, W)`` standardised grey pairs and returns ``(N, 2, C, H/4, W/4)`` unit
    descriptors; :meth:`describe` does one ``(M, 1, H, W)`` stack of images. ``log_temperature`` scales the
    cosine similarities into the matching loss's logits (learnt).
    """

    def __init__(self, encoder_widths: tuple[int, ...] = (16, 32, 64, 64)):
        super().__init__()
        e1, e2, e3, e4 = encoder_widths
        self.encoder = nn.Sequential(_conv(1, e1), nn.MaxPool2d(2), _conv(e1, e2), nn.MaxPool2d(2), _conv(e2, e3), _conv(e3, e4))
        self.context = nn.Sequential(
            nn.Conv2d(e4, e4, 3, padding=2, dilation=2, bias=False), nn.BatchNorm2d(e4), nn.ReLU(inplace=True),
            nn.Conv2d(e4, e4, 3, padding=4, dilation=4, bias=False), nn.BatchNorm2d(e4),
        )
        nn.init.zeros_(self.context[-1].weight)
        self.log_temperature = nn.Parameter(torch.tensor(math.log(20.0)))

    def describe(self, images: torch.Tensor) -> torch.Tensor:
        """(M, 1, H, W) standardised grey -> (M, C, H/4, W/4) unit descriptors."""
        features = self.encoder(images)
        return F.normalize(features + self.context(features), dim=1)

    def forward(self, patches: torch.Tensor) -> torch.Tensor:
        n = patches.shape[0]
        both = self.describe(torch.cat([patches[:, 0:1], patches[:, 1:2]], 0))
        return torch.stack([both[:n], both[n:]], 1)


ARCHS: dict[str, Callable[..., nn.Module]] = {
    "corr": CorrelationNet,
    "corr-lite": partial(CorrelationNet, encoder_widths=(16, 24, 32, 32), regressor_widths=(64, 96, 128), volume_kernel=1),
    "corr-global": partial(CorrelationNet, global_match=True),
    "corr-fine": partial(CorrelationNet, fine=True, radius=3, encoder_widths=(16, 32, 32, 32), regressor_widths=(64, 128, 128, 128)),
    "vgg-paper": PaperVGG,
    "matcher": DenseMatcher,
}
MATCHERS = {"matcher"}  # architectures that describe cells for matching (``udh train --mode match``), not regress offsets


def widen_from(model: nn.Module, state: dict[str, torch.Tensor]) -> list[str]:
    """Load ``state`` into ``model`` where a tensor is wider in ``model`` along input channels only.

    Such tensors get the old weights in their first channels and zeros in the new ones, so the widened
    network computes exactly what the old one did until training teaches it to use the new inputs.
    Returns the names of the widened tensors. Used to start ``corr-global`` from a trained ``corr``.
    """
    own = model.state_dict()
    widened = []
    merged = dict(own)
    for name, tensor in state.items():
        if name not in own:
            raise KeyError(f"unexpected weight '{name}'")
        target = own[name]
        if target.shape == tensor.shape:
            merged[name] = tensor
        elif target.dim() == tensor.dim() and target.dim() > 1 and target.shape[0] == tensor.shape[0] and target.shape[2:] == tensor.shape[2:] \
                and target.shape[1] > tensor.shape[1]:
            grown = torch.zeros_like(target)
            grown[:, : tensor.shape[1]] = tensor
            merged[name] = grown
            widened.append(name)
        else:
            raise KeyError(f"weight '{name}' has shape {tuple(tensor.shape)}, the network wants {tuple(target.shape)}")
    model.load_state_dict(merged)
    return widened


def create_model(arch: str, patch_size: int = 128) -> nn.Module:
    """Build the architecture registered as ``arch`` for ``patch_size`` x ``patch_size`` patches."""
    from udh_cli.errors import UdhError

    if arch not in ARCHS:
        raise UdhError(f"unknown architecture '{arch}'; choose one of: {', '.join(ARCHS)}")
    if patch_size % 32:
        raise UdhError(f"patch size {patch_size} must be a multiple of 32")
    if arch in MATCHERS:
        return ARCHS[arch]()
    return ARCHS[arch](patch_size=patch_size)
