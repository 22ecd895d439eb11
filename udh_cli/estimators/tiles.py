"""Full-resolution precision from the network itself: refine a homography on tiles at finer pyramid levels.

A network that sees a whole 1600 px frame at 128x128 can be no better than about 1/128 of the frame
(12 px at 1600 px), however well it is trained. Here A is pre-warped by the current estimate, and the
refinement network (trained on small residual motion of 128x128 patches) runs on 128x128 tiles cut from
B and the warped A at finer levels, ending at full resolution. Each tile's 4-point answer gives four
local correspondences; a RANSAC fit over all tiles gives the new homography, and the tiles that agree
give its support. No features and no ECC: only network passes, warps of small tiles and a 3x3 fit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.estimators.pair import ImageLike, PreparedImage
from udh_cli.estimators.thresholds import THRESHOLDS
from udh_cli.images import scaled_size
from udh_cli.onnx_model import OnnxHomographyModel


MIN_SEEN_PROBES = 6  # of the 3x3 probes of a tile that must fall inside A


@dataclass(frozen=True)
class TileRefinement:
    """Settings of the tile stage (one reason each).

    Attributes:
        levels: longer side (pixels) of each pyramid level, coarse to fine; 0 means full resolution. Levels
            at least as large as the images run at full resolution once.
        tiles: most tiles per level: enough to outvote bad tiles, few enough to stay within a few ms.
        inlier_px: RANSAC threshold, pixels of the level: the refinement network's median error on a tile.
        max_move: largest corner move, pixels of the level, that a level may make: a tile network trained on
            small residuals is not trusted with more (its training motion was 16 px).
        min_tiles: fewest agreeing tiles for a level's fit to replace the current estimate.
        min_share: fewest share of a level's tiles that must agree as well. Why: with 12 tiles, 3 can agree by
            chance on a start far beyond reach (a test-made 1600x1200 pair 270 px off: the shipped int8
            refinement network confirmed such a level once in five starts); on the consecutive pairs of copr and
            brighton-beach 0.3 changed no answer, on seneca's it took the median from 45.9 to 40.6 px.
        coarse_side: longer side of a first level where the coarse network runs on the tiles (0: none). Why:
            a whole frame squashed to 128x128 leaves the coarse answer up to 10-15 px off in that view on
            low-overlap, repetitive scenes (tree canopy), beyond the refinement network's reach; tiles of a
            384 px level see the scene three times as large. 384 rather than 256: a 16:9 or 3:2 frame gives
            twice as many tiles to outvote the bad ones; on the consecutive pairs of copr (at 800 px, against
            SIFT references) under 3 px went from 65 to 78 % of pairs (under 10 px 85 -> 95 %), on seneca's
            under 10 px 9 -> 17 %, at 5 ms more a pair at 800 px (about 20 ms at 1600x1200); 512 was no better
            (docs/estimators.md).
        coarse_move: largest corner move, pixels of the coarse level, that it may make (3/16 of the level).
    """

    levels: tuple[int, ...] = (480, 0)
    tiles: int = 12
    inlier_px: float = 3.0
    max_move: float = 16.0
    min_tiles: int = 3
    min_share: float = 0.3
    coarse_side: int = 384
    coarse_move: float = 72.0

    def can_confirm(self, size_b: tuple[int, int], tile: int) -> bool:
        """Whether B (``(width, height)`` pixels) holds enough tiles of side ``tile`` at full resolution for a
        level to confirm an answer. A pair at the network's own size (the paper's 128x128 patches) has none,
        so finding no confirmation there says nothing about the answer."""
        return min(size_b) >= tile and len(_tile_origins(size_b, tile)) >= self.min_tiles


# Levels that must accept an answer for it to count as confirmed.
CONFIRMING_LEVELS = THRESHOLDS.confirming_tile_levels


@dataclass(frozen=True)
class TileResult:
    """What the tile stage found.

    Attributes:
        b_from_a: (3, 3) refined homography, pixels of the images given.
        levels_used: levels whose fit was accepted.
        levels_run: levels that ran with room for tiles (:meth:`TileRefinement.can_confirm`; a level of the same
            size and network as an earlier one does not run again).
        agreeing: share of the finest accepted level's tiles that agreed with its fit (0 when none was).
        residual_px: median corner residual of the agreeing tiles at the finest accepted level, in pixels
            of the full-resolution B (nan when no level was accepted).
    """

    b_from_a: np.ndarray
    levels_used: int
    agreeing: float
    residual_px: float
    levels_run: int

    def confirms(self, levels: int = CONFIRMING_LEVELS) -> bool:
        """Whether the answer is confirmed: accepted by ``levels`` levels, or by every level that ran when fewer ran."""
        return self.levels_used >= min(levels, self.levels_run)


def _level_sizes(size_a: tuple[int, int], size_b: tuple[int, int], side: int) -> tuple[tuple[int, int], tuple[int, int]]:
    longest = max(*size_a, *size_b)
    scale = 1.0 if side <= 0 or side >= longest else side / longest
    return scaled_size(size_a, scale), scaled_size(size_b, scale)


def _tile_origins(size_b: tuple[int, int], tile: int) -> list[tuple[int, int]]:
    """Top-left corners of tiles on a grid with half-tile overlap covering B."""
    width, height = size_b
    xs = np.unique(np.linspace(0, width - tile, max(1, int(np.ceil((width - tile) / (tile / 2))) + 1)).round().astype(int))
    ys = np.unique(np.linspace(0, height - tile, max(1, int(np.ceil((height - tile) / (tile / 2))) + 1)).round().astype(int))
    return [(int(x), int(y)) for y in ys for x in xs]


def _tile_texture(gray_b: np.ndarray, origins: np.ndarray, tile: int) -> np.ndarray:
    """(T,) standard deviation of every 4th pixel of each tile of B at ``origins`` (T, 2), gathered at once:
    enough to tell flat from textured (an integral image of a full-resolution level cost more)."""
    steps = np.arange(0, tile, 4)
    rows = origins[:, 1, None] + steps  # T, k
    columns = origins[:, 0, None] + steps  # T, k
    return gray_b[rows[:, :, None], columns[:, None, :]].std(axis=(1, 2), dtype=np.float64)


def _choose_tiles(gray_b: np.ndarray, a_from_b: np.ndarray, size_a: tuple[int, int], tile: int, count: int) -> list[tuple[int, int]]:
    """Tiles of B wholly seen in A, textured, spread over the overlap: at most ``count``."""
    width_a, height_a = size_a
    origins = np.array(_tile_origins((gray_b.shape[1], gray_b.shape[0]), tile), np.float64)  # T, 2
    steps = np.linspace(0, tile - 1, 3)
    probe = np.array([[x, y] for y in steps for x in steps], np.float64)  # a 3x3 grid over the tile
    seen = geometry.transform_points(a_from_b, (origins[:, None, :] + probe[None]).reshape(-1, 2)).reshape(len(origins), -1, 2)
    seen_inside = (np.isfinite(seen).all(2) & (seen[..., 0] > -0.5) & (seen[..., 1] > -0.5)
                   & (seen[..., 0] < width_a - 0.5) & (seen[..., 1] < height_a - 0.5))
    # Most of the tile must be seen in A (the centre and 6 of 9 probes): at coarse levels and low overlap
    # no tile is wholly inside, and the network copes with a margin of A's replicated border.
    inside = seen_inside[:, 4] & (seen_inside.sum(1) >= MIN_SEEN_PROBES)
    if not inside.any():
        return []
    origins = origins[inside].astype(int)
    texture = _tile_texture(gray_b, origins, tile)
    # Flat tiles (water, bare sand, sky) give the network nothing to align; keep the better-textured ones.
    keep = texture >= max(0.01, 0.5 * float(np.median(texture)))
    kept = origins[keep]
    if len(kept) > count:  # evenly through the raster order: spread over the overlap, not clustered
        kept = kept[np.linspace(0, len(kept) - 1, count).round().astype(int)]
    return [(int(x), int(y)) for x, y in kept]


@dataclass(frozen=True)
class _LevelTiles:
    """One pair's tiles at one level, ready for the network: ``patches`` (N, 2, S, S), the warped A over B's tile."""

    origins: list[tuple[int, int]]
    patches: np.ndarray
    b_from_a: np.ndarray
    size_a: tuple[int, int]


def _cut_tiles(tile: int, level_a: np.ndarray, level_b: np.ndarray, b_from_a: np.ndarray, config: TileRefinement) -> _LevelTiles | None:
    """The tiles of one level and A pre-warped onto each; None when too few tiles can be used."""
    if min(level_b.shape) < tile or min(level_a.shape) < tile:
        return None
    size_a = (level_a.shape[1], level_a.shape[0])
    a_from_b = np.linalg.inv(b_from_a)
    origins = _choose_tiles(level_b, a_from_b, size_a, tile, config.tiles)
    if len(origins) < config.min_tiles:
        return None
    warped, seen_b = [], []
    for x0, y0 in origins:
        # WARP_INVERSE_MAP: tile pixel q samples A at a_from_b (q + origin): A pre-warped into B's frame.
        warped.append(cv2.warpPerspective(level_a, a_from_b @ geometry.translation(x0, y0), (tile, tile),
                                          flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE))
        seen_b.append(level_b[y0 : y0 + tile, x0 : x0 + tile])
    return _LevelTiles(origins, np.stack([np.stack(warped), np.stack(seen_b)], 1), np.asarray(b_from_a, np.float64), size_a)


def _fit_tiles(cut: _LevelTiles, offsets: np.ndarray, tile: int, config: TileRefinement,
               max_move: float | None) -> tuple[np.ndarray, int, float, float] | None:
    """A RANSAC fit over the tiles' answers ``offsets`` (N, 4, 2, pixels of a tile): ``(b_from_a, tiles, agreeing
    share, median residual px)`` at the level, or None when too few tiles agreed or the fit moved too far."""
    a_from_b = np.linalg.inv(cut.b_from_a)
    corners = geometry.image_corners(tile, tile)
    shifts = np.array(cut.origins, np.float64)[:, None, :]
    points_b = (corners[None] + shifts + offsets).reshape(-1, 2)
    points_a = geometry.transform_points(a_from_b, (corners[None] + shifts).reshape(-1, 2))
    fitted, mask = cv2.findHomography(points_a, points_b, cv2.RANSAC, config.inlier_px, maxIters=500, confidence=0.999)
    if fitted is None or mask is None:
        return None
    per_tile = mask.reshape(-1, 4).sum(1) >= 3  # a tile agrees when three of its four corners do
    if per_tile.sum() < max(config.min_tiles, config.min_share * len(cut.origins)) or not geometry.is_valid_homography(fitted, *cut.size_a):
        return None
    move = geometry.corner_errors(fitted, cut.b_from_a, *cut.size_a).max()
    if not move <= (config.max_move if max_move is None else max_move):
        return None
    residual = np.linalg.norm(geometry.transform_points(fitted, points_a) - points_b, axis=1).reshape(-1, 4)[per_tile]
    return fitted / fitted[2, 2], len(cut.origins), float(per_tile.mean()), float(np.median(residual))


def _as_prepared(image: ImageLike) -> PreparedImage:
    """A prepared image as it is; an (H, W) float32 grey array wrapped as one, without a copy."""
    if isinstance(image, PreparedImage):
        return image
    return PreparedImage(np.asarray(image, np.float32), np.dtype(np.float32))


def _pyramid(image_a: PreparedImage, image_b: PreparedImage, sides: list[int]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Both images at every level side (0: full resolution), each level resized from the next finer one
    rather than from full resolution, and kept on the prepared image: a frame in two pairs (A of one, B of the
    next) and a pair tiled again (from a searched or matched answer) are resized once."""
    size_a, size_b = image_a.size, image_b.size
    out: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    finer_a, finer_b = image_a.grey, image_b.grey
    for side in sorted(set(sides), key=lambda v: -(v if v > 0 else 10**9)):  # finest first
        level_size_a, level_size_b = _level_sizes(size_a, size_b, side)
        finer_a, finer_b = _smaller(image_a, finer_a, level_size_a), _smaller(image_b, finer_b, level_size_b)
        out[side] = (finer_a, finer_b)
    return out


def _smaller(image: PreparedImage, finer: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``finer`` (a level of ``image``) area-resized to ``size`` (w, h), made once per image; ``finer`` at its size.
    The key names the level it was made from, so the same level is the same pixels whichever pair made it."""
    if size == (finer.shape[1], finer.shape[0]):
        return finer
    return image.derived(("tile-level", finer.shape, size), lambda: cv2.resize(finer, size, interpolation=cv2.INTER_AREA))


@dataclass
class _Progress:
    """One pair's way through the levels."""

    current: np.ndarray
    used: int = 0
    run: int = 0
    agreeing: float = 0.0
    residual: float = float("nan")


def refine_pairs_with_tiles(network: OnnxHomographyModel, pairs: Sequence[tuple[ImageLike, ImageLike]], starts: Sequence[np.ndarray],
                            config: TileRefinement = TileRefinement(),
                            coarse_network: OnnxHomographyModel | None = None) -> list[TileResult]:
    """Refine each ``starts[i]`` (3x3 ``b_from_a``, pixels of pair i) on its pair ``(A, B)`` (prepared images, or
    (H, W) float32 grey in [0, 1]) level by level: ``coarse_network`` on tiles of a ``config.coarse_side`` level
    first (when given), then ``network``. Every pair's tiles of a level go to the network together
    (:meth:`~udh_cli.onnx_model.OnnxHomographyModel.predict_offsets`, in runs of its cache-friendly size).

    A level whose fit fails or moves too far leaves the estimate as it was; finer levels still run.
    """
    prepared = [(_as_prepared(a), _as_prepared(b)) for a, b in pairs]
    progress = [_Progress(np.asarray(h, np.float64)) for h in starts]
    plan = [(side, network, config.max_move) for side in config.levels]
    if coarse_network is not None and config.coarse_side > 0:
        plan.insert(0, (config.coarse_side, coarse_network, config.coarse_move))
    levels = [_pyramid(a, b, [side for side, _, _ in plan]) for a, b in prepared]
    done_sizes: list[set] = [set() for _ in prepared]
    for side, level_network, max_move in plan:
        tile = level_network.input_size
        cuts = []  # (pair index, level sizes, tiles)
        for i, ((image_a, image_b), state) in enumerate(zip(prepared, progress)):
            level_a, level_b = levels[i][side]
            level_size_a, level_size_b = (level_a.shape[1], level_a.shape[0]), (level_b.shape[1], level_b.shape[0])
            # A level size once per network: on small images the coarse network's level is already full
            # resolution, and the refinement network must still run there.
            if (id(level_network), level_size_a, level_size_b) in done_sizes[i]:
                continue
            done_sizes[i].add((id(level_network), level_size_a, level_size_b))
            start = geometry.rescale_homography(state.current, image_a.size, level_size_a, image_b.size, level_size_b)
            state.run += config.can_confirm(level_size_b, tile)  # a level with no room for tiles is no evidence
            cut = _cut_tiles(tile, level_a, level_b, start, config)
            if cut is not None:
                cuts.append((i, level_size_a, level_size_b, cut))
        if not cuts:
            continue
        offsets = level_network.predict_offsets(np.concatenate([cut.patches for *_, cut in cuts]))
        bounds = np.cumsum([0] + [len(cut.origins) for *_, cut in cuts])
        for (i, level_size_a, level_size_b, cut), first, last in zip(cuts, bounds[:-1], bounds[1:]):
            found = _fit_tiles(cut, offsets[first:last], tile, config, max_move)
            if found is None:
                continue
            state, (image_a, image_b) = progress[i], prepared[i]
            fitted, _, state.agreeing, residual_level = found
            state.current = geometry.rescale_homography(fitted, level_size_a, image_a.size, level_size_b, image_b.size)
            state.residual = residual_level * image_b.size[0] / level_size_b[0]
            state.used += 1
    return [TileResult(s.current / s.current[2, 2], s.used, s.agreeing, s.residual, s.run) for s in progress]


def refine_with_tiles(network: OnnxHomographyModel, image_a: ImageLike, image_b: ImageLike, b_from_a: np.ndarray,
                      config: TileRefinement = TileRefinement(), coarse_network: OnnxHomographyModel | None = None) -> TileResult:
    """:func:`refine_pairs_with_tiles` of one pair."""
    return refine_pairs_with_tiles(network, [(image_a, image_b)], [b_from_a], config, coarse_network)[0]
