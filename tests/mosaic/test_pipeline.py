"""run_mosaic end to end on simulated flights: accuracy against ground truth, the sidecar, bounded canvases."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.mosaic import MosaicConfig, run_mosaic
from udh_cli.mosaic.render.composite import plan_canvas
from udh_cli.simulate import load_ground_truth

from conftest import run_main
from mosaic_flights import ACCURATE, SMALL, make_flight


@pytest.fixture(scope="module")
def accurate_run(tmp_path_factory):
    """SIFT over a 10-frame, two-line flight at 480x360 (the configuration the README example scales up)."""
    folder = tmp_path_factory.mktemp("flight")
    make_flight(folder, ACCURATE, seed=3)
    out = tmp_path_factory.mktemp("out") / "mosaic.png"
    report = run_mosaic(folder, out, MosaicConfig(method="sift"))
    return folder, out, report


def test_every_frame_within_one_pixel_of_truth_after_the_solve(accurate_run):
    folder, _, report = accurate_run
    truth = load_ground_truth(folder / "ground_truth.json")
    assert report["summary"]["placed"] == 10 and report["summary"]["parts"] == 1
    # Recompute the error from the sidecar alone: frame->reference homographies against the truth
    # (the mosaic is anchored at the reference frame, so this is the gauge-free comparison).
    frames = report["frames"]
    reference = report["parts"][0]["reference_frame"]
    mosaic_from_ref = np.asarray(frames[reference]["mosaic_from_frame"])
    ref_from_ground = geometry.invert(truth["ground_from_frame"][frames[reference]["file"]])
    errors = []
    for frame in frames:
        ref_from_frame = geometry.invert(mosaic_from_ref) @ np.asarray(frame["mosaic_from_frame"])
        true = ref_from_ground @ truth["ground_from_frame"][frame["file"]]
        errors.append(float(geometry.corner_errors(ref_from_frame, true / true[2, 2], frame["width"], frame["height"]).max()))
    assert max(errors) <= 1.0
    assert report["ground_truth_error"]["solved"]["max_corner_px"] == pytest.approx(max(errors), abs=1e-6)
    # The solve improves on plain chaining, and closes the loops.
    assert report["ground_truth_error"]["solved"]["mean_corner_px"] < report["ground_truth_error"]["chained"]["mean_corner_px"]
    loops = report["loop_consistency"]
    assert loops["loops_after"]["count"] >= 5
    assert loops["loops_after"]["max_px"] < loops["loops_before"]["max_px"]
    assert loops["loops_after"]["max_px"] < 0.5


def test_sidecar_contents(accurate_run):
    _, out, report = accurate_run
    sidecar = json.loads(out.with_suffix(".json").read_text())
    assert sidecar["format"] == "udh-mosaic/1" and sidecar["method"] == "sift"
    assert set(sidecar) >= {"frames", "pairs", "parts", "loop_consistency", "summary", "timings_s", "warnings", "config", "skipped_files"}
    mosaic = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert mosaic.shape[2] == 4  # alpha channel
    part = sidecar["parts"][0]
    assert (part["width"], part["height"]) == (mosaic.shape[1], mosaic.shape[0]) and part["scale"] == 1.0
    assert out.with_name("mosaic.preview.jpg").is_file()
    for frame in sidecar["frames"]:
        assert frame["status"] == "placed" and frame["part"] == 1 and 0.5 < frame["gain"] < 2
        h = np.asarray(frame["mosaic_from_frame"])
        quad = geometry.transform_points(h, geometry.image_corners(frame["width"], frame["height"]))
        assert quad.min() >= -0.5 and quad[:, 0].max() <= mosaic.shape[1] - 0.5 and quad[:, 1].max() <= mosaic.shape[0] - 0.5
        # The frame's centre pixel is covered, and the mosaic shows the same grey level there (gain aside).
        centre = geometry.transform_points(h, np.array([[frame["width"] / 2, frame["height"] / 2]]))[0]
        x, y = np.round(centre).astype(int)
        assert mosaic[y, x, 3] == 255
    consecutive = [p for p in sidecar["pairs"] if p["kind"] == "consecutive"]
    assert [(p["a"], p["b"]) for p in consecutive] == [(i, i + 1) for i in range(9)]
    for pair in sidecar["pairs"]:
        assert pair["status"] in ("ok", "failed", "rejected")
        assert pair["estimates"] and {"method", "confidence", "homography", "ok", "failure"} <= set(pair["estimates"][0])
        if pair["status"] == "ok":
            assert 0 < pair["confidence"] <= 1 and np.asarray(pair["b_from_a"]).shape == (3, 3)
            assert pair["consistency_px"]["after"] < 1.0
    assert any(p["kind"] == "overlap" and p["prewarped"] for p in sidecar["pairs"])
    assert {"reading frames", "consecutive pairs", "global solve", "compositing", "total"} <= set(sidecar["timings_s"])


def test_mosaic_pixels_agree_with_the_frames(accurate_run):
    folder, out, report = accurate_run
    mosaic = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    frame = report["frames"][3]
    image = cv2.imread(str(folder / frame["file"]))
    warped = cv2.warpPerspective(image, np.asarray(frame["mosaic_from_frame"]), (mosaic.shape[1], mosaic.shape[0]))
    inside = cv2.warpPerspective(np.full(image.shape[:2], 255, np.uint8), np.asarray(frame["mosaic_from_frame"]), (mosaic.shape[1], mosaic.shape[0]))
    inside = cv2.erode(inside, np.ones((15, 15), np.uint8)) > 0
    grey_m = cv2.cvtColor(mosaic[..., :3], cv2.COLOR_BGR2GRAY)[inside].astype(np.float32)
    grey_f = cv2.cvtColor(warped, cv2.COLOR_BGR2GRAY)[inside].astype(np.float32)
    assert np.corrcoef(grey_m, grey_f)[0, 1] > 0.9  # aligned: blending never averages misregistered texture


@pytest.fixture(scope="module")
def small_flight(tmp_path_factory):
    folder = tmp_path_factory.mktemp("small")
    make_flight(folder, SMALL, seed=4)
    return folder


def test_max_size_bounds_the_canvas(small_flight, tmp_path):
    out = tmp_path / "small.png"
    report = run_mosaic(small_flight, out, MosaicConfig(method="sift", max_size=300, overlap_per_frame=1, blend="multiband"))
    mosaic = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert max(mosaic.shape[:2]) == 300
    assert report["parts"][0]["scale"] < 1.0
    assert report["ground_truth_error"]["solved"]["max_corner_px"] < 3  # measured in reference pixels, not canvas pixels


def test_too_big_canvas_is_refused_before_writing(small_flight, tmp_path):
    out = tmp_path / "big.png"
    with pytest.raises(UdhError, match="--max-size"):
        run_mosaic(small_flight, out, MosaicConfig(method="orb", overlap_per_frame=0, max_canvas_bytes=100_000), resume=True)
    # No image and no sidecar; only the pair cache (--resume), so that the fix (--max-size) need not estimate again.
    assert [p.name for p in tmp_path.iterdir()] == ["big.pairs.json"]
    report = run_mosaic(small_flight, out, MosaicConfig(method="orb", overlap_per_frame=0, max_size=200), resume=True)
    assert report["summary"]["pairs_from_cache"] == len(report["pairs"]) == 7
    ref_from = {0: np.eye(3), 1: geometry.translation(1e7, 0.0)}
    with pytest.raises(UdhError, match="would be 10000640x240"):  # 9 GiB assembled
        plan_canvas(ref_from, [(640, 240), (640, 240)], "feather")


def test_mosaics_search_for_large_motion_and_skip_autos_views_unless_told_otherwise():
    from udh_cli.estimators import create_estimator
    from udh_cli.mosaic.config import MOSAIC_SEARCH, mosaic_method_options

    assert mosaic_method_options("unsupervised", {}) == {"search": MOSAIC_SEARCH}
    assert mosaic_method_options("auto", {"model": "m.onnx"}) == {"network": {"model": "m.onnx", "search": MOSAIC_SEARCH}, "views": ()}
    assert mosaic_method_options("unsupervised", {"search": 0}) == {"search": 0}
    assert mosaic_method_options("sift", {"ratio": 0.8}) == {"ratio": 0.8}
    assert mosaic_method_options("auto", {"views": ["flipped"]})["views"] == ["flipped"]  # the user's choice stands
    # auto on its own still asks the views; in a mosaic its opinions end with the escalated network.
    assert [o.key for o in create_estimator("auto").opinions] == ["fallback", "escalated", "mirrored", "flipped", "swapped"]
    assert [o.key for o in create_estimator("auto", **mosaic_method_options("auto", {})).opinions] == ["fallback", "escalated"]


def test_the_pair_cache_knows_both_networks_of_a_cascade_inside_auto():
    from udh_cli.estimators import create_estimator
    from udh_cli.models_catalog import models_dir
    from udh_cli.mosaic.pairs.cache import estimator_identity

    if not (models_dir() / "udh-unsupervised-refine-int8.onnx").is_file():
        pytest.skip("shipped refinement model not built yet")

    def files(**options) -> set[str]:
        return {path.split("/")[-1] for path, _, _ in estimator_identity(create_estimator("auto", **options))["files"]}

    # Retraining (or requantizing) either network re-estimates; so does switching precision.
    flight = {"udh-unsupervised-flight-int8.onnx"} if (models_dir() / "udh-unsupervised-flight-int8.onnx").is_file() else set()
    assert files() == {"udh-unsupervised-int8.onnx", "udh-unsupervised-refine-int8.onnx"} | flight
    assert files(precision="fp32") == {"udh-unsupervised.onnx", "udh-unsupervised-refine.onnx"} | {f.replace("-int8", "") for f in flight}
    # The default and an explicit int8 are the same estimator: a resumed mosaic keeps its pairs.
    assert estimator_identity(create_estimator("auto")) == estimator_identity(create_estimator("auto", precision="int8"))


def test_options_reach_the_fallback_in_the_one_syntax(small_flight, tmp_path, monkeypatch):
    """udh mosaic -O: METHOD.KEY reaches that method, the fallback included; the sidecar records what ran."""
    import sys

    from udh_cli import cli

    out = tmp_path / "m.png"
    args = ["udh", "mosaic", str(small_flight), "-o", str(out), "-m", "orb", "--fallback", "sift", "-O", "sift.best_features=300",
            "-O", "orb.orb_features=800", "--overlap-pairs", "0", "-q"]
    monkeypatch.setattr(sys, "argv", args)
    with pytest.raises(SystemExit) as stop:
        cli.main()
    assert stop.value.code == 0
    sidecar = json.loads(out.with_suffix(".json").read_text())
    assert sidecar["fallback_settings"]["best_features"] == 300 and sidecar["method_settings"]["orb_features"] == 800
    assert sidecar["config"]["fallback_options"] == {"best_features": 300}


@pytest.mark.filterwarnings("ignore:Dataset has no geotransform")  # the mosaic in reference-frame pixels has no CRS
def test_a_tif_mosaic_streams_its_tiles_and_holds_the_png_run_s_pixels(small_flight, tmp_path, monkeypatch):
    rasterio = pytest.importorskip("rasterio")
    from udh_cli.mosaic.render import composite as compositing

    monkeypatch.setattr(compositing, "TILE_SIDE", 128)  # many tiles on the small flight's canvas
    config = MosaicConfig(method="sift", overlap_per_frame=1, blend="multiband")
    png = run_mosaic(small_flight, tmp_path / "m.png", config, resume=True)  # keeps the pair cache for the .tif run
    tif = run_mosaic(small_flight, tmp_path / "m.tif", config, resume=True, overwrite=True)  # m.json is the .png run's
    assert tif["summary"]["pairs_from_cache"] == len(tif["pairs"])  # the same homographies
    with rasterio.open(tmp_path / "m.tif") as dataset:
        assert dataset.profile["tiled"] and dataset.count == 4 and dataset.profile["compress"] == "deflate"
        rgba = dataset.read().transpose(1, 2, 0)
    bgra = cv2.imread(str(tmp_path / "m.png"), cv2.IMREAD_UNCHANGED)
    assert rgba.shape == bgra.shape and rgba.shape[0] > 2 * 128
    assert (rgba[..., [2, 1, 0, 3]] == bgra).all()
    assert png["parts"][0]["width"] == tif["parts"][0]["width"]
    preview = cv2.imread(str(tmp_path / "m.preview.jpg"))
    assert preview is not None and preview.shape[:2] == bgra.shape[:2]  # drawn from the tiles as they streamed


def test_rectify_draws_on_the_ground_without_changing_the_frames_relations(accurate_run, tmp_path):
    folder, _, report = accurate_run
    rectified = run_mosaic(folder, tmp_path / "rectified.png", MosaicConfig(method="sift", rectify=True))
    assert report["parts"][0]["plane"] == "reference frame" and rectified["parts"][0]["plane"] == "ground (rectified)"
    before, after = report["ground_truth_error"], rectified["ground_truth_error"]
    # The frames' relations are the solve's: the frame-to-reference error is the same.
    assert after["solved"]["mean_corner_px"] == pytest.approx(before["solved"]["mean_corner_px"], abs=1e-6)
    # The map's shape is what changes: the reference frame's own tilt no longer bends it (3.99 -> 1.22 px median
    # when written).
    assert before["map_shape"]["median_px"] > 3.0 and after["map_shape"]["median_px"] < 1.5


def test_the_camera_model_draws_the_map_on_the_ground(accurate_run, tmp_path):
    folder, _, report = accurate_run
    cameras = run_mosaic(folder, tmp_path / "cameras.png", MosaicConfig(method="sift", solve="camera"))
    part = cameras["parts"][0]
    assert part["plane"] == "ground (camera model)" and report["parts"][0]["cameras"] is None
    assert cameras["summary"]["placed"] == 10
    # No EXIF focal length: 0.7 of the longer side is assumed and held (the simulator's camera has 450 px,
    # tilted by up to 2 degrees; with 336 px the tilts come out smaller, as they trade with it).
    assert part["cameras"]["focal_px"] == pytest.approx(0.7 * 480)
    assert 0.5 < part["cameras"]["tilt_deg"]["max"] < 3.0
    tilts = [frame["tilt_deg"] for frame in cameras["frames"]]
    assert max(tilts) == part["cameras"]["tilt_deg"]["max"] and all(frame["tilt_deg"] is None for frame in report["frames"])
    before, after = report["ground_truth_error"]["map_shape"], cameras["ground_truth_error"]["map_shape"]
    assert after["median_px"] < 0.2 < 3.0 < before["median_px"]  # measured: 0.08 and 3.99 px
    with pytest.raises(UdhError, match="--solve bundle: choose one of homography, camera"):
        run_mosaic(folder, tmp_path / "bad.png", MosaicConfig(method="sift", solve="bundle"))
    assert not (tmp_path / "bad.png").exists()


def test_the_command_line_reports_the_cameras_and_refuses_an_unknown_model(accurate_run, tmp_path, monkeypatch, capfd):
    folder = accurate_run[0]
    code, out, _ = run_main(monkeypatch, capfd, "mosaic", str(folder), "-o", str(tmp_path / "m.png"), "-m", "sift", "--solve", "camera", "-q")
    assert code == 0
    assert "focal length 336 px, held: assumed" in out  # no EXIF: 0.7 of 480 px
    code, out, err = run_main(monkeypatch, capfd, "mosaic", str(folder), "-o", str(tmp_path / "bad.png"), "-m", "sift", "--solve", "bundle")
    assert code == 2 and "Traceback" not in err and "bundle" in err
    assert not (tmp_path / "bad.png").exists()


def test_what_a_methods_model_files_lack_is_a_warning_of_the_run(small_flight, tmp_path):
    from udh_cli.estimators.features import SiftRansac

    class Unlicensed(SiftRansac):
        def model_notes(self) -> list[str]:
            return ["net.onnx: records no licence for its weights"]

    report = run_mosaic(small_flight, tmp_path / "m.png", MosaicConfig(method="sift", overlap_per_frame=0), estimator=Unlicensed())
    assert report["warnings"].count("net.onnx: records no licence for its weights") == 1
    assert json.loads((tmp_path / "m.json").read_text())["warnings"] == report["warnings"]
