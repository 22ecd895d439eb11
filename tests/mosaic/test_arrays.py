"""udh_cli.mosaic_images: arrays in, the mosaic and each frame's homography out, no files."""

from __future__ import annotations

import numpy as np
import pytest

import udh_cli
from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.images import read_image


def test_a_flight_as_arrays_gives_the_same_mosaic_as_its_folder(tmp_path, monkeypatch):
    from mosaic_flights import SMALL, make_flight
    from udh_cli.mosaic import MosaicConfig, run_mosaic

    paths = make_flight(tmp_path / "flight", SMALL, seed=3)
    frames = [read_image(p) for p in paths]
    monkeypatch.setenv("TMPDIR", str(tmp_path / "tmp"))  # where the temporary folder goes, to see it removed
    (tmp_path / "tmp").mkdir()
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", None)
    result = udh_cli.mosaic_images(frames, method="sift", overlap_per_frame=1)
    assert list((tmp_path / "tmp").iterdir()) == []  # no file left anywhere
    whole = run_mosaic(tmp_path / "flight", tmp_path / "whole.png", MosaicConfig(method="sift", overlap_per_frame=1, preview=False))
    assert result.summary["placed"] == whole["summary"]["placed"] == len(frames)
    assert result.image.shape == (whole["parts"][0]["height"], whole["parts"][0]["width"], 4) and result.image.dtype == np.uint8
    for mine, theirs in zip(result.homographies, whole["frames"]):
        np.testing.assert_allclose(mine, theirs["mosaic_from_frame"], atol=1e-6)
    assert result.parts == [0] * len(frames)
    # A frame's pixel lands where its homography says: the mosaic there has its colour.
    x, y = geometry.transform_points(result.homographies[2], np.array([[160.0, 120.0]]))[0]
    assert result.image[round(y), round(x), 3] == 255
    np.testing.assert_allclose(result.image[round(y), round(x), :3].astype(float), frames[2][120, 160].astype(float), atol=40)
    rgb = udh_cli.mosaic_images([f[..., ::-1] for f in frames], method="sift", overlap_per_frame=1, rgb=True)
    np.testing.assert_array_equal(rgb.image[..., :3], result.image[..., 2::-1])  # RGB in, RGBA out, same pixels


def test_bad_arrays_and_options_are_refused_with_their_position():
    good = np.zeros((64, 64, 3), np.uint8)
    with pytest.raises(UdhError, match="at least two images"):
        udh_cli.mosaic_images([good])
    with pytest.raises(UdhError, match="image 1 is float64 with shape"):
        udh_cli.mosaic_images([good, np.zeros((64, 64))])
    with pytest.raises(UdhError, match="unknown option.*colour"):
        udh_cli.mosaic_images([good, good], colour=True)
