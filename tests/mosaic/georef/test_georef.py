"""Georeferencing from the frames' GPS: the fit, the world and projection files, and a simulated flight end to end."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from udh_cli import geometry
from udh_cli.files import MANIFEST_NAME
from udh_cli.mosaic.georef.gps import fit_similarity, georeference_part, utm_epsg, world_file_text

pyproj = pytest.importorskip("pyproj")

GROUND_M_PER_PX = 0.05
ORIGIN = (46.85, -92.0)  # latitude, longitude of the simulated ground's top-left corner: UTM zone 15N
TURN_DEG = 30.0  # the ground's x axis points 30 degrees north of east: the mosaic is not north-up


def test_utm_zones_and_hemispheres():
    assert utm_epsg(46.85, -92.0) == 32615 and utm_epsg(-33.9, 151.2) == 32756 and utm_epsg(0.0, 179.99) == 32660


def test_the_similarity_fit_recovers_a_known_map_with_the_image_y_axis_down():
    theta, scale = math.radians(35.0), 0.07
    truth = np.array([[scale * math.cos(theta), scale * math.sin(theta), 500000.0],
                      [scale * math.sin(theta), -scale * math.cos(theta), 5.2e6], [0, 0, 1.0]])
    pixels = np.random.default_rng(0).uniform(0, 4000, (12, 2))
    fitted = fit_similarity(pixels, geometry.transform_points(truth, pixels))
    np.testing.assert_allclose(fitted, truth, atol=1e-6)
    lines = world_file_text(type("G", (), {"map_from_mosaic": truth})()).split()
    assert [float(v) for v in lines] == pytest.approx([truth[0, 0], truth[1, 0], truth[0, 1], truth[1, 1], 500000.0, 5.2e6])


def test_a_bad_gps_fix_is_left_out_and_too_few_frames_give_none():
    to_utm = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:32615", always_xy=True)
    to_gps = pyproj.Transformer.from_crs("EPSG:32615", "EPSG:4326", always_xy=True)
    east0, north0 = to_utm.transform(ORIGIN[1], ORIGIN[0])
    frames = []
    for k in range(6):
        h = geometry.translation(300.0 * k, 50.0 * k)
        east, north = east0 + 300.0 * k * 0.1, north0 - 50.0 * k * 0.1
        if k == 4:
            east += 80.0  # a GPS jump
        lon, lat = to_gps.transform(east + 0.1 * 99.5, north - 0.1 * 74.5)
        frames.append((k, (200, 150), h, lat, lon))
    found = georeference_part(frames)
    assert found.epsg == 32615 and found.frames_rejected == (4,) and found.residual_rms_m < 0.01
    assert found.pixel_size_m == pytest.approx(0.1, rel=1e-4) and abs(found.north_deg) < 0.01
    assert georeference_part(frames[:2]) is None
    one_fix = [(k, size, h, frames[0][3], frames[0][4]) for k, size, h, _, _ in frames]  # a receiver repeating one fix
    assert georeference_part(one_fix) is None and georeference_part(one_fix, min_frames=2) is None


def test_frames_sharing_one_gps_fix_give_a_mosaic_without_a_georeference(tmp_path, monkeypatch, capfd):
    from PIL import Image

    from conftest import run_main
    from udh_cli.simulate import FlightConfig, GpsConfig, write_flight

    write_flight(tmp_path / "flight", FlightConfig(frame_size=(320, 240), strips=1, frames_per_strip=5, focal_px=300.0), seed=3,
                 gps=GpsConfig(46.85, -92.0))
    frames = tmp_path / "frames"
    frames.mkdir()
    files = sorted((tmp_path / "flight").glob("frame_*.jpg"))
    exif = Image.open(files[0]).info["exif"]
    for path in files:
        Image.open(path).save(frames / path.name, "JPEG", quality=95, exif=exif)
    code, _, err = run_main(monkeypatch, capfd, "mosaic", str(frames), "-o", str(tmp_path / "m.png"), "-m", "sift", "--quiet")
    assert code == 0, err
    assert "internal error" not in err and "written without a georeference" in err
    assert json.loads((tmp_path / "m.json").read_text())["parts"][0]["georeference"] is None


def test_a_simulated_flight_with_gps_lands_where_its_gps_says(tmp_path):
    from PIL import Image

    from mosaic_flights import SMALL, make_flight
    from udh_cli.mosaic import MosaicConfig, run_mosaic

    folder = tmp_path / "flight"
    folder.mkdir()
    make_flight(folder, SMALL, seed=6)
    truth = json.loads((folder / "ground_truth.json").read_text())
    to_utm = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:32615", always_xy=True)
    to_gps = pyproj.Transformer.from_crs("EPSG:32615", "EPSG:4326", always_xy=True)
    east0, north0 = to_utm.transform(ORIGIN[1], ORIGIN[0])
    c, s = math.cos(math.radians(TURN_DEG)), math.sin(math.radians(TURN_DEG))
    width, height = truth["frame_size"]
    positions = {}
    for record in truth["frames"]:
        gx, gy = geometry.transform_points(np.array(record["ground_from_frame"]), np.array([[(width - 1) / 2, (height - 1) / 2]]))[0]
        east = east0 + GROUND_M_PER_PX * (c * gx + s * gy)  # ground y points down, like image rows
        north = north0 + GROUND_M_PER_PX * (s * gx - c * gy)
        positions[record["file"]] = (east, north)
        lon, lat = to_gps.transform(east, north)
        path = folder / record["file"]
        exif = Image.Exif()
        exif.get_ifd(0x8825).update({1: "N" if lat >= 0 else "S", 2: _dms(abs(lat)), 3: "E" if lon >= 0 else "W", 4: _dms(abs(lon))})
        with Image.open(path) as image:
            pixels = image.copy()
        pixels.save(path, exif=exif, quality=95)

    report = run_mosaic(folder, tmp_path / "map.png", MosaicConfig(method="sift", overlap_per_frame=1))
    georeference = report["parts"][0]["georeference"] if report["parts"] else None
    assert georeference is not None and georeference["crs"] == "EPSG:32615" and georeference["gps_frames"] == 8
    assert georeference["gps_residual_rms_m"] < 0.3 and georeference["pixel_size_m"] == pytest.approx(GROUND_M_PER_PX, rel=0.02)
    assert "UTM_Zone_15N" in (tmp_path / "map.prj").read_text()
    world = [float(v) for v in (tmp_path / "map.pgw").read_text().split()]
    map_from_mosaic = np.array([[world[0], world[2], world[4]], [world[1], world[3], world[5]], [0, 0, 1.0]])
    for record in report["frames"]:  # every frame's centre, through the mosaic and the world file, on its GPS
        centre = geometry.transform_points(map_from_mosaic @ np.array(record["mosaic_from_frame"]), np.array([[(width - 1) / 2, (height - 1) / 2]]))[0]
        assert np.linalg.norm(centre - positions[record["file"]]) < 0.5
    # The ground's up direction (the first frame's, within its few degrees of yaw) is TURN_DEG west of north.
    assert abs(georeference["north_deg"] + TURN_DEG) < 5.0


def _dms(degrees: float) -> tuple[float, float, float]:
    d = int(degrees)
    m = int((degrees - d) * 60)
    return (float(d), float(m), (degrees - d - m / 60) * 3600)


def test_the_simulator_writes_noisy_gps_and_the_map_lands_closer_than_one_fix(tmp_path):
    """`udh simulate --gps`: 2 m of noise on each fix; the fitted map, which averages the fixes, puts every
    frame centre within 1.5 m of its exact position (the truth records it)."""
    from udh_cli.mosaic import MosaicConfig, run_mosaic
    from udh_cli.mosaic.inputs.metadata import read_metadata
    from udh_cli.simulate import FlightConfig, GpsConfig, write_flight

    folder = tmp_path / "flight"
    write_flight(folder, FlightConfig(frame_size=(320, 240), strips=3, frames_per_strip=5, focal_px=300.0), seed=2,
                 gps=GpsConfig(46.85, -92.0, metres_per_pixel=0.05, noise_m=2.0))
    truth = json.loads((folder / "ground_truth.json").read_text())
    assert read_metadata(folder / "frame_000.jpg").has_gps
    report = run_mosaic(folder, tmp_path / "map.png", MosaicConfig(method="sift", overlap_per_frame=1))
    georeference = report["parts"][0]["georeference"]
    assert georeference["gps_frames"] == 15 and 0.5 < georeference["gps_residual_rms_m"] < 5.0
    to_utm = pyproj.Transformer.from_crs("EPSG:4326", georeference["crs"], always_xy=True)
    map_from_mosaic = np.array(georeference["map_from_mosaic"])
    width, height = truth["frame_size"]
    errors = []
    for record, frame in zip(truth["frames"], report["frames"]):
        exact = np.array(to_utm.transform(record["gps"]["longitude"], record["gps"]["latitude"]))
        centre = geometry.transform_points(map_from_mosaic @ np.array(frame["mosaic_from_frame"]), np.array([[(width - 1) / 2, (height - 1) / 2]]))[0]
        errors.append(np.linalg.norm(centre - exact))
    assert max(errors) < 1.5, errors


def test_the_camera_model_holds_the_exif_focal_length_and_its_gps_anchors(tmp_path):
    """--solve camera --gps-sigma on a simulated flight with GPS: the focal length comes from the EXIF the simulator
    writes (a 34 mm equivalent for 300 px on 320 px), the fixes anchor the cameras, and the map lands on them."""
    from udh_cli.mosaic import MosaicConfig, run_mosaic
    from udh_cli.simulate import FlightConfig, GpsConfig, write_flight

    folder = tmp_path / "flight"
    write_flight(folder, FlightConfig(frame_size=(320, 240), strips=3, frames_per_strip=5, focal_px=300.0), seed=2,
                 gps=GpsConfig(46.85, -92.0, metres_per_pixel=0.05, noise_m=0.2))
    report = run_mosaic(folder, tmp_path / "map.png", MosaicConfig(method="sift", overlap_per_frame=1, solve="camera", gps_sigma_m=0.2))
    part = report["parts"][0]
    assert part["plane"] == "ground (camera model)"
    assert part["cameras"]["focal_source"] == "EXIF 35 mm equivalent"
    assert part["cameras"]["focal_px"] == pytest.approx(34 / 36 * 320)
    assert part["georeference"]["gps_residual_rms_m"] < 0.5  # 0.2 m fixes
    assert report["ground_truth_error"]["map_shape"]["median_px"] < 0.5  # measured: 0.14 px; free homographies 4.6


def test_a_georeferenced_mosaic_is_also_a_north_up_cloud_optimised_geotiff(tmp_path):
    rasterio = pytest.importorskip("rasterio")
    from udh_cli.mosaic import MosaicConfig, run_mosaic
    from udh_cli.simulate import FlightConfig, GpsConfig, write_flight

    folder = tmp_path / "flight"
    write_flight(folder, FlightConfig(frame_size=(320, 240), strips=2, frames_per_strip=5, focal_px=300.0), seed=4,
                 gps=GpsConfig(-33.9, 151.2, metres_per_pixel=0.1, heading_deg=60.0, noise_m=0.5))
    truth = json.loads((folder / "ground_truth.json").read_text())
    report = run_mosaic(folder, tmp_path / "map.png", MosaicConfig(method="sift", overlap_per_frame=1))
    geotiff = report["parts"][0]["geotiff"]
    assert geotiff["file"] == "map.cog.tif" and geotiff["pixel_size_m"] == pytest.approx(0.1, rel=0.05)
    with rasterio.open(tmp_path / "map.cog.tif") as dataset:
        assert dataset.crs.to_epsg() == 32756  # Sydney: UTM zone 56 south
        transform = dataset.transform
        assert transform.b == 0 and transform.d == 0 and transform.e < 0  # north-up
        assert dataset.count == 4 and dataset.colorinterp[3] == rasterio.enums.ColorInterp.alpha
        assert dataset.overviews(1) and dataset.profile["tiled"]
        alpha = dataset.read(4)
        to_utm = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:32756", always_xy=True)
        for record in truth["frames"]:  # every frame's true position is inside the drawn map
            east, north = to_utm.transform(record["gps"]["longitude"], record["gps"]["latitude"])
            row, column = dataset.index(east, north)
            assert alpha[row, column] == 255


def test_the_geotiff_is_drawn_from_the_mosaic_in_hand_and_equals_the_one_read_back(tmp_path, monkeypatch):
    """The north-up GeoTIFF comes from the assembled image the run holds, never from decoding the staged PNG; with
    no room to hold it (a budget of 0) the file is read back, to the same pixels."""
    rasterio = pytest.importorskip("rasterio")
    import cv2

    from udh_cli.mosaic import MosaicConfig, run_mosaic
    from udh_cli.mosaic import run as mosaic_run
    from udh_cli.mosaic.render.canvases import KEPT_IMAGES_BYTES, kept_images
    from udh_cli.simulate import FlightConfig, GpsConfig, write_flight

    folder = tmp_path / "flight"
    write_flight(folder, FlightConfig(frame_size=(320, 240), strips=2, frames_per_strip=4, focal_px=300.0), seed=6,
                 gps=GpsConfig(-33.9, 151.2, metres_per_pixel=0.1, heading_deg=30.0, noise_m=0.3))
    read_back = []
    real_imread = cv2.imread
    monkeypatch.setattr(cv2, "imread", lambda path, *args: read_back.append(Path(path)) or real_imread(path, *args))
    runs = {}
    for name, budget in (("held", KEPT_IMAGES_BYTES), ("read", 0)):
        monkeypatch.setattr(mosaic_run, "kept_images", lambda plan, wanted, budget=budget: kept_images(plan, wanted, budget))
        (tmp_path / name).mkdir()
        run_mosaic(folder, tmp_path / name / "map.png", MosaicConfig(method="sift", overlap_per_frame=1))
        runs[name] = [p for p in read_back if p.parent == tmp_path / name]
        read_back.clear()
    assert runs["held"] == [] and len(runs["read"]) == 1  # the staged PNG is decoded only where there was no room to hold it
    with rasterio.open(tmp_path / "held" / "map.cog.tif") as held, rasterio.open(tmp_path / "read" / "map.cog.tif") as read:
        assert held.transform == read.transform and np.array_equal(held.read(), read.read())


def test_a_split_flight_becomes_one_map_with_gps(tmp_path):
    """No estimated pair links the two strips; their frames' GPS puts both parts in one GeoTIFF."""
    rasterio = pytest.importorskip("rasterio")
    from mosaic_flights import FailOn, work_fingerprints
    from udh_cli.mosaic import MosaicConfig, run_mosaic
    from udh_cli.simulate import FlightConfig, GpsConfig, write_flight

    folder = tmp_path / "flight"
    write_flight(folder, FlightConfig(frame_size=(320, 240), strips=2, frames_per_strip=5, focal_px=300.0), seed=5,
                 gps=GpsConfig(46.85, -92.0, metres_per_pixel=0.1, noise_m=0.3))
    truth = json.loads((folder / "ground_truth.json").read_text())
    prints = work_fingerprints(sorted(folder.glob("frame_*.jpg")))
    split = FailOn(prints, lambda a, b: a is None or b is None or (a < 5) != (b < 5))
    report = run_mosaic(folder, tmp_path / "map.png", MosaicConfig(overlap_per_frame=1), estimator=split, fallback=split)
    assert report["summary"]["parts"] == 2
    assert report["map"]["parts"] == 2 and report["map"]["frames"] == 10 and report["map"]["frames_on_gps_alone"] == 5
    with rasterio.open(tmp_path / "map.cog.tif") as dataset:
        alpha = dataset.read(4)
        to_utm = pyproj.Transformer.from_crs("EPSG:4326", dataset.crs.to_string(), always_xy=True)
        for record in truth["frames"]:  # both strips' frames on the one map, where their GPS says
            row, column = dataset.index(*to_utm.transform(record["gps"]["longitude"], record["gps"]["latitude"]))
            assert alpha[row, column] == 255


def test_the_geotiffs_are_compressed_on_the_runs_workers(tmp_path, monkeypatch):
    pytest.importorskip("rasterio")
    from udh_cli.mosaic import MosaicConfig, run_mosaic
    from udh_cli.mosaic.georef import place
    from udh_cli.simulate import FlightConfig, GpsConfig, write_flight

    folder = tmp_path / "flight"
    write_flight(folder, FlightConfig(frame_size=(320, 240), strips=1, frames_per_strip=4, focal_px=300.0), seed=5,
                 gps=GpsConfig(46.85, -92.0, metres_per_pixel=0.1, noise_m=0.3))
    asked = []
    real = place.write_cog
    monkeypatch.setattr(place, "write_cog", lambda *args, threads=1, **kwargs: asked.append(threads) or real(*args, threads=threads, **kwargs))
    report = run_mosaic(folder, tmp_path / "map.png", MosaicConfig(method="orb", workers=2))
    assert report["summary"]["placed"] == 4 and asked == [2] and (tmp_path / "map.cog.tif").is_file()


def test_an_earlier_runs_georeference_never_stays_beside_a_mosaic_without_one(tmp_path):
    """Run 1 places the mosaic by GPS; run 2 (frames without GPS) writes a new mosaic under the same name: the
    old world file, .prj and GeoTIFF go, or GIS tools would put the new mosaic where the old one was."""
    pytest.importorskip("rasterio")
    from udh_cli.mosaic import MosaicConfig, run_mosaic
    from udh_cli.simulate import FlightConfig, GpsConfig, write_flight

    small = FlightConfig(frame_size=(320, 240), strips=1, frames_per_strip=4, focal_px=300.0)
    with_gps, without = tmp_path / "gps", tmp_path / "plain"
    write_flight(with_gps, small, seed=1, gps=GpsConfig(46.85, -92.0, noise_m=0.5))
    write_flight(without, small, seed=1)
    out = tmp_path / "out"
    out.mkdir()
    config = MosaicConfig(method="sift", overlap_per_frame=1)
    run_mosaic(with_gps, out / "m.png", config)
    assert {"m.pgw", "m.prj", "m.cog.tif"} <= {p.name for p in out.iterdir()}
    report = run_mosaic(without, out / "m.png", config)
    assert report["parts"] == [] or report["parts"][0].get("georeference") is None
    assert not ({"m.pgw", "m.prj", "m.cog.tif"} & {p.name for p in out.iterdir()})


def test_a_geotiff_too_large_is_a_warning_and_nothing_half_written(tmp_path, monkeypatch):
    pytest.importorskip("rasterio")
    import udh_cli.mosaic.georef.geotiff as geotiff
    from udh_cli.mosaic import MosaicConfig, Reporter, run_mosaic
    from udh_cli.simulate import FlightConfig, GpsConfig, write_flight

    folder = tmp_path / "flight"
    write_flight(folder, FlightConfig(frame_size=(320, 240), strips=1, frames_per_strip=4, focal_px=300.0), seed=1,
                 gps=GpsConfig(46.85, -92.0, noise_m=0.5))
    real = geotiff.write_combined_cog
    monkeypatch.setattr(geotiff, "write_combined_cog", lambda layers, epsg, path, max_pixels=0, threads=1: real(layers, epsg, path, max_pixels=10))
    reporter = Reporter(quiet=True)
    out = tmp_path / "out"
    out.mkdir()
    report = run_mosaic(folder, out / "m.png", MosaicConfig(method="sift", overlap_per_frame=1), reporter)
    assert report["summary"]["placed"] == 4 and (out / "m.png").is_file() and (out / "m.pgw").is_file()
    assert not (out / "m.cog.tif").exists() and not [p for p in out.iterdir() if p.name.startswith(".") and p.name != MANIFEST_NAME]
    assert any("no north-up GeoTIFF" in w for w in reporter.warnings)


@pytest.mark.parametrize("held", ["in memory", "streamed to a tiled TIFF"])
def test_a_north_up_geotiff_drawn_strip_by_strip_equals_the_whole_warp(tmp_path, held):
    """Several strips high, turned 30 degrees: the COG read back is the mosaic warped north-up in one go, whether
    the mosaic is held whole or read window by window from the tiled TIFF it was streamed to."""
    rasterio = pytest.importorskip("rasterio")
    import cv2

    from conftest import textured_image
    from udh_cli.mosaic.georef import geotiff

    grey = textured_image(900, 700, seed=2)
    bgra = cv2.cvtColor(grey, cv2.COLOR_GRAY2BGRA)
    turn, pixel = math.radians(30.0), 0.05  # metres per mosaic pixel; image y runs south
    map_from_mosaic = np.array([[pixel * math.cos(turn), pixel * math.sin(turn), 500000.0],
                                [pixel * math.sin(turn), -pixel * math.cos(turn), 4000000.0], [0.0, 0.0, 1.0]])
    if held == "in memory":
        image = geotiff.MosaicImage(array=bgra)
    else:
        tiles = [((x, y, min(x + 256, 900), min(y + 256, 700)), bgra[y : y + 256, x : x + 256]) for y in range(0, 700, 256) for x in range(0, 900, 256)]
        geotiff.write_tiled_tiff(tmp_path / "m.tif", (900, 700), iter(tiles))
        image = geotiff.MosaicImage(path=tmp_path / "m.tif")
        assert image.size == (900, 700) and (image.window(0, 0, 900, 700) == bgra).all()  # the TIFF holds the mosaic exactly
    written = geotiff.write_cog(image, map_from_mosaic, 32633, tmp_path / "m.cog.tif")
    assert written["height"] > 2 * geotiff.STRIP_ROWS
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.cog.tif"] + (["m.tif"] if held != "in memory" else [])  # the strips file is gone
    with rasterio.open(tmp_path / "m.cog.tif") as dataset:
        assert dataset.crs.to_epsg() == 32633 and (dataset.width, dataset.height) == (written["width"], written["height"])
        assert dataset.overviews(1)  # a COG: overviews inside
        rgba = dataset.read().transpose(1, 2, 0)
    out_from_map = np.array([[1 / pixel, 0, -written["west"] / pixel - 0.5], [0, -1 / pixel, written["north"] / pixel - 0.5], [0, 0, 1]])
    whole = cv2.warpAffine(bgra, (out_from_map @ map_from_mosaic)[:2], (written["width"], written["height"]), flags=cv2.INTER_LINEAR)
    assert np.abs(rgba[..., 3].astype(int) - whole[..., 3]).max() <= 1  # OpenCV's fixed-point rounding
    inside = whole[..., 3] == 255
    assert np.abs(rgba[..., 0][inside].astype(int) - whole[..., 2][inside]).max() <= 1


def test_colour_under_transparent_pixels_never_reaches_the_cog_or_its_overviews(tmp_path):
    """A caller's BGRA with noise where alpha is 0 (OpenCV leaves such pixels): every transparent pixel of the COG
    has colour 0, as the overviews, averaging it as premultiplied colour, need; in the overviews only the
    partly covered edge pixels' own colour is left under a rounded-down alpha (a pixel or two)."""
    rasterio = pytest.importorskip("rasterio")
    import cv2

    from conftest import textured_image
    from udh_cli.mosaic.georef import geotiff

    bgra = cv2.cvtColor(textured_image(900, 700, seed=6), cv2.COLOR_GRAY2BGRA)
    bgra[:, 450:, 3] = 0  # the right half transparent, its colour left as noise
    turn = math.radians(30.0)
    map_from_mosaic = np.array([[0.05 * math.cos(turn), 0.05 * math.sin(turn), 500000.0],
                                [0.05 * math.sin(turn), -0.05 * math.cos(turn), 4000000.0], [0.0, 0.0, 1.0]])
    path = tmp_path / "noisy.cog.tif"
    geotiff.write_cog(geotiff.MosaicImage(array=bgra), map_from_mosaic, 32633, path)
    with rasterio.open(path) as dataset:
        levels = [dataset.read()] + [rasterio.open(path, overview_level=k).read() for k in range(len(dataset.overviews(1)))]
    assert len(levels) >= 2
    full = levels[0]
    assert (full[3] == 0).mean() > 0.3 and not full[:3][:, full[3] == 0].any()
    for overview in levels[1:]:
        coloured = overview[:3][:, overview[3] == 0].max(0) > 0
        assert coloured.sum() <= 2  # the noise itself, averaged in, would colour most of them


def test_a_cog_compressed_on_two_threads_holds_the_same_pixels_and_overviews(tmp_path):
    """GDAL's compression threads change the time, not the map: every level reads back the same."""
    rasterio = pytest.importorskip("rasterio")
    import cv2

    from conftest import textured_image
    from udh_cli.mosaic.georef import geotiff

    bgra = cv2.cvtColor(textured_image(1300, 900, seed=4), cv2.COLOR_GRAY2BGRA)
    map_from_mosaic = np.array([[0.05, 0.0, 500000.0], [0.0, -0.05, 4000000.0], [0.0, 0.0, 1.0]])
    levels = {}
    for threads in (1, 2):
        path = tmp_path / f"t{threads}.cog.tif"
        geotiff.write_cog(geotiff.MosaicImage(array=bgra), map_from_mosaic, 32633, path, threads=threads)
        with rasterio.open(path) as dataset:
            levels[threads] = [dataset.read()] + [rasterio.open(path, overview_level=k).read() for k in range(len(dataset.overviews(1)))]
    assert len(levels[1]) == 3 and all(np.array_equal(a, b) for a, b in zip(levels[1], levels[2], strict=True))


def test_the_cogs_overviews_are_area_averages_of_the_map_without_dark_edges(tmp_path):
    """The overviews built from the strips as they are drawn: every level halves the one below down to one
    block, its inside is the area average of the map, and along the map's turned edges a uniform grey stays
    grey (the empty pixels outside do not dim it)."""
    rasterio = pytest.importorskip("rasterio")
    import cv2

    from conftest import textured_image
    from udh_cli.mosaic.georef import geotiff

    turn, pixel = math.radians(30.0), 0.05
    map_from_mosaic = np.array([[pixel * math.cos(turn), pixel * math.sin(turn), 500000.0],
                                [pixel * math.sin(turn), -pixel * math.cos(turn), 4000000.0], [0.0, 0.0, 1.0]])
    for name, grey in [("textured", textured_image(1500, 1100, seed=3)), ("uniform", np.full((1100, 1500), 200, np.uint8))]:
        path = tmp_path / f"{name}.cog.tif"
        written = geotiff.write_cog(geotiff.MosaicImage(array=cv2.cvtColor(grey, cv2.COLOR_GRAY2BGRA)), map_from_mosaic, 32633, path)
        with rasterio.open(path) as dataset:
            factors = dataset.overviews(1)
            full = dataset.read().transpose(1, 2, 0)
        assert factors == [2, 4] and max(written["width"], written["height"]) // 4 <= geotiff.BLOCK < max(written["width"], written["height"]) // 2
        assert full.shape[0] % 4 == 0 and full.shape[1] % 4 == 0
        below = full
        for level_index in range(len(factors)):  # every level, the deeper ones halved from the ones above
            with rasterio.open(path, overview_level=level_index) as level:
                half = level.read().transpose(1, 2, 0)
            assert half.shape[:2] == (below.shape[0] // 2, below.shape[1] // 2)
            expected = cv2.resize(below, (half.shape[1], half.shape[0]), interpolation=cv2.INTER_AREA)
            if name == "textured":
                inside = cv2.erode((expected[..., 3] == 255).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
                assert inside.mean() > 0.3 and np.abs(half[inside].astype(int) - expected[inside]).max() <= 1
            else:
                covered = half[..., 3] >= 32  # below, the map's own edge pixels round their colour to 0
                edge = covered & (half[..., 3] < 255)
                assert edge.sum() > 200 and np.abs(half[covered][:, :3].astype(int) - 200).max() <= 8  # 8-bit rounding at low alpha
                if level_index == 0:  # the plain average of the map's dimmed edges would darken them
                    assert np.abs(expected[edge][:, :3].astype(int) - 200).max() > 50
            below = half
    assert sorted(p.name for p in tmp_path.iterdir()) == ["textured.cog.tif", "uniform.cog.tif"]  # no temporary left
