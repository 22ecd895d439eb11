"""Placing the written parts on the map: by ground-control points, else by their frames' GPS; world files,
projection files and north-up GeoTIFFs staged beside the images, and a split run's parts in one map."""

from __future__ import annotations

import importlib.util
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import cv2
import numpy as np

from udh_cli.errors import UdhError
from udh_cli.images import atomic_write_bytes
from udh_cli.mosaic.georef.gcp import GcpFile, fit_gcps
from udh_cli.mosaic.georef.gcp_scale import check_gcp_fit, residual_lines
from udh_cli.mosaic.georef.geotiff import MosaicImage, has_rasterio, streams_to_file, write_cog, write_combined_cog
from udh_cli.mosaic.georef.gps import MIN_GPS_FRAMES, georeference_part, projection_text, world_file_text
from udh_cli.mosaic.georef.map_files import georeference_mosaic_file
from udh_cli.mosaic.inputs.frames import FrameSet
from udh_cli.mosaic.outputs.files import MosaicFiles, RunFiles
from udh_cli.mosaic.outputs.staging import StagedFiles
from udh_cli.mosaic.report import Reporter


@dataclass(frozen=True)
class PartOnCanvas:
    """A written part: its number, its image file, and each of its frames' ``mosaic_from_frame`` (3, 3), h33 = 1."""

    number: int
    file: Path
    frames: list[int]
    mosaic_from_frame: dict[int, np.ndarray]


@dataclass
class Placement:
    """What placing the parts found: per part number, the sidecar's ``georeference`` (and ``geotiff``); and the
    split run's one ``map``, or None."""

    parts: dict[int, dict[str, Any]] = field(default_factory=dict)
    map: dict[str, Any] | None = None


def georeference(frameset: FrameSet, parts: list[PartOnCanvas], staged: StagedFiles, reporter: Reporter, files: RunFiles,
                 gcps: GcpFile | None = None, gcp_image_width: int | None = None, gcps_in_solve: bool = False,
                 images: Mapping[int, np.ndarray] | None = None, threads: int = 1) -> Placement:
    """World and projection files for every written part placed by ground-control points (``gcps``) or else
    by its frames' GPS (see :mod:`.gcp`, :mod:`.gps`), staged with the images; returns what the sidecar
    records of them. ``gcps_in_solve``: the points also anchored the solve. ``images``: part number -> its
    (H, W, 4) BGRA mosaic as written, drawn into the GeoTIFFs instead of reading the staged file back.
    ``threads``: how many threads GDAL compresses each GeoTIFF on."""
    placement = Placement()
    images = images or {}
    if gcps is not None:
        _georeference_by_gcps(frameset, parts, placement, staged, reporter, gcps, gcp_image_width, gcps_in_solve, images, threads)
        return placement
    with_gps = {f.index: f.metadata for f in frameset.frames if f.metadata is not None and f.metadata.has_gps}
    if not with_gps:
        return placement
    if importlib.util.find_spec("pyproj") is None:
        reporter.warn("the frames carry GPS, but georeferencing needs pyproj: pip install pyproj (from the udh checkout: "
                      "pip install '.[geo]'); the mosaic is written without a world file")
        return placement
    if len(with_gps) < len(frameset.frames):
        reporter.warn(f"{len(frameset.frames) - len(with_gps)} of {len(frameset.frames)} frames carry no GPS; the map rests on the others")
    placed: list[tuple[PartOnCanvas, Any]] = []
    for part in parts:
        entries = [(i, frameset.frames[i].size, part.mosaic_from_frame[i], with_gps[i].latitude, with_gps[i].longitude)
                   for i in part.frames if i in with_gps]
        found = georeference_part(entries, min_frames=2)
        entry = placement.parts[part.number] = {"georeference": None if found is None else found.to_json()}
        if found is None:
            reporter.warn(f"{part.file.name}: fewer than 2 placed frames with GPS; written without a georeference")
            continue
        if len(found.frames_used) < MIN_GPS_FRAMES:
            reporter.warn(f"{part.file.name}: placed by 2 frames' GPS only, with nothing to check the placement")
        placed.append((part, found))
        if found.frames_rejected:
            names = ", ".join(frameset.frames[i].name for i in found.frames_rejected)
            reporter.warn(f"{part.file.name}: the GPS of {names} disagrees with the other frames' by far (a bad fix); left out of the georeference")
        _write_georeference(part, found, staged, entry, reporter, images.get(part.number), threads)
        reporter.info(f"{part.file.name}: georeferenced in EPSG:{found.epsg} from {len(found.frames_used)} frames' GPS, "
                      f"{found.residual_rms_m:.1f} m RMS, {found.pixel_size_m * 100:.1f} cm per pixel")
    if len(placed) > 1 and has_rasterio():
        placement.map = _write_combined_map(placed, staged, reporter, files.combined_map, images, threads)
    return placement


def _write_combined_map(placed: list, staged: StagedFiles, reporter: Reporter, path: Path,
                        images: Mapping[int, np.ndarray], threads: int) -> dict[str, Any] | None:
    """The parts of a split run in one north-up GeoTIFF, each placed by its own frames' GPS: GPS ties together
    what no estimated pair could. The largest part is drawn on top; the others' frames rest on GPS alone.
    Returns the sidecar's ``map``, or None for none."""
    epsg = max(placed, key=lambda item: len(item[0].frames))[1].epsg  # the largest part's zone
    same_zone = sorted((item for item in placed if item[1].epsg == epsg), key=lambda item: -len(item[0].frames))
    if len(same_zone) < len(placed):
        reporter.warn(f"{len(placed) - len(same_zone)} part(s) lie in another UTM zone than EPSG:{epsg} and are left out of the one map")
    layers = []
    for part, found in same_zone:
        image = _staged_bgra(staged, part, images.get(part.number))
        if image is None:
            reporter.warn(f"{part.file.name}: its image could not be read back; left out of the one map")
            continue
        layers.append((image, found.map_from_mosaic))
    if len(layers) < 2:
        return None
    try:
        written = write_combined_cog(layers, epsg, staged.path_for(path), threads=threads)
    except UdhError as exc:  # the one map is an extra: the parts and their own georeferences still stand
        staged.forget(path)
        reporter.warn(f"no combined map: {exc}")
        return None
    on_gps_alone = sum(len(part.frames) for part, _ in same_zone[1:])
    entry = {**written, "file": path.name, "crs": f"EPSG:{epsg}", "parts": len(same_zone),
             "frames": sum(len(part.frames) for part, _ in same_zone), "frames_on_gps_alone": on_gps_alone}
    reporter.info(f"{path.name}: {len(same_zone)} parts in one map, placed by GPS; {on_gps_alone} frames "
                  f"rest on GPS alone (outside the largest part)")
    return entry


def _staged_bgra(staged: StagedFiles, part: PartOnCanvas, image: np.ndarray | None = None) -> MosaicImage | None:
    """A part's mosaic as written this run: ``image`` (H, W, 4) BGRA when the caller holds it, else its staged
    file, a streamed TIFF read window by window or the image read whole; None if it cannot be read."""
    if image is not None:
        return MosaicImage(array=image)
    temporary = staged.temporary_of(part.file)
    if temporary is None:
        return None
    if streams_to_file(part.file):
        try:
            return MosaicImage(path=temporary)
        except UdhError:
            return None
    image = cv2.imread(str(temporary), cv2.IMREAD_UNCHANGED)
    if image is None or image.ndim != 3 or image.dtype != np.uint8:
        return None
    return MosaicImage(array=image if image.shape[2] == 4 else cv2.cvtColor(image, cv2.COLOR_BGR2BGRA))  # a JPEG mosaic has no alpha


def _write_georeference(part: PartOnCanvas, found, staged: StagedFiles, entry: dict[str, Any], reporter: Reporter,
                        image: np.ndarray | None = None, threads: int = 1) -> None:
    """Stage a georeferenced part's world file, .prj, GDAL PAM file and north-up COG (when rasterio is installed)."""
    names = MosaicFiles(part.file)
    atomic_write_bytes(staged.path_for(names.world_file), world_file_text(found).encode())
    atomic_write_bytes(staged.path_for(names.projection), projection_text(found.epsg).encode())
    georeference_mosaic_file(names, found.map_from_mosaic, found.epsg, staged)  # GDAL reads neither of the two above for a rotated PNG
    if not has_rasterio():
        reporter.warn("no north-up GeoTIFF: it needs rasterio (pip install rasterio; from the udh checkout: pip install '.[geo]')")
        return
    mosaic = _staged_bgra(staged, part, image)
    if mosaic is None:
        reporter.warn(f"{part.file.name}: its image could not be read back for the GeoTIFF; written without one")
        return
    try:
        written = write_cog(mosaic, found.map_from_mosaic, found.epsg, staged.path_for(names.cog), threads=threads)
    except UdhError as exc:  # the GeoTIFF is an extra: the mosaic and its world file still stand
        staged.forget(names.cog)
        reporter.warn(f"{part.file.name}: no north-up GeoTIFF: {exc}")
        return
    entry["geotiff"] = {**written, "file": names.cog.name}


def _georeference_by_gcps(frameset: FrameSet, parts: list[PartOnCanvas], placement: Placement, staged: StagedFiles, reporter: Reporter,
                          gcps: GcpFile, gcp_image_width: int | None, in_solve: bool, images: Mapping[int, np.ndarray],
                          threads: int) -> None:
    for part in parts:
        frames = {f.name: (f.size, part.mosaic_from_frame.get(f.index)) for f in frameset.frames}
        entry = placement.parts[part.number] = {}
        try:
            found = fit_gcps(gcps, frames, gcp_image_width)
        except UdhError as exc:
            entry["georeference"] = None
            reporter.warn(f"{part.file.name}: not georeferenced: {exc}")
            continue
        check_gcp_fit(found, lambda width: fit_gcps(gcps, frames, width), gcp_image_width, frameset.frames)  # before any map
        entry["georeference"] = found.to_json()
        entry["georeference"]["gcp_points_in_solve"] = in_solve  # then a checkpoint left out of the fit was still in the solve
        entry["georeference"]["gcp_image_width"] = gcp_image_width  # None: the frames' own pixels
        for name, point in found.points.items():
            if not point["used"]:
                reporter.warn(f"{name}: contradicts the other ground-control points ({point['checkpoint_m']:.1f} m off when left out); "
                              f"reported and left out of the fit")
        for line in found.skipped[:5]:
            reporter.warn(f"GCP skipped: {line}")
        _write_georeference(part, found, staged, entry, reporter, images.get(part.number), threads)
        used = sum(p["used"] for p in found.points.values())
        reporter.info(f"{part.file.name}: georeferenced in EPSG:{found.epsg} by {used} ground-control points, "
                      f"{found.checkpoint_rms_m:.2f} m RMS at checkpoints (each point left out of the fit in turn"
                      + ("; optimistic, as the points also anchor the solve)" if in_solve else ")"))
        for line in residual_lines(found):
            reporter.info(line)
