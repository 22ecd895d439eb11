"""Shared test helpers: deterministic textured images, pairs warped by a known homography, real data, and a
per-run cache of expensive folders (tiny exported networks, simulated flights) handed out as copies."""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os

# One thread per native pool (torch's OpenMP, and every subprocess a test starts): tiny tensors gain nothing from
# more, and on a shared machine the idle threads spin on busy cores. Set before anything imports torch.
os.environ.setdefault("OMP_NUM_THREADS", "1")

import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Hashable, Iterator

import cv2
import numpy as np
import pytest

from udh_cli import geometry

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def textured_image(width: int = 320, height: int = 240, seed: int = 0) -> np.ndarray:
    """(height, width) uint8: smooth random noise (blur sigma 3 px) with filled discs and boxes on it.

    Enough texture for SIFT, ORB and ECC, and deterministic for a given ``seed``.
    """
    rng = np.random.default_rng(seed)
    noise = cv2.GaussianBlur(rng.random((height, width)).astype(np.float32), (0, 0), 3)
    image = ((noise - noise.min()) / (noise.max() - noise.min()) * 160 + 40).astype(np.uint8)
    for _ in range(width * height // 5000):
        centre = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        shade = int(rng.integers(0, 256))
        if rng.random() < 0.5:
            cv2.circle(image, centre, int(rng.integers(5, 25)), shade, -1)
        else:
            corner = (centre[0] + int(rng.integers(-40, 40)), centre[1] + int(rng.integers(-40, 40)))
            cv2.rectangle(image, centre, corner, shade, -1)
    return image


def warped_pair(b_from_a: np.ndarray, width: int = 320, height: int = 240, seed: int = 0, margin: int = 40):
    """Images A and B of one textured plane with ``x_B ~ b_from_a x_A``, neither with empty borders.

    Both are cut from a larger source S: A is S shifted by ``margin``, and B renders S through
    ``b_from_a @ T(-margin)``, so B's pixels all see real texture as long as the motion stays under the margin.
    """
    source = textured_image(width + 2 * margin, height + 2 * margin, seed)
    image_a = source[margin : margin + height, margin : margin + width].copy()
    b_from_source = b_from_a @ geometry.translation(-margin, -margin)
    image_b = cv2.warpPerspective(source, b_from_source, (width, height), flags=cv2.INTER_LINEAR)
    return image_a, image_b


@pytest.fixture(scope="module")
def pool(tmp_path_factory) -> Path:
    """A folder of 12 textured images the test makes itself (one in ten is held out by the split): training data."""
    folder = tmp_path_factory.mktemp("pool")
    for i in range(12):
        cv2.imwrite(str(folder / f"img{i:02d}.png"), textured_image(320, 240, seed=100 + i))
    return folder


@pytest.fixture
def shared_data() -> Path:
    """The real data at ../shared/data next to the repository; skips the test when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data not found at {SHARED_DATA}")
    return SHARED_DATA


class SessionCache:
    """Folders built once per test run and handed out as copies, so that a test may change its copy freely.

    Keyed by anything hashable with a stable ``repr``; ``build(folder)`` fills an empty folder. The parallel
    workers of one run (pytest-xdist) share ``root``: the first to need a key builds it under a lock while the
    others wait, and a folder appears under its key's name only once whole. Copies get fresh modification times,
    as if the files had just been written.
    """

    def __init__(self, root: Path) -> None:
        self.root = root
        self.built: dict[Hashable, Path] = {}

    def copy_into(self, folder: Path, key: Hashable, build: Callable[[Path], None]) -> None:
        """Fill ``folder`` (created if missing) with the files ``build`` makes, building them only on first use."""
        if key not in self.built:
            entry = self.root / hashlib.sha1(repr(key).encode()).hexdigest()[:16]
            with exclusive_lock(entry.with_name(entry.name + ".lock")):
                if not entry.is_dir():
                    build_atomically(entry, build)
            self.built[key] = entry
        shutil.copytree(self.built[key], folder, copy_function=shutil.copy, dirs_exist_ok=True)


@contextlib.contextmanager
def exclusive_lock(path: Path) -> Iterator[None]:
    """Hold an advisory lock on ``path`` (created if missing), where the platform has one: a parallel worker that
    needs the same folder waits for it rather than building it again."""
    try:
        import fcntl
    except ImportError:  # no flock: workers may build the same folder twice, and :func:`build_atomically` keeps one
        yield
        return
    with open(path, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def build_atomically(entry: Path, build: Callable[[Path], None]) -> None:
    """``build`` into a staging folder beside ``entry``, then rename it to ``entry``: a reader sees the whole folder
    or none. A skip or a failure leaves nothing half-built; losing the rename to another builder keeps theirs."""
    staged = Path(tempfile.mkdtemp(dir=entry.parent, prefix=".part-"))
    try:
        build(staged)
        staged.rename(entry)
    except OSError:
        if not entry.is_dir():
            raise
    finally:
        shutil.rmtree(staged, ignore_errors=True)


_session_cache: SessionCache | None = None


_network_store: Path | None = None


@pytest.fixture(scope="session", autouse=True)
def session_cache(tmp_path_factory, pytestconfig) -> SessionCache:
    """The run's :class:`SessionCache`, reachable from plain helpers such as :func:`export_tiny_network`.

    Under pytest-xdist every worker's temporary folder sits in the run's own, which holds the shared cache."""
    global _session_cache, _network_store
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = tmp_path_factory.getbasetemp().parent / "session-cache"
        root.mkdir(exist_ok=True)
    else:
        root = tmp_path_factory.mktemp("session-cache")
    _session_cache = SessionCache(root)
    cache = getattr(pytestconfig, "cache", None)  # absent with -p no:cacheprovider: every run exports afresh
    _network_store = None if cache is None else cache.mkdir("udh-tiny-networks")
    return _session_cache


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_auto_num_workers(config) -> int:
    """``-n auto``: one worker per core, at most 4: the longest test file bounds the run, and each worker holds
    its own torch and onnxruntime."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(cores, 4))


def cached_copy(folder: Path, key: Hashable, build: Callable[[Path], None]) -> None:
    """:meth:`SessionCache.copy_into` on the run's cache; builds straight into ``folder`` outside a pytest run."""
    if _session_cache is None:
        folder.mkdir(parents=True, exist_ok=True)
        build(folder)
    else:
        _session_cache.copy_into(folder, key, build)


def _export_tiny_network(folder: Path, arch: str, seed: int) -> None:
    torch = pytest.importorskip("torch")
    from udh_cli.train.archs import create_model
    from udh_cli.train.checkpoint import save_checkpoint
    from udh_cli.train.export import export_onnx
    from udh_cli.train.loop import TrainConfig
    from dataclasses import asdict

    torch.manual_seed(seed)
    model = create_model(arch, 32)
    config = asdict(TrainConfig(patch_size=32, data=["synthetic"], rho=8.0, arch=arch))
    save_checkpoint(folder / f"{arch}.pt", {"model": model.state_dict(), "config": config, "step": 0,
                                           "normalization": {"mean": 0.5, "std": 0.25}})
    real = np.stack([textured_image(32, 32, seed=1), textured_image(32, 32, seed=2)])[None].astype(np.float32) / 255
    result = export_onnx(folder / f"{arch}.pt", folder / f"{arch}.onnx", check_inputs=real)
    assert result["max_abs_diff"] < 1e-4
    assert result["metadata"]["input_size"] == "32" and result["metadata"]["arch"] == arch


@functools.cache
def _source_digest() -> str:
    """What a tiny network's files depend on: every udh_cli source file, this file, and the exporters' versions."""
    import onnxruntime
    import torch

    digest = hashlib.sha1(f"{torch.__version__} {onnxruntime.__version__}".encode())
    package = Path(__file__).resolve().parents[1] / "udh_cli"
    for path in [*sorted(package.rglob("*.py")), Path(__file__).resolve()]:
        digest.update(path.relative_to(package.parent).as_posix().encode() + path.read_bytes())
    return digest.hexdigest()[:16]


def _stored_tiny_network(folder: Path, arch: str, seed: int) -> None:
    """:func:`_export_tiny_network` into ``folder``, reusing the files of an earlier run while no source changed."""
    if _network_store is None:
        return _export_tiny_network(folder, arch, seed)
    entry = _network_store / f"{arch}-seed{seed}-{_source_digest()}"
    if not entry.is_dir():
        build_atomically(entry, lambda staged: _export_tiny_network(staged, arch, seed))
    shutil.copytree(entry, folder, copy_function=shutil.copy, dirs_exist_ok=True)


def export_tiny_network(folder: Path, arch: str, seed: int, fresh: bool = False) -> Path:
    """An untrained 32-pixel ``arch`` network, saved as ``folder/<arch>.pt`` and exported like a real one to
    ``folder/<arch>.onnx`` (parity with torch asserted); returns the latter.

    The export (seconds of torch tracing) runs once per ``(arch, seed)`` until a source file changes: the files
    are kept in pytest's cache folder between runs, and callers get copies. ``fresh`` exports now, for the tests
    of the export itself.
    """
    pytest.importorskip("torch")
    if fresh:
        _export_tiny_network(folder, arch, seed)
    else:
        cached_copy(folder, ("tiny-network", arch, seed), lambda built: _stored_tiny_network(built, arch, seed))
    return folder / f"{arch}.onnx"


@dataclass
class BlockDescriptors:
    """A stand-in matcher: each 4-px cell is described by the 12 x 12 pixels around it, mean removed and
    normalised, so that an image shifted by whole cells has exactly matching descriptors."""

    path: Path = Path("blocks")

    def describe(self, grey: np.ndarray) -> np.ndarray:
        padded = np.pad(grey, 4, mode="reflect")
        height, width = grey.shape[0] // 4, grey.shape[1] // 4
        blocks = np.stack([padded[4 * y : 4 * y + 12, 4 * x : 4 * x + 12].ravel() for y in range(height) for x in range(width)], 1)
        blocks = blocks - blocks.mean(0, keepdims=True)
        blocks = blocks / (np.linalg.norm(blocks, axis=0, keepdims=True) + 1e-9)
        return blocks.astype(np.float32).reshape(-1, height, width)


def run_main(monkeypatch, capfd, *args: str) -> tuple[int, str, str]:
    """Run the console entry point in-process; returns (exit code, stdout, stderr)."""
    import sys

    from udh_cli import cli

    monkeypatch.setattr(sys, "argv", ["udh", *args])
    with pytest.raises(SystemExit) as stop:
        cli.main()
    captured = capfd.readouterr()
    code = stop.value.code if isinstance(stop.value.code, int) else (0 if stop.value.code is None else 1)
    return code, captured.out, captured.err
