"""Every georeferenced mosaic opens on the map: rasterio (GDAL) reads its CRS and its transform back."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from udh_cli.mosaic.georef.map_files import gdal_geotransform
from udh_cli.mosaic.outputs.files import MosaicFiles

pytest.importorskip("pyproj")


def test_the_geotransform_starts_at_the_top_left_pixels_corner():
    map_from_mosaic = np.array([[0.1, 0.02, 500.0], [0.02, -0.1, 6000.0], [0, 0, 1]])
    x0, a, b, y0, d, e = gdal_geotransform(map_from_mosaic)
    assert (a, b, d, e) == (0.1, 0.02, 0.02, -0.1)
    assert x0 == pytest.approx(500.0 - 0.05 - 0.01) and y0 == pytest.approx(6000.0 - 0.01 + 0.05)
    assert MosaicFiles(Path("/x/map.part2.png")).pam.name == "map.part2.png.aux.xml"


@pytest.mark.parametrize("suffix", [".png", ".tif", ".jpg"])
def test_every_georeferenced_mosaic_reads_back_with_its_crs_and_rotated_transform(tmp_path, suffix):
    """A simulated flight with GPS, heading 60 degrees (a rotated map): the mosaic itself, whatever its type, has
    the CRS and the transform of the sidecar's map_from_mosaic; the north-up COG beside it too."""
    rasterio = pytest.importorskip("rasterio")
    from udh_cli.mosaic import MosaicConfig, run_mosaic
    from udh_cli.simulate import FlightConfig, GpsConfig, write_flight

    folder = tmp_path / "flight"
    write_flight(folder, FlightConfig(frame_size=(320, 240), strips=2, frames_per_strip=4, focal_px=300.0), seed=4,
                 gps=GpsConfig(-33.9, 151.2, metres_per_pixel=0.1, heading_deg=60.0, noise_m=0.5))
    output = tmp_path / f"map{suffix}"
    report = run_mosaic(folder, output, MosaicConfig(method="sift", overlap_per_frame=1, preview=False))
    map_from_mosaic = np.array(report["parts"][0]["georeference"]["map_from_mosaic"])
    for path in (output, tmp_path / "map.cog.tif"):
        with rasterio.open(path) as dataset:
            assert dataset.crs is not None and dataset.crs.to_epsg() == 32756, path.name
            if path == output:
                t = dataset.transform
                assert abs(t.b) > 0.01  # rotated, as the mosaic is drawn
                # the centre of pixel (col, row) = (10, 20) goes where map_from_mosaic sends (10, 20)
                centre = t @ (10.5, 20.5)
                np.testing.assert_allclose(centre, (map_from_mosaic @ [10, 20, 1])[:2], atol=1e-6)
    assert (tmp_path / f"map{suffix}.aux.xml").is_file()  # beside a TIFF too, which also carries it inside
