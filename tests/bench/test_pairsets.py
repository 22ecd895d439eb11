"""Synthetic benchmark pairs: deterministic from the seed, full-frame geometry, save/load, and the
identity's known error."""

from __future__ import annotations

import math

import numpy as np
import pytest

from udh_cli import geometry
from udh_cli.bench import pairsets
from udh_cli.bench.runner import make_jobs, run_jobs
from udh_cli.errors import UdhError

from conftest import textured_image


@pytest.fixture(scope="module")
def sources() -> list[np.ndarray]:
    return [textured_image(320, 240, seed=s) for s in range(6)]


def test_fixed_seed_reproduces_the_pairs_and_a_shorter_set_is_a_prefix(sources):
    first = pairsets.synthetic_set(sources, 32, 70, seed=5)  # 70 pairs: two generator chunks
    again = pairsets.synthetic_set(sources, 32, 70, seed=5)
    short = pairsets.synthetic_set(sources, 32, 10, seed=5)
    other = pairsets.synthetic_set(sources, 32, 70, seed=6)
    assert np.array_equal(np.stack(first.images_a), np.stack(again.images_a))
    assert np.array_equal(np.stack(first.images_b), np.stack(again.images_b))
    assert np.array_equal(first.truths, again.truths)
    assert np.array_equal(first.truths[:10], short.truths)
    assert not np.allclose(first.truths, other.truths)


def test_full_frames_hold_the_patch_and_their_truth_maps_back_to_the_patch_truth(sources):
    pair_set = pairsets.synthetic_set(sources, 45, 40, seed=1, illumination=False, with_full=True)
    cropped = 0
    for i in range(len(pair_set)):
        assert geometry.is_valid_homography(pair_set.truths[i], 128, 128)  # the generator redraws folded quads
        x0, y0 = (int(v) for v in pair_set.origin[i])
        left, top, right, bottom = pair_set.full_window[i]
        cropped += (left, top, right, bottom) != (0, 0, 320, 240)
        frame_a, frame_b = pair_set.inputs("full", [i])[0]
        # A's window shows the (clean) patch A at the patch origin; B's frame is the source.
        patch_in_frame = frame_a[y0 - top : y0 - top + 128, x0 - left : x0 - left + 128].astype(np.float32) / 255
        assert np.abs(patch_in_frame - pair_set.images_a[i]).max() <= 1.0 / 255 + 1e-6
        assert any(np.array_equal(frame_b, source) for source in sources)
        # The exact full-frame answer (shown A = the window) scores zero at the patch corners.
        exact = pairsets.source_from_patch(geometry.offsets_from_homography(pair_set.truths[i], 128, 128), x0, y0, 128)
        exact_on_window = exact @ geometry.translation(left, top)
        assert geometry.is_valid_homography(exact_on_window, right - left, bottom - top)
        scored = pair_set.to_scored_frame("full", i, exact_on_window)
        assert float(geometry.mace(scored, pair_set.truths[i], 128, 128)) < 1e-6
    assert 0 < cropped < len(pair_set)  # at rho 45 some frames need the crop, most do not


def test_save_and_load_round_trip_with_full_frames(sources, tmp_path):
    sets = [pairsets.synthetic_set(sources, rho, 5, seed=2, with_full=True) for rho in (16, 32)]
    path = tmp_path / "pairs.npz"
    pairsets.save_sets(path, sets, {"seed": 2})
    loaded, meta = pairsets.load_sets(path)
    assert meta == {"seed": 2} and [s.name for s in loaded] == ["rho 16", "rho 32"]
    for original, back in zip(sets, loaded):
        assert back.rho == original.rho
        assert np.array_equal(np.stack(back.images_a), np.stack(original.images_a))
        np.testing.assert_allclose(back.truths, original.truths, atol=1e-4)  # offsets are stored as float32
        assert np.array_equal(back.full_window, original.full_window)
        assert np.array_equal(np.stack(back.full_a), np.stack(original.full_a))


def test_identity_mace_matches_the_uniform_expectation(sources):
    # Each corner offset is uniform in [-rho, rho]^2: E|d| = rho (sqrt(2) + ln(1 + sqrt(2))) / 3.
    rho = 32.0
    expected = rho * (math.sqrt(2) + math.log(1 + math.sqrt(2))) / 3
    pair_set = pairsets.synthetic_set(sources, rho, 2000, seed=0, illumination=False)
    (run,) = run_jobs(make_jobs(["identity"], ["patch"], []), [pair_set], show_progress=False)
    assert expected == pytest.approx(0.7652 * rho, rel=1e-4)
    assert run.summary.mace_mean == pytest.approx(expected, rel=0.02)
    assert run.summary.failure_rate == pytest.approx(1.0, abs=0.01)  # 24 px on average: nearly all over 10 px


def _arrays(n: int = 2, size: int = 128) -> dict:
    return {"patch_a": np.zeros((n, size, size), np.float32), "patch_b": np.zeros((n, size, size), np.float32),
            "offsets": np.zeros((n, 4, 2), np.float32), "origin": np.zeros((n, 2), np.float32), "source_index": np.zeros(n, np.int64)}


@pytest.mark.parametrize(("case", "message"), [
    ("npy", "a single array, not an .npz"),
    ("truncated", "BadZipFile"),
    ("empty_set", "inconsistent shapes"),
    ("not_square", "inconsistent shapes"),
    ("origin", "inconsistent shapes"),
    ("meta", "'meta' entry is not a JSON object"),
    ("window", "windows do not fit"),
])
def test_damaged_pair_set_files_are_one_clear_error(tmp_path, case, message):
    path = tmp_path / "set.npz"
    if case == "npy":
        path = tmp_path / "set.npy"
        np.save(path, np.zeros(3))
    elif case == "truncated":
        path.write_bytes(b"PK\x03\x04" + b"x" * 100)
    else:
        arrays = _arrays(0) if case == "empty_set" else _arrays(2, 64) if case == "not_square" else _arrays()
        arrays["patch_a"] = arrays["patch_a"][:, :, :32] if case == "not_square" else arrays["patch_a"]
        if case == "origin":
            arrays["origin"] = np.zeros(2, np.float32)
        if case == "meta":
            arrays.update(rho=np.full(2, 32.0), meta=np.array("{not json"))
        if case == "window":
            arrays.update(rho=np.full(2, 32.0), full_a=np.zeros((2, 240, 320), np.uint8), full_b=np.zeros((2, 240, 320), np.uint8),
                          full_window=np.array([[0, 0, 320, 240], [10, 10, 10, 10]]))
        np.savez(path, **arrays)
    with pytest.raises(UdhError, match=message):
        pairsets.load_sets(path)


def test_flight_set_frames_are_aligned_by_their_truths():
    from udh_cli.bench.pairsets import flight_set, simulated_sources
    from udh_cli.flight_motion import source_size
    from udh_cli.estimators.verify import alignment_ncc

    sources = simulated_sources(4, size_for=source_size)
    pairs = flight_set(sources, 12, seed=3)
    assert pairs.name == "flight 320x240" and len(pairs) == 12
    assert pairs.images_a[0].shape == (240, 320) and pairs.images_a[0].dtype == np.uint8
    scores = [alignment_ncc(a.astype(np.float32) / 255, b.astype(np.float32) / 255, h, min_overlap=0.2)
              for a, b, h in zip(pairs.images_a, pairs.images_b, pairs.truths)]
    shifted = [alignment_ncc(a.astype(np.float32) / 255, b.astype(np.float32) / 255, h @ np.array([[1, 0, 8.0], [0, 1, 0], [0, 0, 1]]), min_overlap=0.2)
               for a, b, h in zip(pairs.images_a, pairs.images_b, pairs.truths)]
    assert np.median(scores) > 0.5 and np.median(scores) > np.median(shifted) + 0.2
    again = flight_set(sources, 12, seed=3)
    assert np.array_equal(again.truths, pairs.truths)


def test_the_benchmark_runs_without_any_image_folder(tmp_path, monkeypatch):
    from udh_cli.bench.pairsets import held_out_sources

    monkeypatch.chdir(tmp_path)  # no ../shared/data here
    sources, where = held_out_sources(None)
    assert len(sources) == 24 and sources[0].shape == (240, 320) and "simulated" in where
