"""The GCP file's pixel scale read from the frames, and the residual check that refuses a wrong one."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from udh_cli.errors import UdhError
from udh_cli.mosaic.georef.gcp import fit_gcps, read_gcp_file
from udh_cli.mosaic.georef.gcp_scale import check_gcp_fit, infer_gcp_scale, original_widths
from udh_cli.mosaic.inputs.metadata import FrameMetadata

pytest.importorskip("pyproj")

HEADER = "+proj=utm +zone=11 +ellps=WGS84 +datum=WGS84 +units=m +no_defs\n"


def _frame(name: str, size=(400, 300), original=None):
    metadata = None if original is None else FrameMetadata(original_width=original[0], original_height=original[1])
    return SimpleNamespace(name=name, size=size, metadata=metadata)


def _gcps(tmp_path, pixels: list[tuple[float, float, str]]):
    lines = [f"{100 + k} {200 + k} 0 {px} {py} {image} p{k}" for k, (px, py, image) in enumerate(pixels)]
    (tmp_path / "g.txt").write_text(HEADER + "\n".join(lines) + "\n")
    return read_gcp_file(tmp_path / "g.txt")


def test_points_outside_the_frames_with_an_exif_original_take_its_width(tmp_path):
    frames = [_frame("a.jpg", original=(1600, 1200)), _frame("b.jpg", original=(1600, 1200))]
    gcps = _gcps(tmp_path, [(1500, 1000, "a.jpg"), (100, 50, "b.jpg"), (800, 700, "b.jpg")])
    scale = infer_gcp_scale(gcps, frames, None, "g.txt")
    assert scale.image_width == 1600 and "2 of 3 observations fall outside" in scale.reason
    assert infer_gcp_scale(gcps, frames, 1234, "g.txt").image_width == 1234  # given: used as given


def test_exif_original_read_across_a_rotated_frame_and_of_another_aspect_ignored():
    assert original_widths([_frame("a.jpg", size=(300, 400), original=(1200, 1600))]) == {1200}
    assert original_widths([_frame("a.jpg", size=(400, 300), original=(1600, 1600))]) == set()
    assert original_widths([_frame("a.jpg", size=(400, 300), original=(400, 300))]) == set()  # not downscaled


def test_points_inside_the_frames_are_the_frames_own_unless_too_few_to_tell(tmp_path):
    frames = [_frame("a.jpg", original=(1600, 1200))]
    many = _gcps(tmp_path, [(10 + 40 * k, 20 + 25 * k, "a.jpg") for k in range(4)])
    assert infer_gcp_scale(many, frames, None, "g.txt").image_width is None  # (1/4)^2 per point: 4 points inside by chance is < 1 %
    few = _gcps(tmp_path, [(10, 20, "a.jpg")])
    with pytest.raises(UdhError, match=r"--gcp-image-width 400 or --gcp-image-width 1600"):
        infer_gcp_scale(few, frames, None, "g.txt")


def test_points_outside_with_nothing_to_scale_by_are_refused_with_the_option_named(tmp_path):
    gcps = _gcps(tmp_path, [(5000, 20, "a.jpg"), (10, 20, "a.jpg")])
    with pytest.raises(UdhError, match=r"1 of 2 observations fall outside their 400-px frames.*--gcp-image-width"):
        infer_gcp_scale(gcps, [_frame("a.jpg")], None, "g.txt")
    with pytest.raises(UdhError, match="both in the frames' pixels"):
        infer_gcp_scale(_gcps(tmp_path, [(9000, 20, "a.jpg")]), [_frame("a.jpg", original=(1600, 1200))], None, "g.txt")


def test_a_fit_another_scale_beats_by_far_is_refused(tmp_path):
    """Points measured on 800-px originals of 400-px frames placed side by side: read at the frames' own scale,
    every point inside its frame, the fit is metres off; at 800 px it is exact, so the wrong one is refused."""
    metres_per_px = 0.1
    offsets = {"a.jpg": 0.0, "b.jpg": 300.0, "c.jpg": 600.0}  # each frame's x on the mosaic, frame pixels
    rng = np.random.default_rng(0)
    rows = []
    for k in range(9):
        image = list(offsets)[k % 3]
        px, py = rng.uniform(10, 190), rng.uniform(10, 140)  # in the 400-px frame, and doubled still inside it
        east, north = 1000 + (offsets[image] + px) * metres_per_px, 5000 - py * metres_per_px
        rows.append(f"{east:.3f} {north:.3f} 0 {px * 2:.3f} {py * 2:.3f} {image} p{k}")  # marked on the 800-px originals
    (tmp_path / "g.txt").write_text(HEADER + "\n".join(rows) + "\n")
    gcps = read_gcp_file(tmp_path / "g.txt")
    frames = [_frame(name, original=(800, 600)) for name in offsets]
    placed = {name: ((400, 300), np.array([[1.0, 0, x], [0, 1, 0], [0, 0, 1]])) for name, x in offsets.items()}
    right = fit_gcps(gcps, placed, 800)
    assert right.checkpoint_rms_m < 0.01
    check_gcp_fit(right, lambda width: fit_gcps(gcps, placed, width), 800, frames)  # the right scale passes
    frames_own = [p for p in rows if float(p.split()[3]) < 400 and float(p.split()[4]) < 300]
    assert len(frames_own) == 9  # every point inside its frame at either scale: only the residuals tell
    wrong = fit_gcps(gcps, placed, None)
    assert wrong.checkpoint_rms_m > 2 * right.checkpoint_rms_m + 1.0
    with pytest.raises(UdhError, match=r"pixel scale is wrong, so no map is written; run again with --gcp-image-width 800"):
        check_gcp_fit(wrong, lambda width: fit_gcps(gcps, placed, width), None, frames)


@pytest.mark.slow  # a whole real flight
def test_copr_with_a_plain_gcp_file_is_placed_within_2_5_m(shared_data, tmp_path):
    """copr's GCP file is in the 4272-px originals, its frames 1600 px: the scale comes from the frames' EXIF,
    and the checkpoints (each point left out in turn) are within 2.5 m RMS."""
    import json

    from udh_cli.mosaic import MosaicConfig, run_mosaic

    copr = shared_data / "flights" / "copr"
    config = MosaicConfig(method="sift", preview=False, seams="central", exposure="none")  # pixels only: the placement is the same
    report = run_mosaic(copr / "images", tmp_path / "copr.png", config, gcp=copr / "gcp_list.txt")
    georeference = report["parts"][0]["georeference"]
    assert georeference["gcp_image_width"] == 4272
    assert georeference["gcp_checkpoint_rms_m"] <= 2.5
    assert json.loads((tmp_path / "copr.json").read_text())["parts"][0]["georeference"]["gcp_image_width"] == 4272
