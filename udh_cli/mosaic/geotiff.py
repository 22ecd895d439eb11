"""A georeferenced mosaic as a north-up Cloud-Optimised GeoTIFF (rasterio, whose wheels bundle GDAL).

The mosaic is drawn in its reference frame's pixels; the georeference (:mod:`.georef`, :mod:`.gcp`) maps
them to map metres. Here the mosaic is resampled onto a north-up grid of the same pixel size and written as
a COG: tiled, with overviews and an alpha band, in the map's CRS, which QGIS, GDAL and web map servers read
directly.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from udh_cli.errors import UdhError

COG_SUFFIX = ".cog.tif"


def cog_path(mosaic_file: Path) -> Path:
    """``NAME.cog.tif`` beside ``NAME.png``."""
    return mosaic_file.with_name(f"{mosaic_file.stem}{COG_SUFFIX}")


def has_rasterio() -> bool:
    import importlib.util

    return importlib.util.find_spec("rasterio") is not None


def north_up_grid(map_from_mosaic: np.ndarray, size: tuple[int, int]) -> tuple[np.ndarray, tuple[int, int], tuple[float, float, float]]:
    """The north-up grid covering a ``size`` (width, height) mosaic: ``(out_from_mosaic (3, 3), (columns, rows),
    (west, north, pixel size))``, with ``west``/``north`` the outer edges of the top-left output pixel."""
    width, height = size
    pixel = math.hypot(map_from_mosaic[0, 0], map_from_mosaic[1, 0])
    corners = np.array([[-0.5, -0.5, 1], [width - 0.5, -0.5, 1], [width - 0.5, height - 0.5, 1], [-0.5, height - 0.5, 1]]).T
    mapped = (map_from_mosaic @ corners)[:2]
    west, east = mapped[0].min(), mapped[0].max()
    south, north = mapped[1].min(), mapped[1].max()
    columns, rows = int(math.ceil((east - west) / pixel)), int(math.ceil((north - south) / pixel))
    # Output pixel centre (c, r) lies at (west + (c + 0.5) px, north - (r + 0.5) px).
    out_from_map = np.array([[1 / pixel, 0, -west / pixel - 0.5], [0, -1 / pixel, north / pixel - 0.5], [0, 0, 1]])
    return out_from_map @ map_from_mosaic, (columns, rows), (float(west), float(north), float(pixel))


def write_cog(mosaic_bgra: np.ndarray, map_from_mosaic: np.ndarray, epsg: int, path: Path, max_pixels: int = 400_000_000) -> dict:
    """Resample an (H, W, 4) BGRA mosaic north-up and write it as a COG at ``path``; returns its size and grid."""
    try:
        import rasterio
        from rasterio.io import MemoryFile
        from rasterio.shutil import copy as raster_copy
        from affine import Affine
    except ImportError:
        raise UdhError("a GeoTIFF needs rasterio: pip install rasterio (from the udh checkout: pip install '.[geo]')") from None
    out_from_mosaic, (columns, rows), (west, north, pixel) = north_up_grid(map_from_mosaic, (mosaic_bgra.shape[1], mosaic_bgra.shape[0]))
    if columns * rows > max_pixels:
        raise UdhError(f"the north-up GeoTIFF would be {columns}x{rows} pixels; use --max-size to make the mosaic smaller")
    north_up = cv2.warpAffine(mosaic_bgra, out_from_mosaic[:2], (columns, rows), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0, 0))
    bands = north_up[..., [2, 1, 0, 3]].transpose(2, 0, 1)  # RGBA, band-first
    profile = {"driver": "GTiff", "width": columns, "height": rows, "count": 4, "dtype": "uint8", "crs": f"EPSG:{epsg}",
               "transform": Affine(pixel, 0.0, west, 0.0, -pixel, north), "photometric": "RGB", "alpha": "YES"}
    with rasterio.Env(GDAL_NUM_THREADS="1"):
        with MemoryFile() as memory:
            with memory.open(**profile) as dataset:
                dataset.write(bands)
                dataset.colorinterp = [rasterio.enums.ColorInterp.red, rasterio.enums.ColorInterp.green,
                                       rasterio.enums.ColorInterp.blue, rasterio.enums.ColorInterp.alpha]
            with memory.open() as dataset:
                raster_copy(dataset, str(path), driver="COG", COMPRESS="DEFLATE", BLOCKSIZE=512, OVERVIEWS="AUTO")
    return {"file": path.name, "width": columns, "height": rows, "pixel_size_m": pixel, "west": west, "north": north}
