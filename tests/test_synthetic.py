"""The synthetic pair generator: illumination shifts and occluders."""

from __future__ import annotations

import numpy as np

from conftest import textured_image
from udh_cli.synthetic import MAX_CLIPPED, illuminate


def test_illumination_changes_appearance_without_erasing_a_dark_patch():
    dark = textured_image(128, 128, seed=4).astype(np.float32) / 255 * 0.25  # a shadowed scene: values 0.04-0.2
    rng = np.random.default_rng(0)
    changed, kept_texture = 0, []
    for _ in range(200):
        out = illuminate(dark, rng)
        assert out.min() >= 0.0 and out.max() <= 1.0
        assert ((out <= 0.0) | (out >= 1.0)).mean() <= MAX_CLIPPED
        changed += not np.allclose(out, dark)
        kept_texture.append(np.corrcoef(out.ravel(), dark.ravel())[0, 1])
    assert changed >= 190  # almost every draw still shifts the lighting
    assert min(kept_texture) > 0.8  # and the content survives it (measured 0.86 at worst)


def test_unconstrained_shifts_would_have_erased_it():
    """The case the constraint exists for: contrast 1.4 and brightness -0.2 clip this patch to black."""
    dark = textured_image(128, 128, seed=4).astype(np.float32) / 255 * 0.25
    erased = np.clip((dark - 0.5) * 1.4 + 0.5 - 0.2, 0, 1)
    assert (erased == 0).mean() > 0.95


def test_occluders_cover_the_asked_share_of_pairs_and_leave_all_or_none_sets_unchanged():
    from udh_cli.synthetic import PairConfig, make_pairs

    sources = [textured_image(320, 240, seed=s) for s in range(3)]

    def draw(occluders):
        config = PairConfig(patch_size=64, rho=8.0, illumination=False, occluders=occluders)
        return make_pairs(sources, 200, config, np.random.default_rng(7), with_context=False)

    clean, half, every, flag = draw(0.0), draw(0.5), draw(1.0), draw(True)
    occluded_b = ~np.isclose(half.patch_b, half.clean_b).all(axis=(1, 2))
    assert 0.4 < occluded_b.mean() < 0.6  # each pair is occluded with probability 0.5
    assert np.isclose(clean.patch_b, clean.clean_b).all()
    assert (~np.isclose(every.patch_b, every.clean_b).all(axis=(1, 2))).all()
    # True means all, and draws no extra coin: benchmark sets made before the share existed are unchanged.
    np.testing.assert_array_equal(every.patch_a, flag.patch_a)
    np.testing.assert_array_equal(every.offsets, flag.offsets)
