"""The matcher: ``udh train --mode match`` (loss, data, loop), its export and its loading for inference."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from udh_cli import geometry  # noqa: E402
from udh_cli.errors import UdhError  # noqa: E402
from udh_cli.onnx_model import OnnxHomographyModel, OnnxMatcher  # noqa: E402
from udh_cli.train import losses  # noqa: E402
from udh_cli.train.archs import create_model  # noqa: E402
from udh_cli.train.checkpoint import load_checkpoint  # noqa: E402
from udh_cli.train.data import match_view  # noqa: E402
from udh_cli.train.export import export_onnx  # noqa: E402
from udh_cli.train.config import flight_motion  # noqa: E402
from udh_cli.train.loop import TrainConfig, Trainer, train  # noqa: E402
from udh_cli.train.warm_start import init_arch  # noqa: E402


def match_config(pool: Path, out: Path, **changes) -> TrainConfig:
    base = dict(mode="match", arch="matcher", data=[str(pool)], motion=flight_motion("flight", 4.0, max_heading=20.0), patch_size=64, rho=4.0,
                steps=4, batch=2, eval_every=2, checkpoint_every=2, val_pairs=6, out=str(out))
    return TrainConfig(**{**base, **changes})


def test_the_views_are_four_by_three_in_whole_cells():
    assert match_view(192) == (256, 192)
    assert match_view(64) == (84, 64)


def test_the_matching_loss_is_low_for_descriptors_that_identify_cells_and_follows_the_truth():
    # One-hot descriptors of the scene's cells: A's cell (x, y) is scene cell (x + 2, y), which B shows at (x + 2, y - 1).
    height, width = 6, 8
    scene = torch.eye((height + 1) * (width + 2)).reshape(-1, height + 1, width + 2)
    features_a, features_b = scene[:, 0:height, 2 : 2 + width], scene[:, 1 : height + 1, 0:width]
    features = torch.stack([features_a, features_b])[None]  # 1, 2, C, h, w
    truth = torch.as_tensor(geometry.translation(8.0, -4.0))[None]  # 2 cells right, 1 up: 8 and 4 px
    wrong = torch.as_tensor(geometry.translation(-8.0, 4.0))[None]
    temperature = torch.tensor(np.log(30.0))
    torch.manual_seed(0)
    right_loss = losses.match_loss(features, truth, temperature, samples=64)
    torch.manual_seed(0)
    wrong_loss = losses.match_loss(features, wrong, temperature, samples=64)
    assert float(right_loss) < 0.01 and float(wrong_loss) > 3.0


def test_a_matcher_starts_from_a_trained_encoder_and_its_context_block_starts_as_the_identity():
    corr = create_model("corr", 128).eval()
    matcher = create_model("matcher").eval()
    from udh_cli.train.warm_start import load_encoder as _load_encoder

    _load_encoder(matcher, {"model": corr.state_dict(), "config": {"arch": "corr"}}, "test")
    images = torch.rand(2, 1, 64, 96)
    with torch.no_grad():
        expected = torch.nn.functional.normalize(corr.encoder(images), dim=1)
        np.testing.assert_allclose(matcher.describe(images).numpy(), expected.numpy(), atol=1e-6)
    assert matcher(torch.rand(3, 2, 64, 96)).shape == (3, 2, 64, 16, 24)


def test_match_training_learns_logs_its_matching_error_and_resumes(pool, tmp_path):
    out = tmp_path / "run"
    first = train(match_config(pool, out, steps=2, eval_every=2, checkpoint_every=2), threads=1, progress=False)
    last = train(match_config(pool, out, steps=30, eval_every=30, checkpoint_every=30, lr=1e-3), resume=True, threads=1, progress=False)
    assert first["step"] == 2 and last["step"] == 30
    for record in (first, last):
        assert {"val_mace_median", "val_fail_10px", "val_inliers_median"} <= record.keys()
        assert np.isfinite(record["val_mace_median"]) and record["val_identity_median"] > 0
    assert last["loss"] < first["loss"]  # the matching loss falls within a few dozen steps
    assert load_checkpoint(out / "checkpoint.pt")["config"]["mode"] == "match"


def test_match_mode_and_its_architecture_go_together(pool, tmp_path):
    assert init_arch(None, "match") == "matcher" and init_arch(None) == "corr"
    with pytest.raises(UdhError, match="do not go together"):
        Trainer(match_config(pool, tmp_path / "a", arch="corr"), progress=False)
    with pytest.raises(UdhError, match="do not go together"):
        Trainer(TrainConfig(data=[str(pool)], arch="matcher", out=str(tmp_path / "b")), progress=False)
    with pytest.raises(UdhError, match="--motion flight"):
        Trainer(match_config(pool, tmp_path / "c", motion=None), progress=False)
    with pytest.raises(UdhError, match="--teacher"):
        Trainer(match_config(pool, tmp_path / "d", teacher="unsupervised"), progress=False)


def test_an_exported_matcher_describes_frames_of_any_size_and_is_not_taken_for_a_homography_network(pool, tmp_path):
    out = tmp_path / "run"
    train(match_config(pool, out, steps=2), threads=1, progress=False)
    result = export_onnx(out / "best.pt", tmp_path / "matcher.onnx")
    assert result["max_abs_diff"] < 1e-3 and result["metadata"]["arch"] == "matcher"
    matcher = OnnxMatcher.load(tmp_path / "matcher.onnx", "cpu", 1)
    for height, width in ((64, 84), (120, 200)):
        described = matcher.describe(np.random.default_rng(0).random((height, width), dtype=np.float32))
        assert described.shape == (64, height // 4, width // 4)
        np.testing.assert_allclose(np.linalg.norm(described, axis=0), 1.0, atol=1e-4)
    with pytest.raises(UdhError, match="sides multiples of 4"):
        matcher.describe(np.zeros((65, 84), np.float32))
    with pytest.raises(UdhError, match="is a matcher"):
        OnnxHomographyModel.load(tmp_path / "matcher.onnx")
