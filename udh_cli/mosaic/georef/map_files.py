"""The georeference carried by the mosaic file itself, so that GDAL (QGIS, rasterio) opens it on the map.

A ``.tif`` mosaic written by rasterio gets its CRS and its affine transform inside, rotation included. Every
georeferenced mosaic (``.png``, ``.jpg``, ``.tif``) gets a GDAL PAM sidecar, ``NAME.png.aux.xml``, with the CRS as
WKT and the same transform. GDAL does not read the ESRI ``.prj`` beside a world file of a
rotated PNG ("failed to load SRS definition"), but it always reads the PAM file; the world file and the
``.prj`` are still written for the tools that read only those.
"""

from __future__ import annotations

from pathlib import Path
from xml.sax.saxutils import escape

import numpy as np

from udh_cli.errors import UdhError
from udh_cli.images import atomic_write_bytes
from udh_cli.mosaic.georef.geotiff import has_rasterio
from udh_cli.mosaic.outputs.files import MosaicFiles
from udh_cli.mosaic.outputs.staging import StagedFiles


def gdal_geotransform(map_from_mosaic: np.ndarray) -> tuple[float, ...]:
    """GDAL's six numbers (x0, dx/dcol, dx/drow, y0, dy/dcol, dy/drow) of a (3, 3) affine ``map_from_mosaic``
    whose pixel centres sit at integers: GDAL's origin is the top-left pixel's corner, half a pixel before."""
    m = np.asarray(map_from_mosaic, np.float64)
    corner = m @ np.array([-0.5, -0.5, 1.0])
    return (float(corner[0]), float(m[0, 0]), float(m[0, 1]), float(corner[1]), float(m[1, 0]), float(m[1, 1]))


def pam_text(map_from_mosaic: np.ndarray, epsg: int) -> str:
    """A GDAL PAM document: the CRS (WKT2, x = easting first) and the geotransform."""
    from pyproj import CRS

    wkt = CRS.from_epsg(epsg).to_wkt()
    transform = ", ".join(f"{v:.12e}" for v in gdal_geotransform(map_from_mosaic))
    return (f'<PAMDataset>\n  <SRS dataAxisToSRSAxisMapping="1,2">{escape(wkt)}</SRS>\n'
            f"  <GeoTransform>{transform}</GeoTransform>\n</PAMDataset>\n")


def embed_georeference(tiff: Path, map_from_mosaic: np.ndarray, epsg: int) -> None:
    """Write the CRS and the transform into an existing GeoTIFF (GDAL rewrites only its tags)."""
    import warnings

    import rasterio
    from affine import Affine
    from rasterio.crs import CRS
    from rasterio.errors import NotGeoreferencedWarning, RasterioError

    x0, a, b, y0, d, e = gdal_geotransform(map_from_mosaic)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)  # not georeferenced yet: this gives it one
            with rasterio.open(tiff, "r+") as dataset:
                dataset.crs = CRS.from_epsg(epsg)
                dataset.transform = Affine(a, b, x0, d, e, y0)
    except (RasterioError, OSError) as exc:
        raise UdhError(f"{tiff}: writing its georeference failed ({exc}); check the free space and permissions") from None


def georeference_mosaic_file(names: MosaicFiles, map_from_mosaic: np.ndarray, epsg: int, staged: StagedFiles) -> None:
    """Put the georeference where GDAL reads it for the image ``names.image`` as staged in ``staged``: in its PAM
    file (``names.pam``), staged beside it, and inside a TIFF rasterio wrote."""
    temporary = staged.temporary_of(names.image)
    if names.image.suffix.lower() in (".tif", ".tiff") and has_rasterio() and temporary is not None:
        embed_georeference(temporary, map_from_mosaic, epsg)
    # Beside a TIFF too: GDAL reads a PAM file before a TIFF's own tags, so one must never be left from an earlier run.
    atomic_write_bytes(staged.path_for(names.pam), pam_text(map_from_mosaic, epsg).encode())
