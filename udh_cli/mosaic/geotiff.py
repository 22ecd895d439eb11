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


def write_cog(mosaic_bgra: np.ndarray, map_from_mosaic: np.ndarray, epsg: int, path: Path, max_pixels: int = 400_000_000) -> dict:
    """Resample an (H, W, 4) BGRA mosaic north-up and write it as a COG at ``path``; returns its size and grid."""
    return write_combined_cog([(mosaic_bgra, map_from_mosaic)], epsg, path, max_pixels)


def write_combined_cog(layers: list[tuple[np.ndarray, np.ndarray]], epsg: int, path: Path, max_pixels: int = 400_000_000) -> dict:
    """Several mosaics (``(bgra, map_from_mosaic)``, earlier ones on top) resampled onto one north-up grid of
    the finest pixel size among them, written as one COG: the parts of a split flight in one map."""
    _require_rasterio()
    pixel = min(math.hypot(m[0, 0], m[1, 0]) for _, m in layers)
    edges = []
    for bgra, map_from_mosaic in layers:
        height, width = bgra.shape[:2]
        corners = np.array([[-0.5, -0.5, 1], [width - 0.5, -0.5, 1], [width - 0.5, height - 0.5, 1], [-0.5, height - 0.5, 1]]).T
        edges.append((map_from_mosaic @ corners)[:2])
    mapped = np.hstack(edges)
    west, east, south, north = mapped[0].min(), mapped[0].max(), mapped[1].min(), mapped[1].max()
    columns, rows = int(math.ceil((east - west) / pixel)), int(math.ceil((north - south) / pixel))
    if columns * rows > max_pixels:
        raise UdhError(f"the north-up GeoTIFF would be {columns}x{rows} pixels; use --max-size to make the mosaic smaller")
    out_from_map = np.array([[1 / pixel, 0, -west / pixel - 0.5], [0, -1 / pixel, north / pixel - 0.5], [0, 0, 1]])

    def strip(top: int, height: int) -> np.ndarray:
        """Rows ``top`` to ``top + height`` of the north-up grid, (height, columns, 4) BGRA, earlier layers on top."""
        canvas = np.zeros((height, columns, 4), np.uint8)
        strip_from_out = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, -top], [0.0, 0.0, 1.0]])
        for bgra, map_from_mosaic in layers:
            drawn = cv2.warpAffine(bgra, (strip_from_out @ out_from_map @ map_from_mosaic)[:2], (columns, height),
                                   flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0, 0))
            empty = (canvas[..., 3] == 0) & (drawn[..., 3] > 0)
            canvas[empty] = drawn[empty]
        return canvas

    _write_rgba_cog(strip, rows, columns, west, north, pixel, epsg, path)
    return {"file": path.name, "width": columns, "height": rows, "pixel_size_m": float(pixel), "west": float(west), "north": float(north)}


def _require_rasterio() -> None:
    if not has_rasterio():
        raise UdhError("a GeoTIFF needs rasterio: pip install rasterio (from the udh checkout: pip install '.[geo]')")


STRIP_ROWS = 512  # rows of the north-up grid drawn at a time: one COG block high


def _write_rgba_cog(strip, rows: int, columns: int, west: float, north: float, pixel: float, epsg: int, path: Path) -> None:
    """A north-up image drawn strip by strip (``strip(top, height)`` -> (height, columns, 4) BGRA) to a
    Cloud-Optimised GeoTIFF: RGBA with an alpha band, tiled, DEFLATE, overviews; (west, north) is the outer
    corner of the top-left pixel.

    Memory stays at one strip: the strips go to a tiled GeoTIFF beside ``path``, which GDAL's COG driver then
    copies block by block, adding the overviews, and which is removed afterwards whatever happens.
    """
    import rasterio
    from affine import Affine
    from rasterio.shutil import copy as raster_copy
    from rasterio.windows import Window

    profile = {"driver": "GTiff", "width": columns, "height": rows, "count": 4, "dtype": "uint8", "crs": f"EPSG:{epsg}",
               "transform": Affine(pixel, 0.0, west, 0.0, -pixel, north), "photometric": "RGB", "alpha": "YES",
               "tiled": True, "blockxsize": STRIP_ROWS, "blockysize": STRIP_ROWS, "compress": "DEFLATE", "BIGTIFF": "IF_SAFER"}
    # Named like a staged file (outputs.remove_stale_staged), so that one a killed run leaves is removed by the next.
    strips = path.with_name(f"{path.stem}.strips.staged{path.suffix}")
    try:
        with rasterio.Env(GDAL_NUM_THREADS="1"):
            with rasterio.open(strips, "w", **profile) as dataset:
                for top in range(0, rows, STRIP_ROWS):
                    height = min(STRIP_ROWS, rows - top)
                    dataset.write(strip(top, height)[..., [2, 1, 0, 3]].transpose(2, 0, 1), window=Window(0, top, columns, height))
            raster_copy(str(strips), str(path), driver="COG", COMPRESS="DEFLATE", BLOCKSIZE=512, OVERVIEWS="AUTO")
    finally:
        strips.unlink(missing_ok=True)
