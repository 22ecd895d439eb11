"""The training objectives: the paper's unsupervised photometric loss, HomographyNet's L2 loss, and the dense
matching loss of the ``matcher`` descriptors."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from udh_cli import geometry
from udh_cli.estimators import matching
from udh_cli.estimators.matching import MATCH_CELL
from udh_cli.train.config import PHOTOMETRIC_SPACES


def _shift(origin: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) translations by ``origin`` (N, 2) pixels."""
    shift = torch.eye(3, dtype=like.dtype, device=like.device).repeat(len(origin), 1, 1)
    shift[:, :2, 2] = origin.to(like.dtype)
    return shift


def warp_context(offsets: torch.Tensor, context_a: torch.Tensor, origin: torch.Tensor, patch_size: int, scale: int = 1) -> torch.Tensor:
    """Render A in B's patch frame with the predicted homography: the spatial-transformer layer.

    Args:
        offsets: (N, 4, 2) predicted 4-point offsets, pixels of the patch (``b_from_a``).
        context_a: (N, C, H, W) A's full frame (and any extra channels, e.g. a validity mask).
        origin: (N, 2) where the patch's top-left pixel sits in ``context_a``, pixels (x, y).
        patch_size: P.
        scale: render at 1/scale resolution from a box-downsampled context (``avg_pool2d`` with stride
            ``scale`` keeps pixel centres where the resize convention of :mod:`udh_cli.geometry` puts them).

    Returns:
        (N, C, P/scale, P/scale): ``context_a`` sampled at ``a_from_b(y) + origin`` for every pixel ``y`` of B.
    """
    corners = geometry.image_corners(patch_size, patch_size, like=offsets)
    # Tensor DLT with the correspondences swapped gives a_from_b directly, without inverting a matrix.
    a_from_b = geometry.homography_from_points(corners + offsets, corners.expand_as(offsets))  # N, 3, 3
    context_from_b = _shift(origin, a_from_b) @ a_from_b
    height, width = context_a.shape[-2:]
    size_b, size_context = (patch_size, patch_size), (width, height)
    if scale > 1:
        context_a = F.avg_pool2d(context_a, scale)
        small_b = (patch_size // scale, patch_size // scale)
        small_context = (context_a.shape[-1], context_a.shape[-2])
        to_small_context = torch.as_tensor(geometry.resize_matrix(size_context, small_context), dtype=offsets.dtype, device=offsets.device)
        from_small_b = torch.as_tensor(np.linalg.inv(geometry.resize_matrix(size_b, small_b)), dtype=offsets.dtype, device=offsets.device)
        context_from_b = to_small_context @ context_from_b @ from_small_b
        size_b, size_context = small_b, small_context
    grid = geometry.sampling_grid(context_from_b, size_context, size_b)  # N, h_b, w_b, 2
    return F.grid_sample(context_a, grid.to(context_a.dtype), mode="bilinear", padding_mode="zeros", align_corners=False)


PHOTOMETRIC_SCALES = (1, 2, 4, 8)
# px of the 128-px patch: wide enough to keep the structure that gives the loss a wide basin, narrow enough to
# remove vignetting and hot spots. A 9-px window left only fine detail: fine-tuning the flight network with it
# took its validation error from 30.7 to 64.7 px in 1,500 steps (docs/training.md).
CONTRAST_WINDOW = 31
CONTRAST_FLOOR = 0.01  # grey units ([0, 1]); as images.local_contrast: flat regions are not amplified into texture


def local_contrast(image: torch.Tensor, valid: torch.Tensor, window: int = CONTRAST_WINDOW,
                   floor: float = CONTRAST_FLOOR) -> torch.Tensor:
    """(N, 1, H, W) grey in [0, 1] -> (N, 1, H, W) with zero local mean and unit local deviation.

    The torch twin of :func:`udh_cli.images.local_contrast` for the training loss, with a ``window`` x
    ``window`` box instead of a Gaussian and statistics over the ``valid`` (N, 1, H, W) pixels only, so that
    the black surround of a flight-motion canvas does not become an edge. Invalid pixels come out 0.
    The deviation is ``sqrt(var + floor^2)``: smooth, and it caps the gain in flat regions.
    """
    pad = window // 2

    def box(x: torch.Tensor) -> torch.Tensor:  # separable: 2 * window operations a pixel instead of window^2
        x = F.avg_pool2d(x, (window, 1), stride=1, padding=(pad, 0), count_include_pad=True)
        return F.avg_pool2d(x, (1, window), stride=1, padding=(0, pad), count_include_pad=True)

    weight = box(valid).clamp_min(1e-6)
    mean = box(image * valid) / weight
    variance = (box(image * image * valid) / weight - mean * mean).clamp_min(0.0)
    return (image - mean) * valid / torch.sqrt(variance + floor * floor)


def photometric_loss(offsets: torch.Tensor, context_a: torch.Tensor, origin: torch.Tensor, clean_b: torch.Tensor,
                     scales: tuple[int, ...] = PHOTOMETRIC_SCALES, space: str = "intensity") -> torch.Tensor:
    """The paper's unsupervised loss, over a pyramid: mean L1 between warped A and B over valid pixels.

    ``context_a`` is (N, 2, H, W): the image in A's frame and its validity mask (1 where real pixels).
    ``clean_b`` is (N, P, P). Pixels whose sample falls outside A's real pixels do not count.
    The paper uses full resolution only (``scales=(1,)``). The coarser levels widen the basin of the
    L1 error, so large displacements get a useful gradient from the first step; level 1 keeps it precise.

    ``space`` "intensity" compares grey values (the paper's); "contrast" compares both images' local
    contrast (:func:`local_contrast`), which ignores what varies slowly across a frame and does not move
    with the ground: vignetting, a lens hot spot, sun glint, exposure. On low-texture frames those
    dominate the intensity L1 and pull the answer towards the identity.
    """
    if space not in PHOTOMETRIC_SPACES:
        raise ValueError(f"photometric space {space!r}: use one of {', '.join(PHOTOMETRIC_SPACES)}")
    if space == "contrast":
        mask = context_a[:, 1:2]
        context_a = torch.cat([local_contrast(context_a[:, :1], mask), mask], 1)
        clean_b = local_contrast(clean_b[:, None], torch.ones_like(clean_b[:, None]))[:, 0]
    total = clean_b.new_zeros(())
    for scale in scales:
        warped = warp_context(offsets, context_a, origin, clean_b.shape[-1], scale)
        target = clean_b if scale == 1 else F.avg_pool2d(clean_b[:, None], scale)[:, 0]
        valid = (warped[:, 1] > 0.999).to(clean_b.dtype).detach()
        error = (warped[:, 0] - target).abs() * valid
        total = total + error.sum() / valid.sum().clamp_min(1.0)
    return total / len(scales)


def supervised_loss(offsets: torch.Tensor, true_offsets: torch.Tensor) -> torch.Tensor:
    """HomographyNet's loss: ``0.5 * ||H_4pt - H*_4pt||^2`` over the 8 numbers, averaged over the batch."""
    return 0.5 * ((offsets - true_offsets) ** 2).sum(dim=(1, 2)).mean()


def distillation_loss(offsets: torch.Tensor, teacher_offsets: torch.Tensor) -> torch.Tensor:
    """Mean absolute difference, in pixels, between (N, 4, 2) offsets and a teacher's on the same inputs.

    L1 rather than L2: where the teacher is wrong by tens of pixels (its own failures), the student should
    not be pulled hard towards it; the photometric term beside it decides those pairs.
    """
    return (offsets - teacher_offsets).abs().mean()


def corner_error(offsets: torch.Tensor, true_offsets: torch.Tensor) -> torch.Tensor:
    """(N,) mean corner distance in pixels; for a shared set of corners this is exactly MACE."""
    return (offsets - true_offsets).pow(2).sum(-1).sqrt().mean(-1)


def cell_centres(height: int, width: int, like: torch.Tensor) -> torch.Tensor:
    """(h * w, 2) centres (x, y) of a descriptor cell grid in input pixels, as :func:`udh_cli.estimators.matching.cell_centres`."""
    return torch.as_tensor(matching.cell_centres(height, width), dtype=like.dtype, device=like.device)


def _match_direction(from_features: torch.Tensor, to_features: torch.Tensor, to_from: torch.Tensor, scale: torch.Tensor,
                     samples: int, generator: torch.Generator | None) -> tuple[torch.Tensor, torch.Tensor]:
    """Cross-entropy of ``samples`` random cells of one view against every cell of the other: (sum, count)."""
    n, c, h, w = from_features.shape
    centres = cell_centres(h, w, to_from)
    mapped = geometry.transform_points(to_from, centres.expand(n, -1, -1))  # N, hw, 2 in the other view's pixels
    finite = torch.isfinite(mapped).all(-1)
    # Cell j spans pixels [4j - 0.5, 4j + 3.5) in the pixel-centre convention.
    cell = torch.floor((torch.nan_to_num(mapped, nan=-1.0, posinf=-1.0, neginf=-1.0) + 0.5) / MATCH_CELL)
    inside = (cell[..., 0] >= 0) & (cell[..., 0] < w) & (cell[..., 1] >= 0) & (cell[..., 1] < h) & finite
    target = (cell[..., 1].clamp(0, h - 1) * w + cell[..., 0].clamp(0, w - 1)).long()
    # Only cells with a counterpart take part; a random subset of them keeps the logits (samples x hw) small.
    weights = inside.to(from_features.dtype) + 1e-6
    chosen = torch.multinomial(weights, samples, replacement=True, generator=generator)  # N, samples
    valid = inside.gather(1, chosen).to(from_features.dtype)
    queries = from_features.flatten(2).transpose(1, 2).gather(1, chosen.unsqueeze(-1).expand(-1, -1, c))  # N, samples, C
    logits = scale * torch.bmm(queries, to_features.flatten(2))  # N, samples, hw
    loss = F.cross_entropy(logits.reshape(-1, h * w), target.gather(1, chosen).reshape(-1), reduction="none")
    return (loss * valid.reshape(-1)).sum(), valid.sum()


def match_loss(features: torch.Tensor, b_from_a: torch.Tensor, log_temperature: torch.Tensor, samples: int = 256,
               generator: torch.Generator | None = None) -> torch.Tensor:
    """Dense matching loss of ``matcher`` descriptors: for cells of A that the true homography puts inside B,
    the cross-entropy of finding their B cell among all of B's (an InfoNCE over the whole frame), and the
    same from B to A.

    Args:
        features: (N, 2, C, h, w) unit descriptors of A and B (cells of 4 px).
        b_from_a: (N, 3, 3) true homographies in the views' pixels (the synthetic warp: no human labels).
        log_temperature: the similarities are multiplied by its exponential.
        samples: cells drawn per pair and direction.
    """
    scale = log_temperature.exp()
    h = b_from_a.to(features.dtype)
    total_ab, count_ab = _match_direction(features[:, 0], features[:, 1], h, scale, samples, generator)
    total_ba, count_ba = _match_direction(features[:, 1], features[:, 0], torch.linalg.inv(h), scale, samples, generator)
    return (total_ab + total_ba) / (count_ab + count_ba).clamp_min(1.0)
