"""GeoTIFFs (rasterio, whose wheels bundle GDAL): a mosaic streamed tile by tile, and the north-up COG.

The mosaic is drawn in its reference frame's pixels; a ``.tif`` mosaic is written tile by tile as it is blended
(:func:`write_tiled_tiff`), so that its area costs no memory. The georeference (:mod:`.gps`, :mod:`.gcp`)
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

# GDAL's block cache, in MB. Its default is 5 % of the machine's memory (1.2 GB here), which it fills while it
# copies a large map into a COG with overviews: seneca's run peaked at 1.21 GB with it, 0.76 GB with this.
GDAL_CACHE_MB = 128
GDAL_SETTINGS = {"GDAL_NUM_THREADS": "1", "GDAL_CACHEMAX": GDAL_CACHE_MB}


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
        return cv2.cvtColor(np.ascontiguousarray(rgba.transpose(1, 2, 0)), cv2.COLOR_RGBA2BGRA)

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
                    dataset.write(cv2.cvtColor(tile, cv2.COLOR_BGRA2RGBA).transpose(2, 0, 1), window=Window(x0, y0, x1 - x0, y1 - y0))
    except (RasterioError, OSError) as exc:  # a full disk, a folder that went away: one line, and the caller discards the file
        raise UdhError(f"{path}: writing the mosaic failed ({exc}); check the free space and permissions") from None


def write_cog(mosaic: MosaicImage, map_from_mosaic: np.ndarray, epsg: int, path: Path, max_pixels: int = 400_000_000,
              threads: int = 1) -> dict:
    """Resample a mosaic north-up and write it as a COG at ``path``; returns its size and grid."""
    return write_combined_cog([(mosaic, map_from_mosaic)], epsg, path, max_pixels, threads)


def write_combined_cog(layers: list[tuple[MosaicImage, np.ndarray]], epsg: int, path: Path, max_pixels: int = 400_000_000,
                       threads: int = 1) -> dict:
    """Several mosaics (``(image, map_from_mosaic)``, earlier ones on top) resampled onto one north-up grid of
    the finest pixel size among them, written as one COG: the parts of a split flight in one map. Each strip
    of the grid reads only the window of each mosaic it covers; the mosaics' files are closed at the end.
    ``threads``: how many threads GDAL compresses the COG's blocks on (the same file for any count)."""
    _require_rasterio()
    pixel = min(math.hypot(m[0, 0], m[1, 0]) for _, m in layers)
    edges = []
    for image, map_from_mosaic in layers:
        width, height = image.size
        corners = np.array([[-0.5, -0.5, 1], [width - 0.5, -0.5, 1], [width - 0.5, height - 0.5, 1], [-0.5, height - 0.5, 1]]).T
        edges.append((map_from_mosaic @ corners)[:2])
    mapped = np.hstack(edges)
    west, east, south, north = mapped[0].min(), mapped[0].max(), mapped[1].min(), mapped[1].max()
    columns, rows = padded_for_overviews(int(math.ceil((east - west) / pixel)), int(math.ceil((north - south) / pixel)))
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
            empty = True  # the first layer that reaches a block is copied into it, not masked against the ones before
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
                if empty:
                    block[...] = drawn
                    # No colour under no alpha: the overviews average the strips as premultiplied colour.
                    np.copyto(block, 0, where=drawn[..., 3:] == 0)
                    empty = False
                else:
                    np.copyto(block, drawn, where=((block[..., 3] == 0) & (drawn[..., 3] > 0))[..., None])
        return canvas

    try:
        _write_rgba_cog(strip, rows, columns, west, north, pixel, epsg, path, threads)
    finally:
        for image, _ in layers:
            image.close()
    return {"file": path.name, "width": columns, "height": rows, "pixel_size_m": float(pixel), "west": float(west), "north": float(north)}


def _require_rasterio() -> None:
    if not has_rasterio():
        raise UdhError("a GeoTIFF needs rasterio: pip install rasterio (from the udh checkout: pip install '.[geo]')")


BLOCK = 512  # side of a GeoTIFF block, pixels (GDAL's and the COG's usual)
STRIP_ROWS = BLOCK  # rows of the north-up grid drawn at a time: one block high
COG_DEFLATE_LEVEL = 1  # DEFLATE's fastest: a sixth less CPU than GDAL's 6 for a slightly larger file (docs/mosaic.md, "Georeferencing from GPS")


def _write_rgba_cog(strip, rows: int, columns: int, west: float, north: float, pixel: float, epsg: int, path: Path,
                    threads: int = 1) -> None:
    """A north-up image drawn strip by strip (``strip(top, height)`` -> (height, columns, 4) BGRA) to a
    Cloud-Optimised GeoTIFF: RGBA with an alpha band, tiled, DEFLATE, overviews; (west, north) is the outer
    corner of the top-left pixel; GDAL compresses its blocks on ``threads`` threads.

    Memory stays at about two strips: the strips go to a tiled GeoTIFF beside ``path`` and its overviews to
    one more per level (:class:`_OverviewPyramid`); a VRT ties them together and GDAL's COG driver copies it
    block by block, overviews included. The temporary files are removed afterwards whatever happens.
    """
    import warnings

    import rasterio
    from rasterio.errors import NotGeoreferencedWarning, RasterioError
    from rasterio.shutil import copy as raster_copy
    from rasterio.windows import Window

    profile = _temporary_profile(columns, rows)
    # Uncompressed (4 bytes per map pixel of temporary disk): the COG driver reads every file once more, and
    # DEFLATE there cost more time than the disk. Named like staged files (outputs.remove_stale_staged), so
    # that those a killed run leaves are removed by the next.
    strips = path.with_name(f"{path.stem}.strips.staged{path.suffix}")
    levels = path.with_name(f"{path.stem}.levels.staged.vrt")
    pyramid = _OverviewPyramid(columns, rows, lambda level: path.with_name(f"{path.stem}.overview{level}.staged{path.suffix}"))
    try:
        with rasterio.Env(**GDAL_SETTINGS), warnings.catch_warnings():
            warnings.simplefilter("ignore", NotGeoreferencedWarning)  # the temporary files: the VRT holds the georeference
            with rasterio.open(strips, "w", **profile) as dataset, pyramid:
                for top in range(0, rows, STRIP_ROWS):
                    height = min(STRIP_ROWS, rows - top)
                    rgba = cv2.cvtColor(strip(top, height), cv2.COLOR_BGRA2RGBA)
                    dataset.write(rgba.transpose(2, 0, 1), window=Window(0, top, columns, height))
                    pyramid.add(rgba, last=top + height >= rows)
            levels.write_text(_vrt_with_overviews(strips, pyramid.files, columns, rows, west, north, pixel, epsg), encoding="utf-8")
            raster_copy(str(levels), str(path), driver="COG", COMPRESS="DEFLATE", LEVEL=COG_DEFLATE_LEVEL, BLOCKSIZE=BLOCK, OVERVIEWS="AUTO",
                        NUM_THREADS=str(max(1, threads)))
    except (RasterioError, OSError) as exc:  # a full disk, a folder that went away: one line, and the caller goes on without it
        raise UdhError(f"{path.name}: writing the GeoTIFF failed ({exc}); check the free space and permissions") from None
    finally:
        for temporary in [strips, levels, *pyramid.files]:
            temporary.unlink(missing_ok=True)


def _temporary_profile(columns: int, rows: int) -> dict:
    """A tiled, uncompressed RGBA GeoTIFF of ``columns`` x ``rows`` without a georeference (the VRT holds it)."""
    return {"driver": "GTiff", "width": columns, "height": rows, "count": 4, "dtype": "uint8", "photometric": "RGB",
            "alpha": "YES", "tiled": True, "blockxsize": BLOCK, "blockysize": BLOCK, "compress": "NONE", "BIGTIFF": "IF_SAFER"}


def overview_count(columns: int, rows: int) -> int:
    """How many times a map of ``columns`` x ``rows`` is halved until it fits one :data:`BLOCK`."""
    count = 0
    while max(columns, rows) > BLOCK:
        columns, rows, count = (columns + 1) // 2, (rows + 1) // 2, count + 1
    return count


def padded_for_overviews(columns: int, rows: int) -> tuple[int, int]:
    """``columns`` and ``rows`` rounded up to a multiple of 2^:func:`overview_count` (transparent pixels at the
    right and bottom), so that every overview pixel covers exactly 2x2 of the level below, as GDAL assumes when
    it scales a level's extent."""
    step = 2 ** overview_count(columns, rows)
    return -(-columns // step) * step, -(-rows // step) * step


def halve_rgba(rgba: np.ndarray) -> np.ndarray:
    """(h, w, 4) RGBA uint8, h and w even, colour premultiplied by alpha (0 outside the map, dimmed where a
    pixel is partly covered, as warping with a transparent border leaves it) -> (h/2, w/2, 4): the area
    average, still premultiplied, for the next level."""
    height, width = rgba.shape[:2]
    return cv2.resize(rgba, (width // 2, height // 2), interpolation=cv2.INTER_AREA)


def straight_alpha(premultiplied: np.ndarray) -> np.ndarray:
    """(h, w, 4) RGBA uint8 with premultiplied colour -> colour divided by alpha where a pixel is partly covered:
    what a viewer composites (TIFF's unassociated alpha). Without it every overview would darken along the
    map's edges towards the empty pixels outside."""
    out = premultiplied.copy()
    alpha = out[..., 3]
    edge = (alpha > 0) & (alpha < 255)
    if edge.any():
        partial = out[edge].astype(np.float32)
        partial[:, :3] *= 255.0 / partial[:, 3:]
        out[edge] = np.minimum(partial + 0.5, 255.0).astype(np.uint8)
    return out


class _OverviewPyramid:
    """A COG's overview levels, each half the size of the one below (:func:`halve_rgba`) down to one block,
    built from the map's strips as they are drawn and written to one temporary tiled GeoTIFF per level.

    Why not GDAL's own: its COG driver computes the overviews by reading the whole map back for every level,
    with cubic resampling, most of a large map's COG time (docs/benchmarks.md, "2026-11-25, later: confirmed
    network answers, the COG's own overviews"). Each level holds at most one block's height of rows of the level below, so memory
    stays at about one strip.
    """

    def __init__(self, columns: int, rows: int, level_path) -> None:
        self.sizes = [(columns >> level, rows >> level) for level in range(1, overview_count(columns, rows) + 1)]
        if padded_for_overviews(columns, rows) != (columns, rows):
            raise ValueError(f"a {columns}x{rows} map does not halve evenly; pad it with padded_for_overviews")
        self.files = [level_path(level + 1) for level in range(len(self.sizes))]
        self._datasets: list = []
        self._pending: list[np.ndarray | None] = [None] * len(self.sizes)  # rows of level k waiting to be halved
        self._written = [0] * len(self.sizes)

    def __enter__(self) -> "_OverviewPyramid":
        import rasterio

        try:
            for file, (columns, rows) in zip(self.files, self.sizes):
                self._datasets.append(rasterio.open(file, "w", **_temporary_profile(columns, rows)))
        except BaseException:  # __exit__ does not run when __enter__ fails: close what did open
            self.__exit__()
            raise
        return self

    def __exit__(self, *exc) -> None:
        for dataset in self._datasets:
            dataset.close()
        self._datasets = []

    def add(self, rgba: np.ndarray, last: bool, level: int = 0) -> None:
        """The next rows (h, columns, 4) RGBA of ``level`` (0: the map itself); ``last`` after the bottom row.
        Rows are halved in runs of at least :data:`BLOCK` (an even count but for the last)."""
        if level >= len(self.sizes):
            return
        pending = self._pending[level]
        rows = rgba if pending is None else np.concatenate([pending, rgba])
        if len(rows) < BLOCK and not last:
            self._pending[level] = rows
            return
        self._pending[level] = None
        half = halve_rgba(rows)  # premultiplied, as the level below: the next level halves this, not the written copy
        from rasterio.windows import Window

        self._datasets[level].write(straight_alpha(half).transpose(2, 0, 1), window=Window(0, self._written[level], half.shape[1], half.shape[0]))
        self._written[level] += len(half)
        self.add(half, last, level + 1)


def _vrt_with_overviews(base: Path, overviews: list[Path], columns: int, rows: int, west: float, north: float,
                        pixel: float, epsg: int) -> str:
    """A GDAL VRT of the RGBA ``base`` file with ``overviews`` as its overview levels, north-up in EPSG
    ``epsg``: what the COG driver copies (it keeps a source's overviews rather than computing its own)."""
    from xml.sax.saxutils import escape

    west, north, pixel = float(west), float(north), float(pixel)  # repr() of a numpy scalar is not a number
    bands = []
    for band, colour in enumerate(["Red", "Green", "Blue", "Alpha"], start=1):
        levels = "".join(f'<Overview><SourceFilename relativeToVRT="1">{escape(level.name)}</SourceFilename>'
                         f"<SourceBand>{band}</SourceBand></Overview>" for level in overviews)
        bands.append(f'<VRTRasterBand dataType="Byte" band="{band}"><ColorInterp>{colour}</ColorInterp>'
                     f'<SimpleSource><SourceFilename relativeToVRT="1">{escape(base.name)}</SourceFilename>'
                     f"<SourceBand>{band}</SourceBand></SimpleSource>{levels}</VRTRasterBand>")
    return (f'<VRTDataset rasterXSize="{columns}" rasterYSize="{rows}"><SRS>EPSG:{epsg}</SRS>'
            f"<GeoTransform>{west!r}, {pixel!r}, 0.0, {north!r}, 0.0, {-pixel!r}</GeoTransform>{''.join(bands)}</VRTDataset>")


def streams_to_file(path: Path) -> bool:
    """Whether a mosaic written to ``path`` streams tile by tile (a TIFF, with rasterio) rather than being held
    whole to be encoded (PNG, JPEG)."""
    return path.suffix.lower() in (".tif", ".tiff") and has_rasterio()
