"""The two training objectives: the paper's unsupervised photometric loss and HomographyNet's L2 loss."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from udh_cli import geometry


def warp_context(offsets: torch.Tensor, context_a: torch.Tensor, origin: torch.Tensor, patch_size: int) -> torch.Tensor:
    """Render A in B's patch frame with the predicted homography: the spatial-transformer layer.

    Args:
        offsets: (N, 4, 2) predicted 4-point offsets, pixels of the patch (``b_from_a``).
        context_a: (N, C, H, W) A's full frame (and any extra channels, e.g. a validity mask).
        origin: (N, 2) where the patch's top-left pixel sits in ``context_a``, pixels (x, y).
        patch_size: P.

    Returns:
        (N, C, P, P): ``context_a`` sampled at ``a_from_b(y) + origin`` for every pixel ``y`` of B's patch.
    """
    corners = geometry.image_corners(patch_size, patch_size, like=offsets)
    # Tensor DLT with the correspondences swapped gives a_from_b directly, without inverting a matrix.
    a_from_b = geometry.homography_from_points(corners + offsets, corners.expand_as(offsets))  # N, 3, 3
    shift = torch.eye(3, dtype=offsets.dtype, device=offsets.device).repeat(len(offsets), 1, 1)
    shift[:, :2, 2] = origin
    context_from_b = shift @ a_from_b
    height, width = context_a.shape[-2:]
    grid = geometry.sampling_grid(context_from_b, (width, height), (patch_size, patch_size))  # N, P, P, 2
    return F.grid_sample(context_a, grid.to(context_a.dtype), mode="bilinear", padding_mode="zeros", align_corners=False)


def photometric_loss(offsets: torch.Tensor, context_a: torch.Tensor, origin: torch.Tensor, clean_b: torch.Tensor) -> torch.Tensor:
    """The paper's unsupervised loss: mean L1 between warped A and B over the valid pixels.

    ``context_a`` is (N, 2, H, W): the image in A's frame and its validity mask (1 where real pixels).
    ``clean_b`` is (N, P, P). Pixels whose sample falls outside A's real pixels do not count.
    """
    warped = warp_context(offsets, context_a, origin, clean_b.shape[-1])
    valid = (warped[:, 1] > 0.999).to(clean_b.dtype).detach()
    error = (warped[:, 0] - clean_b).abs() * valid
    return error.sum() / valid.sum().clamp_min(1.0)


def supervised_loss(offsets: torch.Tensor, true_offsets: torch.Tensor) -> torch.Tensor:
    """HomographyNet's loss: ``0.5 * ||H_4pt - H*_4pt||^2`` over the 8 numbers, averaged over the batch."""
    return 0.5 * ((offsets - true_offsets) ** 2).sum(dim=(1, 2)).mean()


def corner_error(offsets: torch.Tensor, true_offsets: torch.Tensor) -> torch.Tensor:
    """(N,) mean corner distance in pixels; for a shared set of corners this is exactly MACE."""
    return (offsets - true_offsets).pow(2).sum(-1).sqrt().mean(-1)
