"""Training: both losses learn, checkpoints resume exactly after a kill, bad input fails cleanly, torchrun works."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

torch = pytest.importorskip("torch")

from conftest import cached_copy, textured_image  # noqa: E402
from udh_cli.errors import UdhError  # noqa: E402
from udh_cli.train import losses  # noqa: E402
from udh_cli.train.checkpoint import load_checkpoint  # noqa: E402
from udh_cli.train.config import flight_motion  # noqa: E402
from udh_cli.train.loop import TrainConfig, Trainer, train  # noqa: E402

REPO = Path(__file__).resolve().parents[2]


def tiny_config(pool: Path, out: Path, **changes) -> TrainConfig:
    """32-pixel patches, rho 6: small enough to learn something in seconds on a CPU."""
    base = TrainConfig(data=[str(pool)], patch_size=32, rho=6.0, small_motion_fraction=0.0, steps=300, batch=32,
                       lr=2e-3, eval_every=100, checkpoint_every=100, val_pairs=64, out=str(out))
    return replace(base, **changes)


def read_metrics(out: Path) -> list[dict]:
    return [json.loads(line) for line in (out / "metrics.jsonl").read_text().splitlines() if line.strip()]


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["supervised", "unsupervised"])
def test_a_few_hundred_steps_lower_loss_and_corner_error(pool, mode):
    """The whole differentiable path (network, Tensor DLT, spatial transformer, losses) learns: 300 Adam
    steps on 64 fixed synthetic pairs must cut both the loss and the corner error."""
    from udh_cli.synthetic import PairConfig, list_images, load_sources, make_pairs
    from udh_cli.train.archs import create_model

    torch.manual_seed(0)
    sources = load_sources(list_images(pool))
    pairs = make_pairs(sources, 64, PairConfig(patch_size=32, rho=6.0, illumination=False), np.random.default_rng(0))
    patches = torch.from_numpy(np.stack([pairs.patch_a, pairs.patch_b], 1) - 0.5) / 0.25
    truth = torch.from_numpy(pairs.offsets)
    context, origin, clean_b = (torch.from_numpy(x) for x in (pairs.context_a, pairs.origin, pairs.clean_b))
    model = create_model("corr", patch_size=32)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)

    def loss_of(offsets):
        if mode == "supervised":
            return losses.supervised_loss(offsets, truth)
        return losses.photometric_loss(offsets, context, origin, clean_b)

    def measure():
        model.eval()
        with torch.no_grad():
            offsets = model(patches)
            result = float(loss_of(offsets)), float(losses.corner_error(offsets, truth).mean())
        model.train()
        return result

    loss_before, error_before = measure()
    for _ in range(300):
        optimizer.zero_grad()
        loss_of(model(patches)).backward()
        optimizer.step()
    loss_after, error_after = measure()
    assert 3.5 < error_before < 5.5  # about the identity's 0.765 * rho
    assert loss_after < 0.7 * loss_before
    assert error_after < 0.7 * error_before


def test_unsupervised_loss_is_zero_at_the_truth_and_grows_away_from_it(pool):
    from udh_cli.synthetic import PairConfig, list_images, load_sources, make_pairs

    sources = load_sources(list_images(pool)[:3])
    pairs = make_pairs(sources, 4, PairConfig(patch_size=64, rho=10, illumination=False), np.random.default_rng(1))
    context, origin = torch.from_numpy(pairs.context_a), torch.from_numpy(pairs.origin)
    clean_b, truth = torch.from_numpy(pairs.clean_b), torch.from_numpy(pairs.offsets)
    at_truth = losses.photometric_loss(truth, context, origin, clean_b).item()
    off_truth = losses.photometric_loss(truth + 3.0, context, origin, clean_b).item()
    assert at_truth < 0.01  # bilinear resampling noise only
    assert off_truth > 3 * at_truth


def test_contrast_loss_ignores_a_hot_spot_that_the_intensity_loss_follows(pool):
    """A bright blob fixed in B's frame (a lens hot spot) raises the intensity L1 at the truth by far more
    than the contrast L1, and in contrast space the truth still beats a 3-px error by more than 2x."""
    from udh_cli.synthetic import PairConfig, list_images, load_sources, make_pairs

    sources = load_sources(list_images(pool)[:3])
    pairs = make_pairs(sources, 4, PairConfig(patch_size=128, rho=10, illumination=False), np.random.default_rng(1))
    context, origin = torch.from_numpy(pairs.context_a), torch.from_numpy(pairs.origin)
    clean_b, truth = torch.from_numpy(pairs.clean_b), torch.from_numpy(pairs.offsets)
    yy, xx = torch.meshgrid(torch.arange(128.0), torch.arange(128.0), indexing="ij")
    hot_b = (clean_b + 0.3 * torch.exp(-((xx - 64) ** 2 + (yy - 64) ** 2) / (2 * 32.0 ** 2))).clamp(0, 1)

    def loss(offsets, b, space):
        return losses.photometric_loss(offsets, context, origin, b, space=space).item()

    intensity_rise = loss(truth, hot_b, "intensity") - loss(truth, clean_b, "intensity")
    contrast_rise = loss(truth, hot_b, "contrast") - loss(truth, clean_b, "contrast")
    intensity_scale, contrast_scale = loss(truth + 3.0, clean_b, "intensity"), loss(truth + 3.0, clean_b, "contrast")
    assert intensity_rise / intensity_scale > 5 * contrast_rise / contrast_scale
    assert loss(truth + 3.0, hot_b, "contrast") > 2 * loss(truth, hot_b, "contrast")
    with pytest.raises(ValueError, match="photometric space"):
        loss(truth, clean_b, "gradient")


def _interrupt_and_resume(pool: Path, tmp_path: Path, sig: int, slow_first_save: bool) -> None:
    """Train 60 steps straight; train the same run in a subprocess, send ``sig`` once its first checkpoint
    exists, resume it in this process: the weights, the Adam state and the log must equal the straight run's."""
    straight = tmp_path / "straight"  # the same straight run serves SIGKILL and SIGTERM: trained once per run
    cached_copy(straight, ("straight-run", str(pool)),
                lambda built: train(tiny_config(pool, built, steps=60, eval_every=20, checkpoint_every=20), threads=1, progress=False))
    interrupted = tmp_path / "interrupted"
    slow = ("import time, udh_cli.train.loop as loop; original = loop.Trainer.save\n"
            "def slow_save(self):\n    original(self); time.sleep(0.5 if self.step == 20 else 0)\n"
            "loop.Trainer.save = slow_save\n") if slow_first_save else ""
    script = (
        "import sys; sys.path[:0] = [%r, %r]; from test_train import tiny_config; from pathlib import Path;"
        "from udh_cli.train.loop import train\n" + slow +
        "train(tiny_config(Path(%r), Path(%r), steps=60, eval_every=20, checkpoint_every=20), threads=1, progress=False)"
    ) % (str(Path(__file__).parent), str(Path(__file__).parents[1]), str(pool), str(interrupted))
    process = subprocess.Popen([sys.executable, "-c", script], cwd=REPO, stderr=subprocess.DEVNULL)
    deadline = time.time() + 120
    while time.time() < deadline and not (interrupted / "checkpoint.pt").exists():
        time.sleep(0.02)
    process.send_signal(sig)
    assert process.wait(timeout=120) != 0
    assert 20 <= load_checkpoint(interrupted / "checkpoint.pt")["step"] < 60

    # No steps given on resume: the run goes on to its own planned total (60), into the --out given now.
    train(tiny_config(pool, interrupted, steps=None), resume=True, threads=1, progress=False)
    a, b = load_checkpoint(straight / "checkpoint.pt"), load_checkpoint(interrupted / "checkpoint.pt")
    assert a["step"] == b["step"] == 60
    for name, tensor in a["model"].items():
        assert torch.equal(tensor, b["model"][name]), name
    for key, value in a["optimizer"]["state"].items():
        for field, tensor in value.items():
            assert torch.equal(tensor, b["optimizer"]["state"][key][field]), (key, field)
    assert [m["step"] for m in read_metrics(interrupted)] == [m["step"] for m in read_metrics(straight)]


@pytest.mark.slow
def test_resume_after_kill_matches_an_uninterrupted_run(pool, tmp_path):
    """SIGKILL after the first checkpoint (held open half a second so the kill lands on it)."""
    _interrupt_and_resume(pool, tmp_path, signal.SIGKILL, slow_first_save=True)


@pytest.mark.slow
def test_nan_loss_stops_with_a_message_and_keeps_the_checkpoint(pool, tmp_path, monkeypatch):
    config = tiny_config(pool, tmp_path, steps=40, eval_every=20, checkpoint_every=20)
    trainer = Trainer(config, progress=False)
    real_loss = trainer._loss
    monkeypatch.setattr(trainer, "_loss", lambda t, o: real_loss(t, o) * (float("nan") if trainer.step >= 25 else 1.0))
    with pytest.raises(UdhError, match="loss became nan"):
        trainer.run()
    assert load_checkpoint(tmp_path / "checkpoint.pt")["step"] == 20


def test_bad_training_input_is_reported(tmp_path, pool):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(UdhError, match="need at least"):
        Trainer(tiny_config(empty, tmp_path / "a"), progress=False)
    small = tmp_path / "small"
    small.mkdir()
    cv2.imwrite(str(small / "one.png"), textured_image(64, 48))
    with pytest.raises(UdhError):
        Trainer(tiny_config(small, tmp_path / "b"), progress=False)
    with pytest.raises(UdhError, match="no checkpoint"):
        Trainer(tiny_config(pool, tmp_path / "c"), resume=True, progress=False)
    with pytest.raises(UdhError, match="unknown architecture"):
        Trainer(tiny_config(pool, tmp_path / "d", arch="resnet"), progress=False)


def test_foreign_and_corrupt_checkpoints_are_refused(tmp_path):
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"not a checkpoint at all")
    with pytest.raises(UdhError, match="not a readable"):
        load_checkpoint(corrupt)
    foreign = tmp_path / "foreign.pt"
    torch.save({"weights": torch.zeros(3)}, foreign)
    with pytest.raises(UdhError, match="not a udh checkpoint"):
        load_checkpoint(foreign)


def test_flight_reference_table_skips_damaged_rows(tmp_path):
    from udh_cli.train.data import _reference_homographies

    (tmp_path / "consecutive_pairs_sift_reference.csv").write_text(
        "img1,img2,H_sift_ransac_1to2\n"
        "a.jpg,b.jpg,2 0 10 0 2 0 0 0 2\n"  # kept, normalised to h33 = 1
        "b.jpg,c.jpg,nan 0 0 0 1 0 0 0 1\n"  # not finite: SIFT is computed for this pair instead
        "c.jpg,d.jpg,1 0 0 0 1\n"  # not nine numbers
    )
    found = _reference_homographies(tmp_path)
    assert list(found) == [("a.jpg", "b.jpg")]
    np.testing.assert_allclose(found[("a.jpg", "b.jpg")], [[1, 0, 5], [0, 1, 0], [0, 0, 1]])


@pytest.mark.slow
def test_torchrun_two_processes(pool, tmp_path):
    """`udh train` runs unchanged under torchrun with 2 CPU processes (gloo)."""
    out = tmp_path / "ddp"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    command = [sys.executable, "-m", "torch.distributed.run", "--nproc_per_node=2", "--standalone", "-m", "udh_cli",
               "train", "--data", str(pool), "--out", str(out), "--steps", "6", "--batch", "4", "--eval-every", "3", "--rho", "16"]
    result = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    state = load_checkpoint(out / "checkpoint.pt")
    assert state["step"] == 6
    assert len(state["rng_states"]) == 2  # each process's data stream is saved for an exact resume
    assert [m["step"] for m in read_metrics(out)] == [0, 3, 6]


def test_impossible_settings_and_outputs_are_refused_before_any_work(pool, tmp_path):
    for change in ({"batch": 0}, {"steps": 0}, {"rho": 0.0}):
        out = tmp_path / f"run_{list(change)[0]}"
        with pytest.raises(UdhError, match="must be"):
            Trainer(tiny_config(pool, out, **change), progress=False)
    a_file = tmp_path / "a.png"
    a_file.write_bytes(b"x")
    with pytest.raises(UdhError, match="is a file"):
        Trainer(tiny_config(pool, a_file), progress=False)
    assert a_file.read_bytes() == b"x"


@pytest.mark.slow
def test_distillation_pulls_the_student_towards_the_teacher(pool, tmp_path):
    """A student trained with --teacher ends far closer to the teacher's answers than the same run without,
    and a teacher that cannot serve (supervised mode, another patch size) is refused before any work."""
    from udh_cli.train.checkpoint import save_checkpoint

    # A teacher whose answer is known and wrong: every corner moved by (+3, -2) px, whatever the input.
    # The photometric loss alone leads elsewhere, so only the teacher term can bring the student there.
    teacher_run = tmp_path / "teacher"
    train(tiny_config(pool, teacher_run, steps=1), threads=1, progress=False)
    state = load_checkpoint(teacher_run / "checkpoint.pt")
    last = [k for k in state["model"] if k.startswith("head.") and k.endswith(".weight")][-1]  # in module order
    state["model"][last].zero_()
    state["model"][last.replace("weight", "bias")].copy_(torch.tensor([3.0, -2.0] * 4) / 32.0)
    teacher_ckpt = tmp_path / "constant_teacher.pt"
    save_checkpoint(teacher_ckpt, state)
    constant = torch.tensor([3.0, -2.0]).expand(4, 2)

    def distance_to_teacher(out: Path) -> float:
        trainer = Trainer(tiny_config(pool, out, steps=None), resume=True, threads=1, progress=False)
        norm = trainer.normalization
        patches = (torch.from_numpy(trainer.validation.patches) - norm["mean"]) / norm["std"]
        with torch.no_grad():
            predicted = trainer._bare_model().eval()(patches)
        return float(losses.distillation_loss(predicted, constant.expand_as(predicted)))

    plain, distilled = tmp_path / "plain", tmp_path / "distilled"
    train(tiny_config(pool, plain, steps=60), threads=1, progress=False)
    train(tiny_config(pool, distilled, steps=60, teacher=str(teacher_ckpt), teacher_weight=1.0), threads=1, progress=False)
    assert distance_to_teacher(distilled) < 0.5 * distance_to_teacher(plain)
    assert distance_to_teacher(distilled) < 1.0  # px
    assert load_checkpoint(distilled / "checkpoint.pt")["config"]["teacher"] == str(teacher_ckpt)

    with pytest.raises(UdhError, match="needs --mode unsupervised"):
        Trainer(tiny_config(pool, tmp_path / "sup", mode="supervised", teacher=str(teacher_ckpt)), progress=False)
    with pytest.raises(UdhError, match="32px patches, this run on 64px"):
        Trainer(tiny_config(pool, tmp_path / "big", patch_size=64, teacher=str(teacher_ckpt)), progress=False)
    for weight in (-1.0, 0.0):
        with pytest.raises(UdhError, match="--teacher-weight"):
            Trainer(tiny_config(pool, tmp_path / "neg", teacher=str(teacher_ckpt), teacher_weight=weight), progress=False)


@pytest.mark.slow
def test_sigterm_stops_at_a_step_boundary_and_resume_is_bit_identical(pool, tmp_path):
    """SIGTERM mid-run saves after a whole step (not mid-step); --resume then ends exactly as a straight run."""
    _interrupt_and_resume(pool, tmp_path, signal.SIGTERM, slow_first_save=False)


def test_an_out_holding_a_run_needs_resume_or_overwrite_and_one_run_at_a_time(pool, tmp_path):
    out = tmp_path / "run"
    train(tiny_config(pool, out, steps=10, eval_every=10, checkpoint_every=10), threads=1, progress=False)
    before = (out / "checkpoint.pt").read_bytes()
    with pytest.raises(UdhError, match="holds a run"):
        Trainer(tiny_config(pool, out, steps=5), progress=False)
    assert (out / "checkpoint.pt").read_bytes() == before  # refused before anything was touched
    from udh_cli.train.run_folder import lock_run_folder as _lock_run_folder

    held = _lock_run_folder(out)  # another process's run, as far as flock is concerned
    try:
        with pytest.raises(UdhError, match="another training"):
            Trainer(tiny_config(pool, out, steps=5), progress=False, overwrite=True)
    finally:
        held.close()
    train(tiny_config(pool, out, steps=5, eval_every=5, checkpoint_every=5), threads=1, progress=False, overwrite=True)
    assert load_checkpoint(out / "checkpoint.pt")["step"] == 5
    assert [m["step"] for m in read_metrics(out)] == [0, 5]  # no lines of the replaced run


def test_diverging_weights_stop_the_run_and_are_never_saved(pool, tmp_path):
    out = tmp_path / "run"
    train(tiny_config(pool, out, steps=10, eval_every=10, checkpoint_every=10), threads=1, progress=False)
    with pytest.raises(UdhError, match="became (nan|inf|NaN)|NaN or infinite"):
        train(tiny_config(pool, out, steps=30, lr=1e30), resume=True, threads=1, progress=False)
    kept = load_checkpoint(out / "checkpoint.pt")  # load_checkpoint refuses non-finite weights
    assert kept["step"] == 10


def test_a_new_lr_on_resume_is_honoured_and_said(pool, tmp_path):
    out = tmp_path / "run"
    train(tiny_config(pool, out, steps=10, eval_every=10, checkpoint_every=10), threads=1, progress=False)
    said: list[str] = []
    train(tiny_config(pool, out, steps=20, lr=1e-4), resume=True, threads=1, progress=False, on_note=said.append)
    assert load_checkpoint(out / "checkpoint.pt")["config"]["lr"] == 1e-4
    assert len(said) == 1 and "1e-04" in said[0].replace("0.0001", "1e-04")


def test_corr_global_starts_exactly_as_the_corr_network_it_widens():
    from udh_cli.train.archs import create_model, widen_from

    torch.manual_seed(0)
    old = create_model("corr", 64).eval()
    new = create_model("corr-global", 64).eval()
    assert widen_from(new, old.state_dict()) == ["regressor.0.0.weight"]
    patches = torch.rand(3, 2, 64, 64)
    assert torch.equal(old(patches), new(patches))
    with pytest.raises(KeyError):
        widen_from(create_model("corr-lite", 64), old.state_dict())


def test_flight_motion_training_runs_and_records_its_motion(pool, tmp_path):
    out = tmp_path / "flight"
    last = train(tiny_config(pool, out, patch_size=64, motion=flight_motion("flight", 6.0, max_heading=20.0), arch="corr-global", steps=4,
                             eval_every=2, checkpoint_every=2, val_pairs=8, batch=4), threads=1, progress=False)
    assert last["step"] == 4 and np.isfinite(last["val_mace_median"])
    assert load_checkpoint(out / "checkpoint.pt")["config"]["motion"]["max_heading"] == 20.0
    with pytest.raises(UdhError, match="flight motion out of range"):
        Trainer(tiny_config(pool, tmp_path / "bad", motion=flight_motion("flight", 6.0, max_heading=200.0)), progress=False)


def make_flight(folder: Path, frames: int = 6, shift: int = 12) -> Path:
    """A flight folder the test makes itself: overlapping 320x240 crops of one large image, each ``shift``
    px right of the last, with a manifest (the marker of a flight) and the true homographies as references."""
    folder.mkdir()
    (folder / "images").mkdir()
    world = textured_image(320 + shift * frames, 240, seed=7)
    rows = ["img1,img2,H_sift_ransac_1to2"]
    for i in range(frames):
        cv2.imwrite(str(folder / "images" / f"f{i:02d}.png"), world[:, i * shift : i * shift + 320])
        if i:
            rows.append(f"f{i - 1:02d}.png,f{i:02d}.png,1 0 {-shift} 0 1 0 0 0 1")
    (folder / "manifest.csv").write_text("file\n")
    (folder / "consecutive_pairs_sift_reference.csv").write_text("\n".join(rows) + "\n")
    return folder


def test_pools_and_flights_together_mix_real_pairs_into_flight_motion_batches(pool, tmp_path):
    """Real pairs join synthetic flight-motion pairs on the same 3P canvas, and the photometric loss of a real
    pair is lowest at its true motion: the loss can learn from it without labels."""
    from udh_cli.flight_motion import MotionConfig
    from udh_cli.synthetic import PairConfig
    from udh_cli.train.data import MixedData, open_data

    flight = make_flight(tmp_path / "flight")
    config = PairConfig(patch_size=32, rho=4.0, illumination=False, motion=MotionConfig())
    data = open_data([pool, flight], "auto", config, real_fraction=0.25)
    assert isinstance(data, MixedData)
    batch = data.batch(np.random.default_rng(0), 8, unsupervised=True)
    assert batch.patches.shape == (8, 2, 32, 32) and batch.context_a.shape == (8, 2, 96, 96) and batch.offsets is None
    np.testing.assert_array_equal(batch.origin, 32.0)  # A's frame in the middle of the canvas, for both kinds
    real_mask = batch.context_a[6:, 1]
    assert real_mask[:, 32:64, 32:64].min() == 1.0 and real_mask.sum() == 2 * 32 * 32  # no pixel outside A's frame is valid
    assert data.real_validation(8).patches.shape[0] == 1  # the 5th of 5 consecutive pairs is held out

    # The one real training-style pair, unaugmented: B shows A's content moved 12/320 of the frame left.
    a, b = data.flight.train_pairs[0]
    truth = np.array([[-12 * 32 / 320, 0.0]] * 4, np.float32)
    context = np.zeros((1, 2, 96, 96), np.float32)
    context[0, 0, 32:64, 32:64], context[0, 1, 32:64, 32:64] = a, 1.0
    args = (torch.from_numpy(context), torch.tensor([[32.0, 32.0]]), torch.from_numpy(b[None]))
    at_truth = float(losses.photometric_loss(torch.from_numpy(truth[None]), *args))
    at_identity = float(losses.photometric_loss(torch.zeros(1, 4, 2), *args))
    assert at_truth < 0.5 * at_identity

    with pytest.raises(UdhError, match="--motion flight"):
        open_data([pool, flight], "auto", PairConfig(patch_size=32), real_fraction=0.5)
    with pytest.raises(UdhError, match="--real-fraction"):
        Trainer(tiny_config(pool, tmp_path / "bad", real_fraction=1.5), progress=False)
    with pytest.raises(UdhError, match="--residual trains a later round on flight motion"):
        flight_motion("paper", 6.0, residual=8.0)
    with pytest.raises(UdhError, match="--residual 40"):
        Trainer(tiny_config(pool, tmp_path / "bad", motion=flight_motion("flight", 6.0, residual=40.0)), progress=False)


def test_pool_images_at_a_larger_side_give_pairs_from_windows_at_that_scale(pool, tmp_path):
    """--source-side 640: the 320x240 pool images are kept at 640x480 and pairs come from 320x240 windows,
    each a quarter of the image: the scene at twice the paper's scale."""
    from udh_cli.synthetic import PairConfig
    from udh_cli.train.data import PoolData

    data = PoolData([pool], PairConfig(patch_size=32, rho=6.0, illumination=False), source_side=640)
    assert {im.shape for im in data.train + data.held_out} == {(480, 640)}
    batch = data.batch(np.random.default_rng(0), 16, unsupervised=True)
    assert batch.context_a.shape == (16, 2, 240, 320) and np.abs(batch.offsets).max() <= 6.0
    assert data.validation(8).patches.shape == (8, 2, 32, 32)
    # The same scenes seen twice as large: the patches' texture is smoother, pixel for pixel.
    paper = PoolData([pool], PairConfig(patch_size=32, rho=6.0, illumination=False)).batch(np.random.default_rng(0), 64, unsupervised=False)
    larger = data.batch(np.random.default_rng(0), 64, unsupervised=False)

    def roughness(patches):
        return float(np.abs(np.diff(patches, axis=-1)).mean())

    assert roughness(larger.patches) < 0.7 * roughness(paper.patches)
    with pytest.raises(UdhError, match="--source-side"):
        Trainer(tiny_config(pool, tmp_path / "bad", source_side=100), progress=False)
    from udh_cli.flight_motion import MotionConfig

    with pytest.raises(UdhError, match="--motion flight uses whole frames"):
        PoolData([pool], PairConfig(patch_size=32, motion=MotionConfig()), source_side=640)


def test_a_real_pair_on_a_return_leg_is_turned_by_the_networks_own_heading_choice():
    """A strip's return leg: B is A's view turned half a turn. The shipped network's heading search picks the
    half turn for it, and not for the same pair unturned."""
    from udh_cli.train.data import half_turn_choices

    world = cv2.resize(textured_image(400, 300, seed=3), (128 + 16, 128), interpolation=cv2.INTER_AREA).astype(np.float32) / 255
    a, b = world[:, :128], world[:, 8:136]
    assert half_turn_choices([(a, b), (a, np.ascontiguousarray(b[::-1, ::-1]))]) == [False, True]


def test_export_refuses_its_own_checkpoint_and_a_non_onnx_name(tmp_path):
    from conftest import export_tiny_network
    from udh_cli.train.export import export_onnx

    onnx_path = export_tiny_network(tmp_path, "corr-global", seed=0, fresh=True)  # the widened network exports and matches torch
    checkpoint = tmp_path / "corr-global.pt"
    before = checkpoint.read_bytes()
    with pytest.raises(UdhError, match=r"\.onnx name"):
        export_onnx(checkpoint, checkpoint)
    same = tmp_path / "same.onnx"
    same.write_bytes(before)
    with pytest.raises(UdhError, match="is the checkpoint being exported"):
        export_onnx(same, same)
    assert checkpoint.read_bytes() == before and same.read_bytes() == before
    from udh_cli.onnx_model import OnnxHomographyModel

    assert OnnxHomographyModel.load(onnx_path).metadata["motion"] == "paper"


# A run stopped between two evaluations (SIGTERM, Ctrl-C) and resumed logs what the uninterrupted run logs.
STEPS, EVAL_EVERY, STOP_AT = 10, 8, 3  # stopped after step 3: the evaluation at step 8 averages steps 1-8
STOPPED_RUN = dict(steps=STEPS, eval_every=EVAL_EVERY, checkpoint_every=EVAL_EVERY, val_pairs=16, batch=8)


def logged_without_times(out) -> list[dict]:
    return [{k: v for k, v in record.items() if k != "time_s"} for record in read_metrics(out)]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["sigterm", "ctrl-c"])
def test_a_run_stopped_between_evaluations_then_resumed_logs_the_same_loss(sig, pool, tmp_path, monkeypatch):
    straight = tmp_path / "straight"
    train(tiny_config(pool, straight, **STOPPED_RUN), threads=1, progress=False)

    made = Trainer.__init__

    def signalled_during_step(self, *args, **kwargs):  # the signal arrives while step STOP_AT draws its batch
        made(self, *args, **kwargs)
        draw = self.data.batch

        def batch(rng, size, unsupervised):
            if self.step == STOP_AT - 1:
                os.kill(os.getpid(), sig)
            return draw(rng, size, unsupervised)

        self.data.batch = batch

    interrupted = tmp_path / "interrupted"
    with monkeypatch.context() as patch:
        patch.setattr(Trainer, "__init__", signalled_during_step)
        with pytest.raises(KeyboardInterrupt):
            train(tiny_config(pool, interrupted, **STOPPED_RUN), threads=1, progress=False)
    assert load_checkpoint(interrupted / "checkpoint.pt")["step"] == STOP_AT  # stopped between two evaluations
    train(tiny_config(pool, interrupted, **STOPPED_RUN), resume=True, threads=1, progress=False)
    assert [record["step"] for record in logged_without_times(interrupted)] == [0, EVAL_EVERY, STEPS]
    assert logged_without_times(interrupted) == logged_without_times(straight)  # the mean losses too, to the last bit
