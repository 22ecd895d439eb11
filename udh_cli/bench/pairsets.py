"""The pairs a benchmark runs on: synthetic sets drawn with the training generator, saved and reloaded.

A :class:`PairSet` holds, for N pairs, what each estimator is shown and the true ``b_from_a`` between
the images it is scored on. Synthetic sets come from :func:`udh_cli.synthetic.make_pairs`, the very
generator the networks train on, so the benchmark measures the training distribution.

Two inputs per synthetic pair (the issue asks for both, and the output names which one a row used):

* ``patch``: the two 128x128 patches, exactly as the networks see them.
* ``full``: the paper gave the classical methods the whole 320x240 image. A's full frame is the source
  warped into A's frame (``context_a[:, 0]``, black where A sees outside the source); B's full frame is
  the source image itself. Since ``context_a(x) = source(H x)`` with ``H = source_from_a``, the
  full-frame truth is ``b_from_a = H``, and a full-frame estimate is turned into patch pixels with
  ``T(-c0) H T(c0)`` (``c0`` = patch origin), so both inputs are scored at the same four patch corners.

  The patch perturbation, extrapolated over the whole frame, can put the horizon inside A's frame (at
  rho 45, for about a quarter of the pairs). Every estimator then rejects even the exact answer as
  degenerate (:func:`udh_cli.geometry.is_valid_homography` on A's frame). So A's frame is cropped to
  the largest window around the patch on which the true homography is valid (``full_window``); the
  whole frame whenever it is. The crop tells the estimator nothing about the motion.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from udh_cli import geometry, synthetic
from udh_cli.errors import UdhError
from udh_cli.files import write_output
from udh_cli.images import MIN_IMAGE_SIDE

CHUNK = 64  # pairs drawn per generator call; each chunk has its own seeded stream (see synthetic_set)
MIN_IMAGES = 5  # fewer held-out images than this make a set too narrow to say much about a method
DEFAULT_POOL = Path("..") / "shared" / "data" / "pools" / "rsscn7-aerial" / "images"  # relative to the cwd


@dataclass
class PairSet:
    """N pairs with ground truth.

    Attributes:
        name: what the set is, e.g. ``"rho 32"`` or a CSV file name; the table groups rows by it.
        images_a, images_b: N images each (any size; grey or BGR; uint8 or float in [0, 1]), the ``patch``
            input for synthetic sets and the given images for real pairs.
        truths: (N, 3, 3) true ``b_from_a`` between ``images_a[i]`` and ``images_b[i]``.
        rho: corner perturbation of a synthetic set, pixels; ``None`` for real pairs.
        full_a, full_b: N full 320x240 frames (uint8) for the ``full`` input, or ``None``.
        origin: (N, 2) patch origin ``(x0, y0)`` in the full frames, pixels; used with ``full_a``.
        full_window: (N, 4) int ``(left, top, right, bottom)``: the part of ``full_a[i]`` shown (see above).
        labels: N short names of the pairs (file names for real pairs).
    """

    name: str
    images_a: list[np.ndarray]
    images_b: list[np.ndarray]
    truths: np.ndarray
    rho: float | None = None
    full_a: list[np.ndarray] | None = None
    full_b: list[np.ndarray] | None = None
    origin: np.ndarray | None = None
    full_window: np.ndarray | None = None
    labels: list[str] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.images_a)

    def sizes_a(self) -> list[tuple[int, int]]:
        """N ``(width, height)`` of the scored image A."""
        return [(a.shape[1], a.shape[0]) for a in self.images_a]

    def no_motion(self) -> list[np.ndarray]:
        """N identity homographies (rescaled when A and B differ in size): the no-answer score."""
        out = []
        for a, b in zip(self.images_a, self.images_b):
            size_a, size_b = (a.shape[1], a.shape[0]), (b.shape[1], b.shape[0])
            out.append(geometry.rescale_homography(np.eye(3), size_a, size_a, size_a, size_b))
        return out

    def inputs(self, kind: str, indices: range | list[int]) -> list[tuple[np.ndarray, np.ndarray]]:
        """The image pairs shown to an estimator for ``kind`` ``"patch"`` (or ``"image"``) or ``"full"``."""
        if kind == "full":
            if self.full_a is None or self.full_b is None:
                raise UdhError(f"{self.name}: this pair set has no full frames; generate it with --mode full or both")
            return [(self._window(i), self.full_b[i]) for i in indices]
        return [(self.images_a[i], self.images_b[i]) for i in indices]

    def _window(self, i: int) -> np.ndarray:
        left, top, right, bottom = self.full_window[i]
        return self.full_a[i][top:bottom, left:right]

    def to_scored_frame(self, kind: str, index: int, b_from_a: np.ndarray | None) -> np.ndarray | None:
        """An estimate on input ``kind`` expressed between the scored images (the patches)."""
        if b_from_a is None or kind != "full":
            return b_from_a
        x0, y0 = (float(v) for v in self.origin[index])
        left, top = (float(v) for v in self.full_window[index][:2])
        return geometry.translation(-x0, -y0) @ b_from_a @ geometry.translation(x0 - left, y0 - top)


SIMULATED_SOURCES = 24  # ground images the simulator paints when no image folder is at hand


def simulated_sources(count: int, size_for=None) -> list[np.ndarray]:
    """``count`` grey uint8 ground images painted by the flight simulator (seeds 1000...), resized as
    :func:`udh_cli.synthetic.load_sources` would: a benchmark that runs anywhere, data or not."""
    import cv2

    from udh_cli.simulate import make_ground

    sources = []
    for k in range(count):
        grey = cv2.cvtColor(make_ground((640, 480), seed=1000 + k), cv2.COLOR_BGR2GRAY)
        size = synthetic.SOURCE_SIZE if size_for is None else size_for(640, 480)
        sources.append(cv2.resize(grey, size, interpolation=cv2.INTER_AREA))
    return sources


def held_out_sources(
    images: Path | None, default_pool: Path = DEFAULT_POOL, min_images: int = MIN_IMAGES, size_for=None,
) -> tuple[list[np.ndarray], str]:
    """Source images for a synthetic benchmark, as 320x240 grey uint8, and a description of where from.

    A folder the user names is taken as held out in full. Without one, the default pool (relative to
    the current folder) is split with :func:`udh_cli.synthetic.split_holdout` and only its held-out tenth
    is used, the images that training never sees. Where that pool is not (a fresh clone on its own), the
    simulator paints the sources (:func:`simulated_sources`).
    """
    if images is None:
        if not default_pool.is_dir():
            return simulated_sources(SIMULATED_SOURCES, size_for), (
                f"{SIMULATED_SOURCES} simulated ground images (udh_cli.simulate.make_ground; no --images given and "
                f"the default pool {default_pool} is not here)")
        _, paths = synthetic.split_holdout(synthetic.list_images(default_pool))
        where = f"{default_pool} (held-out split: every 10th image)"
    else:
        if not Path(images).is_dir():
            raise UdhError(f"{images}: no such folder; pass --images DIR with held-out images")
        paths = synthetic.list_images(Path(images))
        where = f"{images} (all images, taken as held out)"
    if not paths:
        raise UdhError(f"{images or default_pool}: no images found (JPEG, PNG or TIFF); pass --images DIR")
    try:
        sources = synthetic.load_sources(paths, min_count=min_images, size_for=size_for)
    except UdhError as exc:
        raise UdhError(f"{images or default_pool}: {exc}; pass --images DIR with more held-out images") from None
    return sources, f"{where}, {len(sources)} images"


PAIR_BYTES = 2 * 4 * (128 * 128 + 320 * 240)  # a pair's two patches and two frames, as float32 at most


def check_pairs_memory(count: int, sets: int) -> None:
    """Raise :class:`UdhError` naming ``--n`` when ``sets`` sets of ``count`` pairs would not fit in memory."""
    from udh_cli.budget import check_memory

    check_memory(count * sets * PAIR_BYTES, f"--n {count} pairs in {sets} set(s)", "lower --n")


def synthetic_set(
    sources: list[np.ndarray], rho: float, count: int, seed: int, illumination: bool = True,
    with_full: bool = False, patch_size: int = 128, occluders: bool = False,
) -> PairSet:
    """Draw ``count`` synthetic pairs at corner perturbation ``rho`` (pixels), deterministically from ``seed``.

    Pairs are drawn ``CHUNK`` at a time, chunk ``k`` from ``np.random.default_rng([seed, k])``, so memory
    stays bounded and the first pairs of a larger set equal a smaller set's. With ``illumination``, the
    full frames get their own brightness/contrast/gamma draw from the generator's distribution (the
    generator keeps the patch draws to itself), seeded from ``[seed, k, 1]``. ``occluders`` pastes the
    generator's random blobs on the patches (the full frames get none).
    """
    if count < 1:
        raise UdhError(f"--n {count}: need at least one pair")
    config = synthetic.PairConfig(patch_size=patch_size, rho=float(rho), illumination=illumination, occluders=occluders)
    patch_a, patch_b, truths, origin, full_a, full_b, windows = [], [], [], [], [], [], []
    for chunk, start in enumerate(range(0, count, CHUNK)):
        size = min(CHUNK, count - start)
        # Always draw a whole chunk (the generator's first draw depends on the count), keep what is needed.
        batch = synthetic.make_pairs(sources, CHUNK, config, np.random.default_rng([seed, chunk]), with_context=with_full)
        patch_a.extend(batch.patch_a[:size])
        patch_b.extend(batch.patch_b[:size])
        truths.append(batch.homographies()[:size])
        origin.append(batch.origin[:size])
        if with_full:
            light = np.random.default_rng([seed, chunk, 1])
            for i in range(size):
                frame_a = batch.context_a[i, 0] * batch.context_a[i, 1]  # black where A sees outside the source
                x0, y0 = batch.origin[i]
                windows.append(valid_window(source_from_patch(batch.offsets[i], x0, y0, patch_size), x0, y0, patch_size))
                frame_b = sources[batch.source_index[i]].astype(np.float32) / 255.0
                if illumination:
                    frame_a, frame_b = synthetic.illuminate(frame_a, light), synthetic.illuminate(frame_b, light)
                full_a.append(_to_u8(frame_a))
                full_b.append(_to_u8(frame_b))
    return PairSet(
        name=f"rho {rho:g}" + (" occluded" if occluders else ""), images_a=patch_a, images_b=patch_b, truths=np.concatenate(truths), rho=float(rho),
        full_a=full_a if with_full else None, full_b=full_b if with_full else None,
        origin=np.concatenate(origin), full_window=np.array(windows, np.int64) if with_full else None,
        labels=[str(i) for i in range(count)],
    )


FLIGHT_VIEW = (320, 240)  # whole frames of the flight-motion set, as the paper's full frames


def flight_set(sources: list[np.ndarray], count: int, seed: int, view: tuple[int, int] = FLIGHT_VIEW) -> PairSet:
    """``count`` pairs of whole ``view``-sized frames with real flight motion (:mod:`udh_cli.flight_motion`):
    any heading within the training range, scale changes, overlap down to its floor, flight lighting.
    Deterministic from ``seed``. Every method sees the whole frames."""
    from udh_cli.flight_motion import MotionConfig, make_flight_frames

    if count < 1:
        raise UdhError(f"--n {count}: need at least one pair")
    frames_a, frames_b, truths = make_flight_frames(sources, count, MotionConfig(), np.random.default_rng([seed, 7]), view)
    return PairSet(name=f"flight {view[0]}x{view[1]}", images_a=list(frames_a), images_b=list(frames_b), truths=truths,
                   labels=[str(i) for i in range(count)])


WINDOW_MARGINS = (None, 128, 96, 64, 48, 32, 16, 0)  # tried in turn around the patch; None = the whole frame


def source_from_patch(offsets: np.ndarray, x0: float, y0: float, patch_size: int) -> np.ndarray:
    """The full-frame truth ``source_from_a = T(c0) H_patch T(-c0)``, (3, 3), from a pair's ``offsets`` (4, 2)."""
    patch = geometry.homography_from_offsets(np.asarray(offsets, np.float64), patch_size, patch_size)
    return geometry.translation(x0, y0) @ patch @ geometry.translation(-x0, -y0)


def valid_window(b_from_a_full: np.ndarray, x0: float, y0: float, patch_size: int) -> tuple[int, int, int, int]:
    """The largest window ``(left, top, right, bottom)`` of A's 320x240 frame around the patch at
    ``(x0, y0)`` on which ``b_from_a_full`` is a valid homography (see the module docstring)."""
    w, h = synthetic.SOURCE_SIZE
    for margin in WINDOW_MARGINS:
        if margin is None:
            window = (0, 0, w, h)
        else:
            window = (max(0, int(x0) - margin), max(0, int(y0) - margin),
                      min(w, int(x0) + patch_size + margin), min(h, int(y0) + patch_size + margin))
        shifted = b_from_a_full @ geometry.translation(window[0], window[1])
        if geometry.is_valid_homography(shifted, window[2] - window[0], window[3] - window[1]):
            return window
    return window


def _to_u8(frame: np.ndarray) -> np.ndarray:
    return np.clip(frame * 255.0 + 0.5, 0, 255).astype(np.uint8)


def save_sets(path: str | Path, sets: list[PairSet], meta: dict, overwrite: bool = False) -> None:
    """Save synthetic sets to one ``.npz``, atomically.

    The arrays of all sets are concatenated, with a per-pair ``rho``. The keys ``patch_a``, ``patch_b``,
    ``offsets``, ``origin`` and ``source_index`` are those of :func:`udh_cli.synthetic.save_pairs`, so
    :func:`udh_cli.synthetic.load_pairs` reads the file too. ``full_a``/``full_b`` (uint8) are stored when
    every set has full frames. ``meta`` (how the pairs were made) is stored as JSON. An existing file is
    replaced only when udh wrote it, or with ``overwrite``.
    """
    if not sets or any(s.rho is None for s in sets):
        raise UdhError("only synthetic pair sets can be saved")
    patch_a = np.stack([a for s in sets for a in s.images_a]).astype(np.float32)
    arrays = {
        "patch_a": patch_a,
        "patch_b": np.stack([b for s in sets for b in s.images_b]).astype(np.float32),
        "offsets": np.concatenate([geometry.offsets_from_homography(s.truths, patch_a.shape[2], patch_a.shape[1])
                                   for s in sets]).astype(np.float32),
        "origin": np.concatenate([s.origin for s in sets]).astype(np.float32),
        "source_index": np.full(len(patch_a), -1, np.int64),  # not kept: the sources are identified by meta
        "rho": np.concatenate([np.full(len(s), s.rho) for s in sets]),
        "meta": np.array(json.dumps(meta)),
    }
    if all(s.full_a is not None for s in sets):
        arrays["full_a"] = np.stack([f for s in sets for f in s.full_a])
        arrays["full_b"] = np.stack([f for s in sets for f in s.full_b])
        arrays["full_window"] = np.concatenate([s.full_window for s in sets])
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    write_output(path, buffer.getvalue(), overwrite)


def _check_is_zip(path: str | Path) -> None:
    """An .npz is a zip archive: anything else (a CSV renamed, a single .npy) is refused here, in plain words,
    before numpy reads it as a pickle and answers with advice about allow_pickle."""
    path = Path(path)
    if not path.is_file():
        return  # load_pairs names the problem
    try:
        with path.open("rb") as handle:
            magic = handle.read(6)
    except OSError as exc:
        raise UdhError(f"{path}: cannot read it ({exc.strerror}); check its permissions") from None
    # A zip's first entry or an empty zip; a single .npy array is left to load_pairs, which names it.
    if magic[:4] not in (b"PK\x03\x04", b"PK\x05\x06") and magic != b"\x93NUMPY":
        raise UdhError(f"{path}: not a udh pair set (not an .npz archive); give an .npz written by --save-pairs")


def load_sets(path: str | Path) -> tuple[list[PairSet], dict]:
    """Load sets written by :func:`save_sets` (or a plain :func:`udh_cli.synthetic.save_pairs` file).

    Returns the sets, one per rho, and the stored ``meta`` (empty for a plain file).
    """
    _check_is_zip(path)
    batch = synthetic.load_pairs(path)  # checks shapes and finiteness of the shared keys
    with np.load(Path(path), allow_pickle=False) as data:
        n = len(batch.patch_a)
        rho = data["rho"] if "rho" in data else np.full(n, np.nan)
        full_a = data["full_a"] if "full_a" in data else None
        full_b = data["full_b"] if "full_b" in data else None
        window = data["full_window"] if "full_window" in data else None
        meta_text = str(data["meta"]) if "meta" in data else "{}"
    try:
        meta = json.loads(meta_text)
    except (ValueError, RecursionError):  # RecursionError: absurdly nested JSON
        meta = None
    if not isinstance(meta, dict):
        raise UdhError(f"{path}: the pair set's 'meta' entry is not a JSON object")
    if rho.shape != (n,) or rho.dtype.kind != "f" or (full_a is not None and (
            len(full_a) != n or full_b is None or full_b.shape != full_a.shape or window is None or window.shape != (n, 4))):
        raise UdhError(f"{path}: inconsistent shapes in the pair set")
    if full_a is not None:
        width, height = synthetic.SOURCE_SIZE
        left, top, right, bottom = window.T
        if (full_a.dtype != np.uint8 or full_b.dtype != np.uint8 or full_a.shape[1:3] != (height, width) or window.dtype.kind not in "iu"
                or np.any(left < 0) or np.any(top < 0) or np.any(right > width) or np.any(bottom > height)
                or np.any(right - left < MIN_IMAGE_SIDE) or np.any(bottom - top < MIN_IMAGE_SIDE)):
            raise UdhError(f"{path}: the full frames or their windows do not fit {width}x{height} uint8 frames")
    truths = batch.homographies()
    sets = []
    for value in _unique_in_order(rho):
        index = np.flatnonzero(rho == value) if np.isfinite(value) else np.flatnonzero(~np.isfinite(rho))
        known = bool(np.isfinite(value))
        sets.append(PairSet(
            name=f"rho {value:g}" if known else Path(path).stem, images_a=[batch.patch_a[i] for i in index],
            images_b=[batch.patch_b[i] for i in index], truths=truths[index], rho=float(value) if known else None,
            full_a=None if full_a is None else [full_a[i] for i in index],
            full_b=None if full_b is None else [full_b[i] for i in index],
            origin=batch.origin[index], full_window=None if window is None else window[index],
            labels=[str(i) for i in range(len(index))],
        ))
    return sets, meta


def _unique_in_order(values: np.ndarray) -> list[float]:
    seen: list[float] = []
    for v in values.tolist():
        if not any((v == s) or (v != v and s != s) for s in seen):
            seen.append(v)
    return seen
