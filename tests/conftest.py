"""Shared test helpers: deterministic textured images, pairs warped by a known homography, real data."""

from __future__ import annotations

from pathlib import Path

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


@pytest.fixture
def shared_data() -> Path:
    """The real data at ../shared/data next to the repository; skips the test when it is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data not found at {SHARED_DATA}")
    return SHARED_DATA


def export_tiny_network(folder: Path, arch: str, seed: int) -> Path:
    """An untrained 32-pixel ``arch`` network, saved as a checkpoint and exported like a real one."""
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
    return folder / f"{arch}.onnx"


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
