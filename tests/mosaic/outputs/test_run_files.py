"""RunFiles and MosaicFiles: every file name of a run, made in one place."""

from __future__ import annotations

from pathlib import Path

import pytest

from udh_cli.errors import UdhError
from udh_cli.mosaic.outputs.files import GEOREFERENCE_SUFFIXES, PAM_SUFFIX, MosaicFiles, RunFiles


def test_every_file_of_a_run_is_named_beside_the_mosaic(tmp_path):
    files = RunFiles(tmp_path / "flight.v2.png")
    named = {"sidecar": files.sidecar, "preview": files.preview, "cameras": files.cameras, "pair_cache": files.pair_cache,
             "combined_map": files.combined_map, "live_picture": files.live_picture, "live_record": files.live_record}
    assert {k: p.name for k, p in named.items()} == {
        "sidecar": "flight.v2.json", "preview": "flight.v2.preview.jpg", "cameras": "flight.v2.cameras.json",
        "pair_cache": "flight.v2.pairs.json", "combined_map": "flight.v2.cog.tif", "live_picture": "flight.v2.live.jpg",
        "live_record": "flight.v2.live.json"}
    assert all(p.parent == tmp_path for p in named.values())


def test_parts_are_the_output_itself_or_numbered(tmp_path):
    files = RunFiles(tmp_path / "m.tif")
    assert files.parts(1) == [tmp_path / "m.tif"]
    assert [p.name for p in files.parts(3)] == ["m.part1.tif", "m.part2.tif", "m.part3.tif"]


@pytest.mark.parametrize("image, world", [("m.png", "m.pgw"), ("m.part2.tif", "m.part2.tfw"), ("m.TIFF", "m.tfw"), ("m.jpeg", "m.jgw")])
def test_a_written_image_names_its_georeference_files(tmp_path, image, world):
    names = MosaicFiles(tmp_path / image)
    stem = image.rsplit(".", 1)[0]
    assert [p.name for p in names.georeference] == [world, f"{stem}.prj", f"{stem}.cog.tif", f"{image}.aux.xml"]
    assert names.preview.name == f"{stem}.preview.jpg"
    assert all(p.name.endswith(GEOREFERENCE_SUFFIXES + (PAM_SUFFIX,)) for p in names.georeference)


def test_an_image_type_without_a_world_file_convention_is_refused(tmp_path):
    with pytest.raises(UdhError, match="no world file convention"):
        MosaicFiles(tmp_path / "m.gif").world_file


def test_the_pair_cache_goes_to_the_cache_folder_when_given(tmp_path):
    assert RunFiles(tmp_path / "m.png", tmp_path / "cache").pair_cache == tmp_path / "cache" / "m.pairs.json"
    # what must never be read as a frame stays beside the mosaic
    assert tmp_path / "m.pairs.json" in RunFiles(tmp_path / "m.png", tmp_path / "cache").own_files()


def test_own_files_include_every_part_file_there_is(tmp_path):
    for name in ("m.part1.png", "m.part2.preview.jpg", "other.part1.png"):
        (tmp_path / name).write_bytes(b"")
    own = {p.name for p in RunFiles(tmp_path / "m.png").own_files()}
    assert {"m.png", "m.json", "m.preview.jpg", "m.part1.png", "m.part2.preview.jpg", "m.live.jpg", "m.cameras.json", "m.report.html",
            "m.png.aux.xml"} <= own
    assert "other.part1.png" not in own


def test_roles_name_every_file_a_run_may_write_over(tmp_path):
    files = RunFiles(tmp_path / "m.png")
    assert {k: p.name for k, p in files.roles().items()} == {
        "mosaic": "m.png", "sidecar": "m.json", "preview": "m.preview.jpg", "pair cache": "m.pairs.json", "world file": "m.pgw",
        "GeoTIFF": "m.cog.tif", "projection file": "m.prj", "camera file": "m.cameras.json",
        "report page": "m.report.html", "GDAL metadata file": "m.png.aux.xml"}
    assert {k: p.name for k, p in files.live_roles().items()} == {"live picture": "m.live.jpg", "live record": "m.live.json"}


def test_the_longest_name_is_a_hidden_temporary_of_a_far_part_s_preview(tmp_path):
    longest = RunFiles(tmp_path / "m.png").longest_name()
    assert longest.startswith(".") and longest.endswith(".part")
    assert "m.part9999.preview" in longest


def test_the_longest_name_counts_a_far_part_s_gdal_file_where_it_is_longer():
    # "m.part9999.tiff.aux" is one byte longer than "m.part9999.preview": the staged .aux.xml sets the limit
    assert ".m.part9999.tiff.aux." in RunFiles(Path("/x/m.tiff")).longest_name()


def test_the_report_page_and_the_gdal_file_sit_beside_the_mosaic(tmp_path):
    files = RunFiles(tmp_path / "m.part.png")
    assert files.report_page == tmp_path / "m.part.report.html"
    assert files.mosaic.pam == tmp_path / "m.part.png.aux.xml"
