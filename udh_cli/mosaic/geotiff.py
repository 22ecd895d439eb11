"""GeoTIFFs (rasterio, whose wheels bundle GDAL): a mosaic streamed tile by tile, and the north-up COG.

The mosaic is drawn in its reference frame's pixels; a ``.tif`` mosaic is written tile by tile as it is blended
(:func:`write_tiled_tiff`), so that its area costs no memory. The georeference (:mod:`.georef`, :mod:`.gcp`)
maps those pixels to map metres. Here the mosaic is resampled onto a north-up grid of the same pixel size,
strip by strip, and written as a COG: tiled, with overviews and an alpha band, in the map's CRS, which QGIS,
GDAL and web map servers read directly.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from udh_cli.errors import UdhError

COG_SUFFIX = ".cog.tif"
# GDAL's block cache, in MB. Its default is 5 % of the machine's memory (1.2 GB here), which it fills while it
# copies a large map into a COG with overviews: seneca's run peaked at 1.21 GB with it, 0.76 GB with this.
GDAL_CACHE_MB = 128
GDAL_SETTINGS = {"GDAL_NUM_THREADS": "1", "GDAL_CACHEMAX": GDAL_CACHE_MB}


def cog_path(mosaic_file: Path) -> Path:
    """``NAME.cog.tif`` beside ``NAME.png``."""
    return mosaic_file.with_name(f"{mosaic_file.stem}{COG_SUFFIX}")


def has_rasterio() -> bool:
    import importlib.util

    return importlib.util.find_spec("rasterio") is not None


class MosaicImage:
    """A written mosaic to resample north-up, read window by window: held in memory, or in a tiled TIFF that
    :func:`write_tiled_tiff` streamed (so that a map larger than memory is never held whole). The TIFF stays
    open between windows, so that GDAL's block cache serves the blocks neighbouring windows share; :meth:`close`
    releases it (it reopens on the next window)."""

    def __init__(self, array: np.ndarray | None = None, path: Path | None = None) -> None:
        if (array is None) == (path is None):
            raise ValueError("give the mosaic as an array or as a tiled TIFF's path")
        self.array, self.path, self._dataset = array, path, None
        if array is not None:
            self.size = (array.shape[1], array.shape[0])
        else:
            dataset = self._open()
            self.size = (dataset.width, dataset.height)

    def _open(self):
        if self._dataset is None:
            from rasterio.errors import RasterioError

            try:
                self._dataset = _open_tiff(self.path)
            except (RasterioError, OSError) as exc:
                raise UdhError(f"{self.path}: not a readable mosaic ({exc})") from None
        return self._dataset

    def window(self, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
        """Pixels ``x0:x1``, ``y0:y1`` as (h, w, 4) BGRA uint8 (inside the image)."""
        if self.array is not None:
            return self.array[y0:y1, x0:x1]
        from rasterio.errors import RasterioError
        from rasterio.windows import Window

        try:
            rgba = self._open().read(window=Window(x0, y0, x1 - x0, y1 - y0))
        except (RasterioError, OSError) as exc:
            raise UdhError(f"{self.path}: reading the mosaic back failed ({exc})") from None
        return np.ascontiguousarray(rgba.transpose(1, 2, 0)[..., [2, 1, 0, 3]])

    def close(self) -> None:
        if self._dataset is not None:
            self._dataset.close()
            self._dataset = None


def _open_tiff(path: Path):
    import warnings

    import rasterio
    from rasterio.errors import NotGeoreferencedWarning

    with warnings.catch_warnings():  # the mosaic in reference-frame pixels has no CRS of its own: that is expected
        warnings.simplefilter("ignore", NotGeoreferencedWarning)
        return rasterio.open(path)


def write_tiled_tiff(path: Path, size: tuple[int, int], tiles) -> None:
    """Stream ``tiles`` (``((x0, y0, x1, y1), (h, w, 4) BGRA uint8)``, as :func:`.composite.composite_tiles`
    yields them) into a tiled RGBA TIFF of ``size`` (width, height) with an alpha band, DEFLATE-compressed:
    only one tile is in memory at a time. GDAL, QGIS and OpenCV read it."""
    _require_rasterio()
    import rasterio
    from rasterio.errors import NotGeoreferencedWarning
    from rasterio.windows import Window
    import warnings

    width, height = size
    from rasterio.errors import RasterioError

    profile = {"driver": "GTiff", "width": width, "height": height, "count": 4, "dtype": "uint8", "photometric": "RGB",
               "alpha": "YES", "tiled": True, "blockxsize": BLOCK, "blockysize": BLOCK, "compress": "DEFLATE",
               "BIGTIFF": "IF_SAFER"}
    try:
        with warnings.catch_warnings(), rasterio.Env(**GDAL_SETTINGS):
            warnings.simplefilter("ignore", NotGeoreferencedWarning)
            with rasterio.open(path, "w", **profile) as dataset:
                for (x0, y0, x1, y1), tile in tiles:
                    dataset.write(tile[..., [2, 1, 0, 3]].transpose(2, 0, 1), window=Window(x0, y0, x1 - x0, y1 - y0))
    except (RasterioError, OSError) as exc:  # a full disk, a folder that went away: one line, and the caller discards the file
        raise UdhError(f"{path}: writing the mosaic failed ({exc}); check the free space and permissions") from None


def write_cog(mosaic: MosaicImage, map_from_mosaic: np.ndarray, epsg: int, path: Path, max_pixels: int = 400_000_000) -> dict:
    """Resample a mosaic north-up and write it as a COG at ``path``; returns its size and grid."""
    return write_combined_cog([(mosaic, map_from_mosaic)], epsg, path, max_pixels)


def write_combined_cog(layers: list[tuple[MosaicImage, np.ndarray]], epsg: int, path: Path, max_pixels: int = 400_000_000) -> dict:
    """Several mosaics (``(image, map_from_mosaic)``, earlier ones on top) resampled onto one north-up grid of
    the finest pixel size among them, written as one COG: the parts of a split flight in one map. Each strip
    of the grid reads only the window of each mosaic it covers; the mosaics' files are closed at the end."""
    _require_rasterio()
    pixel = min(math.hypot(m[0, 0], m[1, 0]) for _, m in layers)
    edges = []
    for image, map_from_mosaic in layers:
        width, height = image.size
        corners = np.array([[-0.5, -0.5, 1], [width - 0.5, -0.5, 1], [width - 0.5, height - 0.5, 1], [-0.5, height - 0.5, 1]]).T
        edges.append((map_from_mosaic @ corners)[:2])
    mapped = np.hstack(edges)
    west, east, south, north = mapped[0].min(), mapped[0].max(), mapped[1].min(), mapped[1].max()
    columns, rows = int(math.ceil((east - west) / pixel)), int(math.ceil((north - south) / pixel))
    if columns * rows > max_pixels:
        raise UdhError(f"the north-up GeoTIFF would be {columns}x{rows} pixels; use --max-size to make the mosaic smaller")
    out_from_map = np.array([[1 / pixel, 0, -west / pixel - 0.5], [0, -1 / pixel, north / pixel - 0.5], [0, 0, 1]])

    def strip(top: int, height: int) -> np.ndarray:
        """Rows ``top`` to ``top + height`` of the north-up grid, (height, columns, 4) BGRA, earlier layers on top.
        Drawn block by block (:data:`BLOCK` columns): a block's outline in a turned mosaic spans a window about
        its own size, where a whole strip's would span most of the mosaic."""
        canvas = np.zeros((height, columns, 4), np.uint8)
        for left in range(0, columns, BLOCK):
            width = min(BLOCK, columns - left)
            block_from_out = np.array([[1.0, 0.0, -left], [0.0, 1.0, -top], [0.0, 0.0, 1.0]])
            outline = np.array([[-1, -1, 1], [width, -1, 1], [width, height, 1], [-1, height, 1]], float).T
            block = canvas[:, left : left + width]
            for image, map_from_mosaic in layers:
                block_from_mosaic = block_from_out @ out_from_map @ map_from_mosaic
                seen = (np.linalg.inv(block_from_mosaic) @ outline)[:2]  # the block's outline in mosaic pixels
                x0, y0 = np.maximum(np.floor(seen.min(1)).astype(int) - 1, 0)
                x1, y1 = np.minimum(np.ceil(seen.max(1)).astype(int) + 2, image.size)
                if x1 <= x0 or y1 <= y0:
                    continue
                window_to_block = block_from_mosaic @ np.array([[1.0, 0.0, x0], [0.0, 1.0, y0], [0.0, 0.0, 1.0]])
                drawn = cv2.warpAffine(image.window(x0, y0, x1, y1), window_to_block[:2], (width, height),
                                       flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0, 0))
                empty = (block[..., 3] == 0) & (drawn[..., 3] > 0)
                block[empty] = drawn[empty]
        return canvas

    try:
        _write_rgba_cog(strip, rows, columns, west, north, pixel, epsg, path)
    finally:
        for image, _ in layers:
            image.close()
    return {"file": path.name, "width": columns, "height": rows, "pixel_size_m": float(pixel), "west": float(west), "north": float(north)}


def _require_rasterio() -> None:
    if not has_rasterio():
        raise UdhError("a GeoTIFF needs rasterio: pip install rasterio (from the udh checkout: pip install '.[geo]')")


BLOCK = 512  # side of a GeoTIFF block, pixels (GDAL's and the COG's usual)
STRIP_ROWS = BLOCK  # rows of the north-up grid drawn at a time: one block high


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
               "tiled": True, "blockxsize": BLOCK, "blockysize": BLOCK, "compress": "NONE", "BIGTIFF": "IF_SAFER"}
    # Uncompressed (4 bytes per map pixel of temporary disk): the COG driver reads it again for every overview
    # level, and with GDAL's cache bounded (GDAL_CACHE_MB) decompressing DEFLATE each time cost a third more time.
    # Named like a staged file (outputs.remove_stale_staged), so that one a killed run leaves is removed by the next.
    strips = path.with_name(f"{path.stem}.strips.staged{path.suffix}")
    try:
        with rasterio.Env(**GDAL_SETTINGS):
            with rasterio.open(strips, "w", **profile) as dataset:
                for top in range(0, rows, STRIP_ROWS):
                    height = min(STRIP_ROWS, rows - top)
                    dataset.write(strip(top, height)[..., [2, 1, 0, 3]].transpose(2, 0, 1), window=Window(0, top, columns, height))
            raster_copy(str(strips), str(path), driver="COG", COMPRESS="DEFLATE", BLOCKSIZE=BLOCK, OVERVIEWS="AUTO")
    finally:
        strips.unlink(missing_ok=True)
