"""The synthetic pair generator's illumination shift."""

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
