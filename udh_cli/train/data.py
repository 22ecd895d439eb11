"""Training data: synthetic pairs from image pools, consecutive real frames from flights, or both mixed.

All produce the same batch layout (numpy, float32), which :func:`to_tensors` turns into torch:
``patches (N, 2, P, P)`` in [0, 1] (what the network sees, augmented), ``offsets (N, 4, 2)`` (the truth,
synthetic only), ``context_a (N, 2, H, W)`` (clean A frame + validity mask), ``origin (N, 2)`` and
``clean_b (N, P, P)`` (what the photometric loss compares against).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.homography_files import homography_from_values, parse_numbers
from udh_cli.flight_motion import MotionConfig, make_flight_frames, make_motion_pairs, source_size
from udh_cli.images import read_image, to_gray_u8
from udh_cli.train.config import DEFAULT_REAL_FRACTION
from udh_cli.synthetic import SOURCE_SIZE, PairConfig, illuminate, list_images, load_sources, make_pairs, split_holdout

FLIGHT_MARKERS = ("manifest.csv", "consecutive_pairs_sift_reference.csv")


def is_flight_folder(folder: Path) -> bool:
    """A flight folder holds a sequence of overlapping frames; udh recognises the shared-data layout."""
    return any((folder / marker).is_file() for marker in FLIGHT_MARKERS)


@dataclass
class Batch:
    patches: np.ndarray
    offsets: np.ndarray | None
    context_a: np.ndarray
    origin: np.ndarray
    clean_b: np.ndarray


class PoolData:
    """Synthetic pairs (DeTone procedure) from folders of single images; every 10th image is held out.

    ``source_side``: 0 resizes every image to 320x240, the paper's procedure. A larger side resizes each
    image so that its longer side is that many pixels and draws every pair from a random 320x240 window of
    it: the patches then show the scene at the scale of a tile of a frame that size. Why: the tile stage runs
    the refinement network on 128 px tiles of frames 480-1600 px wide, whose texture the 320x240 procedure
    never shows it (a 1600 px frame squashed to 320 px is five times coarser).
    """

    kind = "pool"
    has_labels = True

    def __init__(self, folders: list[Path], config: PairConfig, source_side: int = 0):
        paths = list_images(folders)
        train_paths, held_out = split_holdout(paths)
        if len(train_paths) < 2 or not held_out:
            raise UdhError(f"found {len(paths)} images in {', '.join(map(str, folders))}; need at least 3 to train and hold one out")
        self.config = config
        self.source_side = source_side
        size_for = source_size if config.motion is not None else None
        if source_side:
            if config.motion is not None:
                raise UdhError("--source-side is for the paper's motion (patches of larger frames); --motion flight uses whole frames")
            width, height = SOURCE_SIZE
            size_for = lambda w, h: _longer_side(w, h, source_side, (width, height))  # noqa: E731
        self.train = load_sources(train_paths, min_count=2, size_for=size_for)
        self.held_out = load_sources(held_out, min_count=1, size_for=size_for)
        self.description = f"{len(self.train)} pool images ({len(self.held_out)} held out)" + (f" at {source_side} px" if source_side else "")

    def _windows(self, sources: list[np.ndarray], count: int, rng: np.random.Generator) -> list[np.ndarray]:
        """``count`` random 320x240 windows of randomly chosen ``sources``."""
        width, height = SOURCE_SIZE
        out = []
        for index in rng.integers(0, len(sources), count):
            image = sources[index]
            x0 = int(rng.integers(0, image.shape[1] - width + 1))
            y0 = int(rng.integers(0, image.shape[0] - height + 1))
            out.append(image[y0 : y0 + height, x0 : x0 + width])
        return out

    def _pairs(self, sources: list[np.ndarray], size: int, config: PairConfig, rng: np.random.Generator, with_context: bool):
        if config.motion is None:
            if self.source_side:
                sources = self._windows(sources, size, rng)
            return make_pairs(sources, size, config, rng, with_context=with_context)
        return make_motion_pairs(sources, size, config.motion, rng, config.patch_size, config.small_motion_fraction,
                                 config.illumination, config.occluders, with_context=with_context)

    def batch(self, rng: np.random.Generator, size: int, unsupervised: bool) -> Batch:
        pairs = self._pairs(self.train, size, self.config, rng, with_context=unsupervised)
        return Batch(np.stack([pairs.patch_a, pairs.patch_b], 1), pairs.offsets, pairs.context_a, pairs.origin, pairs.clean_b)

    def validation(self, size: int, seed: int = 12345) -> Batch:
        """A fixed set from the held-out images at the full motion, with illumination: the benchmark protocol."""
        config = PairConfig(self.config.patch_size, self.config.rho, 0.0, True, False, self.config.motion)
        pairs = self._pairs(self.held_out, size, config, np.random.default_rng(seed), with_context=False)
        return Batch(np.stack([pairs.patch_a, pairs.patch_b], 1), pairs.offsets, pairs.context_a, pairs.origin, pairs.clean_b)


class FlightData:
    """Consecutive frames of real flights, each frame resized whole to P x P (as the estimator does).

    There are no labels: only the unsupervised loss can train on them. Every 5th pair is held out; its
    reference homography (the folder's SIFT reference CSV, else SIFT computed here) measures progress.
    Training pairs are augmented with the same flip/rotation for both frames, a random A/B swap, and
    independent illumination on what the network sees.

    ``canvas``: the side of ``context_a`` (default P). A larger canvas puts A's frame at ``(c - P) / 2``
    with a zero mask around it, the layout of synthetic flight-motion pairs, so that both kinds share a
    batch. ``orient``: turn B half a turn where the shipped network's own heading choice says so
    (:func:`half_turn_choices`): a strip's return leg is otherwise a pair no network trained for turns of
    tens of degrees can learn from.
    """

    kind = "flight"
    has_labels = False

    def __init__(self, folders: list[Path], config: PairConfig, canvas: int | None = None, orient: bool = False):
        self.config = config
        p = config.patch_size
        self.canvas = p if canvas is None else canvas
        self.train_pairs: list[tuple[np.ndarray, np.ndarray]] = []
        self.val_pairs: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        for folder in folders:
            frames = flight_frames(folder)
            images, sizes = [], []
            for path in frames:
                try:
                    gray = to_gray_u8(read_image(path))
                except UdhError:
                    continue
                sizes.append((gray.shape[1], gray.shape[0]))
                images.append((path.name, cv2.resize(gray, (p, p), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0, gray))
            references = _reference_homographies(folder)
            for i in range(len(images) - 1):
                (name_a, small_a, full_a), (name_b, small_b, full_b) = images[i], images[i + 1]
                if i % 5 == 4:
                    reference = references.get((name_a, name_b))
                    if reference is None:
                        reference = _sift_reference(full_a, full_b)
                    if reference is not None:
                        small = geometry.rescale_homography(reference, sizes[i], (p, p), sizes[i + 1], (p, p))
                        self.val_pairs.append((small_a, small_b, geometry.offsets_from_homography(small, p, p)))
                        continue
                self.train_pairs.append((small_a, small_b))
        if len(self.train_pairs) < 1:
            raise UdhError(f"found no usable consecutive frame pairs in {', '.join(map(str, folders))}; a flight needs at least 2 readable frames")
        turned = 0
        if orient:
            for i, turn in enumerate(half_turn_choices(self.train_pairs)):
                if turn:
                    a, b = self.train_pairs[i]
                    self.train_pairs[i] = (a, np.ascontiguousarray(b[::-1, ::-1]))
                    turned += 1
        self.description = f"{len(self.train_pairs)} consecutive real pairs ({len(self.val_pairs)} held out" + \
            (f", {turned} turned half a turn)" if orient else ")")

    def batch(self, rng: np.random.Generator, size: int, unsupervised: bool) -> Batch:
        p, c = self.config.patch_size, self.canvas
        at = (c - p) // 2
        patches = np.empty((size, 2, p, p), np.float32)
        context = np.zeros((size, 2, c, c), np.float32)
        clean_b = np.empty((size, p, p), np.float32)
        for i in range(size):
            a, b = self.train_pairs[rng.integers(len(self.train_pairs))]
            if rng.uniform() < 0.5:
                a, b = b, a
            turns, flip = int(rng.integers(4)), bool(rng.integers(2))
            a, b = (np.rot90(x, turns) for x in (a, b))
            if flip:
                a, b = a[:, ::-1], b[:, ::-1]
            context[i, 0, at:at + p, at:at + p], context[i, 1, at:at + p, at:at + p], clean_b[i] = a, 1.0, b
            seen_a, seen_b = (a, b) if not self.config.illumination else (illuminate(a, rng), illuminate(b, rng))
            patches[i, 0], patches[i, 1] = seen_a, seen_b
        return Batch(patches, None, context, np.full((size, 2), float(at), np.float32), clean_b)

    def validation(self, size: int, seed: int = 12345) -> Batch | None:
        if not self.val_pairs:
            return None
        chosen = self.val_pairs[:size]
        patches = np.stack([np.stack([a, b]) for a, b, _ in chosen]).astype(np.float32)
        offsets = np.stack([o for _, _, o in chosen]).astype(np.float32)
        return Batch(patches, offsets, patches[:, :1], np.zeros((len(chosen), 2), np.float32), patches[:, 1])


class MixedData:
    """Synthetic flight-motion pairs from image pools and real consecutive pairs from flights in every batch.

    Why: the pools teach motion with labels to validate on; the real pairs carry what no generator draws
    (a fixed-wing's low-texture fields, false colour, a camera's hot spot and the real motion between
    frames), and the photometric loss needs no labels for them: the paper's own advantage over supervised
    training. ``real_fraction`` of each batch is real. Validation is the pools' labelled set; the flights'
    held-out pairs (scored against SIFT references) are :meth:`real_validation`.
    """

    kind = "mixed"
    has_labels = False

    def __init__(self, pools: list[Path], flights: list[Path], config: PairConfig, real_fraction: float, source_side: int = 0):
        if config.motion is None:
            raise UdhError("mixing image pools and flights needs --motion flight: real consecutive frames are whole frames")
        from udh_cli.flight_motion import CONTEXT_FACTOR

        self.pool = PoolData(pools, config, source_side)
        self.flight = FlightData(flights, config, canvas=CONTEXT_FACTOR * config.patch_size, orient=True)
        self.real_fraction = real_fraction
        self.description = f"{self.pool.description} and {self.flight.description}, {real_fraction:.0%} of each batch real"

    def batch(self, rng: np.random.Generator, size: int, unsupervised: bool) -> Batch:
        real = int(round(size * self.real_fraction))
        parts = [data.batch(rng, n, unsupervised) for data, n in ((self.pool, size - real), (self.flight, real)) if n]
        if len(parts) == 1:
            return parts[0]
        return Batch(*(np.concatenate([getattr(part, name) for part in parts]) if name != "offsets" else None
                       for name in ("patches", "offsets", "context_a", "origin", "clean_b")))

    def validation(self, size: int, seed: int = 12345) -> Batch:
        return self.pool.validation(size, seed)

    def real_validation(self, size: int) -> Batch | None:
        return self.flight.validation(size)


def match_view(patch_size: int) -> tuple[int, int]:
    """(width, height) of the matching views for ``--patch-size`` P: P high, 4:3, the width a multiple of the
    descriptor cell (4 px) so that cells tile the view exactly."""
    return (patch_size * 4 // 3) // 4 * 4, patch_size


class MatchData:
    """Pairs of whole views with flight motion and their true homographies, for the ``matcher`` (``--mode match``).

    Each pair is two views of a pool image (:func:`~udh_cli.flight_motion.make_flight_frames`: turns, scale
    changes, low overlap, real-flight lighting) at the views' own 4:3 aspect, as the estimator shows a frame
    to the matcher. The synthetic warp is the only label. Every 10th image is held out for validation.
    ``offsets`` are the 4-point offsets of the true ``b_from_a`` in the views' pixels.
    """

    kind = "match"
    has_labels = True

    def __init__(self, folders: list[Path], config: PairConfig):
        if config.motion is None:
            raise UdhError("--mode match draws flight motion; add --motion flight")
        paths = [p for folder in folders for p in (flight_frames(folder) if is_flight_folder(folder) else list_images([folder]))]
        train_paths, held_out = split_holdout(sorted(paths))
        if len(train_paths) < 2 or not held_out:
            raise UdhError(f"found {len(paths)} images in {', '.join(map(str, folders))}; need at least 3 to train and hold one out")
        self.view = match_view(config.patch_size)
        self.motion: MotionConfig = config.motion
        self.illumination = config.illumination
        self.train = load_sources(train_paths, min_count=2, size_for=source_size)
        self.held_out = load_sources(held_out, min_count=1, size_for=source_size)
        self.description = f"{len(self.train)} images ({len(self.held_out)} held out), {self.view[0]}x{self.view[1]} views"

    def _batch(self, sources: list[np.ndarray], size: int, rng: np.random.Generator) -> Batch:
        frames_a, frames_b, truths = make_flight_frames(sources, size, self.motion, rng, self.view, self.illumination)
        patches = np.stack([frames_a, frames_b], 1).astype(np.float32) / 255.0
        offsets = geometry.offsets_from_homography(truths, *self.view).astype(np.float32)
        empty = np.zeros((size, 1, 1, 1), np.float32)
        return Batch(patches, offsets, empty, np.zeros((size, 2), np.float32), empty[:, 0])

    def batch(self, rng: np.random.Generator, size: int, unsupervised: bool) -> Batch:  # noqa: ARG002 - one kind of batch
        return self._batch(self.train, size, rng)

    def validation(self, size: int, seed: int = 12345) -> Batch:
        return self._batch(self.held_out, size, np.random.default_rng(seed))


def half_turn_choices(pairs: list[tuple[np.ndarray, np.ndarray]]) -> list[bool]:
    """For each (A, B) pair of P x P grey frames in [0, 1]: whether the shipped unsupervised network's
    heading search (B as given or turned half a turn, the better photometric score) answers with B turned.
    The network's own choice, not a label: no SIFT is involved."""
    from udh_cli.estimators import create_estimator

    estimator = create_estimator("unsupervised", tiles=False, refine_rounds=0, threads=1)
    found = estimator.estimate_many([(a, b) for a, b in pairs])
    turned = []
    for estimate in found:
        h = estimate.homography
        # The answer's rotation: a turn of more than a quarter means the half-turned view won.
        turned.append(h is not None and abs(np.degrees(np.arctan2(h[1, 0] - h[0, 1], h[0, 0] + h[1, 1]))) > 90.0)  # a failure: as given
    return turned


def _longer_side(width: int, height: int, side: int, least: tuple[int, int]) -> tuple[int, int]:
    """(width, height) with the longer side ``side``, the aspect kept, and never smaller than ``least``."""
    scale = max(side / max(width, height), least[0] / width, least[1] / height)
    return max(least[0], int(round(width * scale))), max(least[1], int(round(height * scale)))


def flight_frames(folder: Path) -> list[Path]:
    """The frames of a flight in order: its ``images/`` subfolder when there is one (the shared-data layout,
    whose top level also holds previews that are not frames), else the images directly in ``folder``."""
    frames_folder = folder / "images" if (folder / "images").is_dir() else folder
    return [p for p in list_images([frames_folder]) if p.parent == frames_folder]


def _reference_homographies(folder: Path) -> dict[tuple[str, str], np.ndarray]:
    candidates = [folder / "consecutive_pairs_sift_reference.csv", folder.parent / "consecutive_pairs_sift_reference.csv"]
    table = next((c for c in candidates if c.is_file()), candidates[0])
    found: dict[tuple[str, str], np.ndarray] = {}
    if not table.is_file():
        return found
    with table.open(newline="") as handle:
        for row in csv.DictReader(handle):
            try:  # a row without names or with a damaged matrix is skipped: SIFT is computed for that pair instead
                matrix = homography_from_values(parse_numbers(row["H_sift_ransac_1to2"] or ""), str(table))
                found[(row["img1"], row["img2"])] = matrix
            except (KeyError, ValueError, UdhError):
                continue
    return found


# Least SIFT confidence (its RANSAC inlier share) for a flight pair's reference to be trained against: a rule of the
# training data, so that tuning the mosaic's acceptance floor never changes what the networks learn from.
MIN_REFERENCE_CONFIDENCE = 0.2


def _sift_reference(gray_a: np.ndarray, gray_b: np.ndarray) -> np.ndarray | None:
    from udh_cli.estimators import create_estimator

    estimate = create_estimator("sift").estimate(gray_a, gray_b)
    return estimate.homography if estimate.ok and estimate.confidence > MIN_REFERENCE_CONFIDENCE else None


def open_data(folders: list[Path], kind: str, config: PairConfig, real_fraction: float = DEFAULT_REAL_FRACTION,
              source_side: int = 0) -> PoolData | FlightData | MixedData:
    """Open training folders as a pool of single images, as flights, or (auto, with both kinds among the
    folders) as both mixed with ``real_fraction`` of each batch from the flights (``kind``: auto, pool,
    flight)."""
    folders = [Path(f) for f in folders]
    for folder in folders:
        if not folder.is_dir():
            raise UdhError(f"{folder}: no such data folder")
    if kind == "auto":
        flights = [f for f in folders if is_flight_folder(f)]
        if flights and len(flights) < len(folders):
            return MixedData([f for f in folders if f not in flights], flights, config, real_fraction, source_side)
        kind = "flight" if flights else "pool"
    if kind == "pool":
        return PoolData(folders, config, source_side)
    if kind == "flight":
        return FlightData(folders, config)
    raise UdhError(f"unknown --data-kind '{kind}'; choose auto, pool or flight")
