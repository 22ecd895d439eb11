"""Synthetic image pairs with known homographies: the DeTone/paper procedure, for training and benchmarks.

One generator serves both, so the benchmark measures exactly the distribution the models train on.

The procedure (pixel conventions of :mod:`udh_cli.geometry`):

1. The source image is resized to 320x240 and made grey.
2. A patch position ``c0`` is drawn so that the patch plus a margin of ``rho`` stays inside the image.
3. The four patch corners are perturbed uniformly in ``[-rho, rho]`` (``offsets``); a draw that folds
   the quadrilateral (non-convex, about 0.5 % at rho 45) is drawn again. The homography
   ``H`` maps the corners ``C`` to ``C + offsets``.
4. Patch B is the image cropped at ``c0``. Patch A samples the image at ``H(x + c0)``: a scene point
   at ``x`` in patch A therefore sits at ``H(x + c0) - c0`` in patch B, so the patch homography
   ``b_from_a`` has exactly ``offsets`` as its 4-point parameterisation. Both patches are sampled from
   inside the image (the perturbed quadrilateral lies within the margin), so no pixel is invented.
   This is the paper's "warp with H_AB^-1 and crop" with the roles of A and B written in udh's direction.
5. Illumination (optional, as in the paper): each patch gets its own random brightness, contrast and
   gamma. Occluders (optional, the paper's future work): random textured blobs pasted on either patch.

The *clean* (un-augmented) image in A's frame is kept as ``context_a`` so that the unsupervised loss can
compare geometry without being fooled by the illumination change the network has to ignore.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.images import IMAGE_SUFFIXES, read_image, to_gray_u8

if TYPE_CHECKING:
    from udh_cli.generator_settings import MotionConfig

SOURCE_SIZE = (320, 240)  # (width, height) every source image is resized to, as in DeTone et al.


@dataclass(frozen=True)
class PairConfig:
    """How synthetic pairs are drawn.

    Attributes:
        patch_size: side of the square patches, pixels (the paper: 128).
        rho: largest corner perturbation, pixels of the 320x240 image.
        small_motion_fraction: share of pairs whose own rho is drawn uniformly in [0, rho] instead of
            being rho; it teaches a network the small residuals that iterative refinement asks about.
        illumination: random brightness, contrast and gamma per patch.
        occluders: share of pairs (0 to 1) whose patches get random textured blobs; ``True`` means all.
        motion: None for the paper's corner perturbation; a :class:`~udh_cli.flight_motion.MotionConfig`
            for real flight motion (whole frames, any heading, scale, low overlap; ``rho`` is then unused).
    """

    patch_size: int = 128
    rho: float = 32.0
    small_motion_fraction: float = 0.0
    illumination: bool = True
    occluders: float = 0.0
    motion: "MotionConfig | None" = None


@dataclass
class PairBatch:
    """A batch of synthetic pairs. N pairs, P = patch size, in [0, 1] float32 unless said otherwise.

    Attributes:
        patch_a: (N, P, P) what the estimator sees of A (augmented).
        patch_b: (N, P, P) what the estimator sees of B (augmented).
        offsets: (N, 4, 2) true 4-point parameterisation of ``b_from_a`` in patch pixels.
        context_a: (N, 2, H, W) the clean source image in A's frame (channel 0) and its validity mask
            (channel 1); patch A is ``context_a[:, 0, y0:y0+P, x0:x0+P]`` before augmentation.
        clean_b: (N, P, P) patch B before augmentation.
        origin: (N, 2) ``(x0, y0)``: where the patches sit in ``context_a``, pixels.
        source_index: (N,) which source image each pair came from.
    """

    patch_a: np.ndarray
    patch_b: np.ndarray
    offsets: np.ndarray
    context_a: np.ndarray
    clean_b: np.ndarray
    origin: np.ndarray
    source_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def homographies(self) -> np.ndarray:
        """(N, 3, 3) true ``b_from_a`` between the patches."""
        p = self.patch_a.shape[-1]
        return geometry.homography_from_offsets(self.offsets.astype(np.float64), p, p)


def list_images(folders: list[Path] | Path) -> list[Path]:
    """Image files below ``folders`` (recursively), sorted by path so every run sees the same order."""
    folders = [folders] if isinstance(folders, (str, Path)) else folders
    found: list[Path] = []
    for folder in folders:
        folder = Path(folder)
        if not folder.exists():
            raise UdhError(f"{folder}: no such folder")
        if folder.is_file():
            found.append(folder)
            continue
        found.extend(p for p in folder.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    return sorted(found)


def split_holdout(paths: list[Path], every: int = 10) -> tuple[list[Path], list[Path]]:
    """Deterministic train/held-out split: every ``every``-th image (in sorted order) is held out.

    Training never sees the held-out images; benchmarks use them.
    """
    train = [p for i, p in enumerate(paths) if i % every != 0]
    held_out = [p for i, p in enumerate(paths) if i % every == 0]
    return train, held_out


def load_sources(paths: list[Path], min_count: int = 1,
                 size_for: Callable[[int, int], tuple[int, int]] | None = None) -> list[np.ndarray]:
    """Read images as grey uint8, resized to 320x240 or to ``size_for(width, height)``.

    Unreadable files are skipped; fewer than ``min_count`` is an error.
    """
    sources = []
    for path in paths:
        try:
            image = to_gray_u8(read_image(path))
        except UdhError:
            continue
        size = SOURCE_SIZE if size_for is None else size_for(image.shape[1], image.shape[0])
        sources.append(cv2.resize(image, size, interpolation=cv2.INTER_AREA))
    if len(sources) < min_count:
        raise UdhError(f"found {len(sources)} usable images; need at least {min_count} (JPEG, PNG or TIFF)")
    return sources


MAX_CLIPPED = 0.1  # share of an image's pixels an illumination shift may push out of [0, 1]


def illuminate(patch: np.ndarray, rng: np.random.Generator, max_clipped: float = MAX_CLIPPED) -> np.ndarray:
    """Random gamma, contrast and brightness; (P, P) float in [0, 1] -> same.

    A draw that would clip more than ``max_clipped`` of the pixels strictly inside (0, 1) is drawn again
    (up to 20 times, then the patch is returned unchanged). Why: unconstrained, a dark source under low
    brightness and high contrast came out black; 7 of 200 held-out rho-32 pairs had more than 95 % of one
    image clipped to 0, and every method failed on them. Lighting changes should change appearance, not
    erase the content.
    """
    inside = (patch > 0.0) & (patch < 1.0)
    for _ in range(20):
        gamma = np.exp(rng.uniform(np.log(0.6), np.log(1.6)))
        contrast = rng.uniform(0.6, 1.4)
        brightness = rng.uniform(-0.2, 0.2)
        out = (np.power(np.clip(patch, 0.0, 1.0), gamma) - 0.5) * contrast + 0.5 + brightness
        if (((out < 0.0) | (out > 1.0)) & inside).mean() <= max_clipped:
            return np.clip(out, 0.0, 1.0)
    return patch.copy()


def _occlude(patch: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Paste 1-3 random textured ellipses covering up to about a fifth of the patch."""
    out = patch.copy()
    size = patch.shape[0]
    for _ in range(rng.integers(1, 4)):
        mask = np.zeros_like(patch, dtype=np.uint8)
        centre = tuple(int(v) for v in rng.integers(0, size, 2))
        axes = tuple(int(v) for v in rng.integers(size // 12, size // 5, 2))
        cv2.ellipse(mask, centre, axes, float(rng.uniform(0, 180)), 0, 360, 1, -1)
        texture = cv2.GaussianBlur(rng.random(patch.shape).astype(np.float32), (0, 0), rng.uniform(0.5, 3.0))
        texture = rng.uniform(0.0, 1.0) + (texture - texture.mean()) * rng.uniform(0.5, 3.0)
        out = np.where(mask > 0, np.clip(texture, 0, 1), out)
    return out


def make_pairs(
    sources: list[np.ndarray], count: int, config: PairConfig, rng: np.random.Generator, with_context: bool = True
) -> PairBatch:
    """Draw ``count`` pairs from ``sources`` (320x240 grey uint8, see :func:`load_sources`).

    Deterministic given ``rng``'s state. ``with_context=False`` skips the full-frame warp that only the
    unsupervised loss needs.
    """
    p = config.patch_size
    w, h = SOURCE_SIZE
    margin = int(np.ceil(config.rho))
    if p + 2 * margin > min(w, h):
        raise UdhError(f"rho {config.rho} is too large for {p}-pixel patches in a {w}x{h} image")
    corners = geometry.image_corners(p, p)
    patch_a = np.empty((count, p, p), np.float32)
    patch_b = np.empty((count, p, p), np.float32)
    clean_b = np.empty((count, p, p), np.float32)
    offsets = np.empty((count, 4, 2), np.float32)
    origin = np.empty((count, 2), np.float32)
    index = rng.integers(0, len(sources), count)
    context = np.empty((count, 2, h, w), np.float32) if with_context else np.zeros((count, 2, 1, 1), np.float32)
    ones = np.ones((h, w), np.float32)
    for i in range(count):
        image = sources[index[i]].astype(np.float32) / 255.0
        x0 = rng.integers(margin, w - p - margin + 1)
        y0 = rng.integers(margin, h - p - margin + 1)
        rho_i = config.rho * (rng.uniform() if rng.uniform() < config.small_motion_fraction else 1.0)
        delta = rng.uniform(-rho_i, rho_i, (4, 2))
        while not geometry.is_valid_homography(geometry.homography_from_points(corners, corners + delta), p, p):
            # At rho 45 about 0.5 % of draws fold the quadrilateral: no camera sees a plane that way.
            delta = rng.uniform(-rho_i, rho_i, (4, 2))
        source_from_a = geometry.homography_from_points(corners + [x0, y0], corners + [x0, y0] + delta)
        # WARP_INVERSE_MAP: dst(x) = src(M x), i.e. patch A samples the image at H(x + c0).
        a = cv2.warpPerspective(image, source_from_a @ geometry.translation(x0, y0), (p, p),
                                flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REFLECT)
        b = image[y0 : y0 + p, x0 : x0 + p]
        if with_context:
            context[i, 0] = cv2.warpPerspective(image, source_from_a, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                                borderMode=cv2.BORDER_REFLECT)
            context[i, 1] = cv2.warpPerspective(ones, source_from_a, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                                borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        clean_b[i] = b
        a_seen, b_seen = a, b
        if config.illumination:
            a_seen, b_seen = illuminate(a_seen, rng), illuminate(b_seen, rng)
        # Only a fractional share draws a coin, so sets made with all or none occluded stay as they were.
        if config.occluders >= 1.0 or (config.occluders > 0.0 and rng.uniform() < config.occluders):
            a_seen, b_seen = _occlude(a_seen, rng), _occlude(b_seen, rng)
        patch_a[i], patch_b[i] = a_seen, b_seen
        offsets[i] = delta
        origin[i] = (x0, y0)
    return PairBatch(patch_a, patch_b, offsets, context, clean_b, origin, index)


def save_pairs(path: str | Path, batch: PairBatch) -> None:
    """Save a benchmark set (patches, offsets, sources) to a compressed ``.npz``, atomically."""
    import io

    from udh_cli.images import atomic_write_bytes

    buffer = io.BytesIO()
    np.savez_compressed(buffer, patch_a=batch.patch_a, patch_b=batch.patch_b, offsets=batch.offsets,
                        origin=batch.origin, source_index=batch.source_index)
    atomic_write_bytes(path, buffer.getvalue())


def load_pairs(path: str | Path) -> PairBatch:
    """Load a set written by :func:`save_pairs`, checking shapes, types and finiteness (the file is untrusted)."""
    arrays = _read_npz(path, ("patch_a", "patch_b", "offsets", "origin", "source_index"))
    patch_a, patch_b, offsets = arrays["patch_a"], arrays["patch_b"], arrays["offsets"]
    origin, source_index = arrays["origin"], arrays["source_index"]
    n = len(patch_a)
    if (n < 1 or patch_a.ndim != 3 or patch_a.shape[1] != patch_a.shape[2] or patch_b.shape != patch_a.shape
            or offsets.shape != (n, 4, 2) or origin.shape != (n, 2) or source_index.shape != (n,)):
        raise UdhError(f"{path}: inconsistent shapes in the pair set (want N >= 1 square patches, (N, 4, 2) offsets, (N, 2) origins)")
    if any(x.dtype.kind not in "fiu" for x in (patch_a, patch_b, offsets, origin, source_index)):
        raise UdhError(f"{path}: the pair set holds non-numeric arrays")
    if not all(np.isfinite(x).all() for x in (patch_a, patch_b, offsets, origin)):
        raise UdhError(f"{path}: the pair set holds NaN or infinite values")
    empty_context = np.zeros((n, 2, 1, 1), np.float32)
    batch = PairBatch(patch_a, patch_b, offsets, empty_context, patch_b, origin, source_index)
    try:
        batch.homographies()
    except np.linalg.LinAlgError:
        raise UdhError(f"{path}: some offsets give a degenerate homography (three corners in a line)") from None
    return batch


def _read_npz(path: str | Path, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The arrays ``keys`` of an ``.npz`` file, loaded without pickles; :class:`UdhError` if it is not one."""
    try:
        data = np.load(Path(path), allow_pickle=False)
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise ValueError("a single array, not an .npz archive")
        with data:
            return {key: data[key] for key in keys}
    except Exception as exc:  # noqa: BLE001 - missing, truncated, non-zip, pickled or key-less files alike
        reason = str(exc) if isinstance(exc, (OSError, ValueError)) else f"{type(exc).__name__}: {exc}"
        if "pickle" in reason:  # numpy's advice to unpickle would be bad advice for an untrusted file
            reason = "not an .npz archive of arrays"
        raise UdhError(f"{path}: not a udh pair set ({reason}); give an .npz written by --save-pairs") from None
