"""Every file a mosaic run reads or writes, named in one place (:class:`RunFiles`, like OpenDroneMap's ``ODM_Tree``).

Stages ask a :class:`RunFiles` (or, for one written image, a :class:`MosaicFiles`) for a path instead of building
a name of their own, so which files belong to a run, and which it may remove, is a question for this module.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from udh_cli.errors import UdhError
from udh_cli.images import check_output_path

OUTPUT_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg")  # the mosaic's own image types
SIDECAR_SUFFIX = ".json"
PREVIEW_SUFFIX = ".preview.jpg"
CAMERAS_SUFFIX = ".cameras.json"  # the lens `--camera estimate` fitted, in OpenSfM's format
PAIR_CACHE_SUFFIX = ".pairs.json"
COG_SUFFIX = ".cog.tif"  # the north-up Cloud Optimized GeoTIFF beside a georeferenced mosaic
PROJECTION_SUFFIX = ".prj"
WORLD_FILE_SUFFIX = {".png": ".pgw", ".tif": ".tfw", ".tiff": ".tfw", ".jpg": ".jgw", ".jpeg": ".jgw"}
LIVE_PICTURE_SUFFIX = ".live.jpg"
LIVE_RECORD_SUFFIX = ".live.json"
REPORT_PAGE_SUFFIX = ".report.html"  # the page to look at a run, beside the mosaic
PAM_SUFFIX = ".aux.xml"  # GDAL's own metadata file, added to the image's whole name: NAME.png.aux.xml
# world and projection files beside a georeferenced mosaic
GEOREFERENCE_SUFFIXES = (*dict.fromkeys(WORLD_FILE_SUFFIX.values()), PROJECTION_SUFFIX, COG_SUFFIX)
MAX_PART_DIGITS = 4  # the name check makes room for part numbers up to 9999


@dataclass(frozen=True)
class MosaicFiles:
    """The files beside one written mosaic image (the run's output or one part of a split run)."""

    image: Path

    def _beside(self, suffix: str) -> Path:
        return self.image.with_name(f"{self.image.stem}{suffix}")

    @property
    def preview(self) -> Path:
        return self._beside(PREVIEW_SUFFIX)

    @property
    def world_file(self) -> Path:
        """ESRI world file: ``.pgw`` for PNG, ``.tfw`` for TIFF, ``.jgw`` for JPEG."""
        suffix = WORLD_FILE_SUFFIX.get(self.image.suffix.lower())
        if suffix is None:
            raise UdhError(f"{self.image}: no world file convention for '{self.image.suffix}'")
        return self.image.with_suffix(suffix)

    @property
    def projection(self) -> Path:
        return self.image.with_suffix(PROJECTION_SUFFIX)

    @property
    def cog(self) -> Path:
        """``NAME.cog.tif`` beside ``NAME.png``."""
        return self._beside(COG_SUFFIX)

    @property
    def pam(self) -> Path:
        """``NAME.png.aux.xml`` beside ``NAME.png``: where GDAL looks for the image's CRS and transform."""
        return self.image.with_name(self.image.name + PAM_SUFFIX)

    @property
    def georeference(self) -> tuple[Path, Path, Path, Path]:
        """World file, projection file, north-up GeoTIFF and GDAL PAM file: what placing the image on the map writes."""
        return self.world_file, self.projection, self.cog, self.pam


@dataclass(frozen=True)
class RunFiles:
    """Every path of a run writing the mosaic ``output``; ``cache_dir``: where the pair cache goes instead of
    beside the mosaic."""

    output: Path
    cache_dir: Path | None = None

    def _beside(self, suffix: str) -> Path:
        return self.output.with_name(f"{self.output.stem}{suffix}")

    @property
    def mosaic(self) -> MosaicFiles:
        return MosaicFiles(self.output)

    @property
    def sidecar(self) -> Path:
        return self.output.with_suffix(SIDECAR_SUFFIX)

    @property
    def preview(self) -> Path:
        return self.mosaic.preview

    @property
    def cameras(self) -> Path:
        """``NAME.cameras.json``: the lens ``--camera estimate`` fitted, in OpenSfM's format."""
        return self._beside(CAMERAS_SUFFIX)

    @property
    def pair_cache(self) -> Path:
        """``NAME.pairs.json`` beside the mosaic, or in ``cache_dir``."""
        beside = self._beside(PAIR_CACHE_SUFFIX)
        return beside if self.cache_dir is None else Path(self.cache_dir) / beside.name

    @property
    def combined_map(self) -> Path:
        """The north-up GeoTIFF of a split run's parts together (``NAME.cog.tif``)."""
        return self.mosaic.cog

    @property
    def report_page(self) -> Path:
        """``NAME.report.html`` beside the mosaic ``NAME.png`` (a split run's parts share it)."""
        return self._beside(REPORT_PAGE_SUFFIX)

    @property
    def live_picture(self) -> Path:
        return self._beside(LIVE_PICTURE_SUFFIX)

    @property
    def live_record(self) -> Path:
        return self._beside(LIVE_RECORD_SUFFIX)

    def parts(self, n_parts: int) -> list[Path]:
        """The mosaic file of each part: ``output`` itself for one part, ``stem.partK.suffix`` for several."""
        if n_parts == 1:
            return [self.output]
        return [self.output.with_name(f"{self.output.stem}.part{k}{self.output.suffix}") for k in range(1, n_parts + 1)]

    def roles(self) -> dict[str, Path]:
        """Every file a run may write over, by what it is (for :func:`.staging.check_outputs_are_not_inputs`)."""
        return {"mosaic": self.output, "sidecar": self.sidecar, "preview": self.preview, "pair cache": self.pair_cache,
                "world file": self.mosaic.world_file, "GeoTIFF": self.combined_map, "projection file": self.mosaic.projection,
                "camera file": self.cameras, "report page": self.report_page, "GDAL metadata file": self.mosaic.pam}

    def live_roles(self) -> dict[str, Path]:
        """The files live mode adds, by what they are."""
        return {"live picture": self.live_picture, "live record": self.live_record}

    def own_files(self) -> list[Path]:
        """Outputs of this run (or an earlier one), which must never be read back as frames."""
        return ([self.output, self.sidecar, self.preview, self._beside(PAIR_CACHE_SUFFIX), self.combined_map, self.live_picture,
                 self.live_record, self.cameras, self.report_page, self.mosaic.pam] + [p for p in self.output.parent.glob(f"{self.output.stem}.part*")])

    def longest_name(self) -> str:
        """The longest file name the run may create, temporary ones included: a part's preview, staged
        (``.NAME.partK.preview.xxxxxxxx.staged.jpg``) and written through a temporary file of
        :func:`udh_cli.images.atomic_write_bytes` (``.<that name>.xxxxxxxx.part``)."""
        part = self.output.with_name(f"{self.output.stem}.part{'9' * MAX_PART_DIGITS}{self.output.suffix}")
        finals = [self.output, part, self.preview, MosaicFiles(part).preview, self.sidecar, MosaicFiles(part).pam]
        written = [f".{f.stem}.{'0' * 8}.staged{f.suffix}" for f in finals] + [self._beside(PAIR_CACHE_SUFFIX).name]  # see StagedFiles.path_for
        return max((f".{name}.{'x' * 8}.part" for name in written), key=lambda name: len(os.fsencode(name)))


def check_output(output: Path) -> None:
    """Fail before any work when the mosaic could not be written."""
    if output.suffix.lower() not in OUTPUT_SUFFIXES:
        raise UdhError(f"{output}: unknown image type '{output.suffix}'; use .png or .tif (they keep the alpha channel)")
    longest, limit = len(os.fsencode(RunFiles(output).longest_name())), _name_max(output.parent)
    if limit is not None and longest > limit:
        raise UdhError(f"{output}: the name is too long for this file system: the files a run writes beside it (NAME.part12.preview.jpg, "
                       f"hidden temporary names) need {longest} bytes where {limit} are allowed; shorten the name to at most "
                       f"{max(1, len(os.fsencode(output.stem)) - (longest - limit))} bytes before its suffix")
    check_output_path(output)  # folder exists and is writable, and the name is not a folder


def _name_max(folder: Path) -> int | None:
    """The longest file name (bytes) ``folder``'s file system takes; None when the folder does not exist."""
    try:
        if not folder.is_dir():
            return None
        return int(os.pathconf(folder, "PC_NAME_MAX"))
    except (OSError, ValueError, AttributeError):  # no pathconf (Windows) or no answer: the usual limit
        return 255
