"""Output hygiene of split runs: the parts appear together or not at all, and an earlier run's extra parts go."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import pytest

from udh_cli.errors import UdhError
from udh_cli.files import MANIFEST_NAME, record_written
from udh_cli.mosaic import MosaicConfig, Reporter, run_mosaic
from udh_cli.mosaic.render import composite as compositing
from udh_cli.mosaic.outputs.files import RunFiles
from udh_cli.mosaic.outputs.staging import STALE_AFTER_S, StagedFiles, remove_stale_files, stale_part_files

from mosaic_flights import SMALL, FailOn, make_flight, work_fingerprints

FAST = MosaicConfig(overlap_per_frame=1, batch_size=4)


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """8 frames on two lines; ``split`` fails every pair across the lines, so a run makes two parts."""
    folder = tmp_path_factory.mktemp("flight")
    prints = work_fingerprints(make_flight(folder, SMALL, seed=4))
    return folder, prints


def split(prints):
    return FailOn(prints, lambda a, b: a is not None and b is not None and (a < 4) != (b < 4))


def snapshot(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def listed(folder: Path) -> list[str]:
    """The file names in ``folder``, udh's record of what it wrote left out."""
    return sorted(p.name for p in folder.iterdir() if p.name != MANIFEST_NAME)


def fail_in_part(monkeypatch, number: int) -> None:
    """Make the compositing of part ``number`` (1-based, in order) fail, as a full disk or a bug would."""
    real, calls = compositing.composite_tiles, []

    def composite_tiles(*args, **kwargs):
        calls.append(1)
        if len(calls) == number:
            raise UdhError("made to fail by the test")
        return real(*args, **kwargs)

    monkeypatch.setattr(compositing, "composite_tiles", composite_tiles)


def test_a_failing_later_part_leaves_no_part_behind(flight, tmp_path, monkeypatch):
    folder, prints = flight
    fail_in_part(monkeypatch, 2)
    with pytest.raises(UdhError, match="made to fail"):
        run_mosaic(folder, tmp_path / "m.png", FAST, estimator=split(prints), fallback=split(prints))
    assert [p.name for p in tmp_path.iterdir()] == []  # no part 1, no preview, no temporary file


def test_a_failing_later_part_leaves_the_earlier_run_whole(flight, tmp_path, monkeypatch):
    folder, prints = flight
    out = tmp_path / "m.png"
    run_mosaic(folder, out, FAST, estimator=split(prints), fallback=split(prints))
    before = snapshot(tmp_path)
    assert sorted(set(before) - {MANIFEST_NAME}) == ["m.json", "m.part1.png", "m.part1.preview.jpg", "m.part2.png", "m.part2.preview.jpg", "m.report.html"]
    fail_in_part(monkeypatch, 2)
    with pytest.raises(UdhError, match="made to fail"):  # another blend: part 1 would differ from the earlier one
        run_mosaic(folder, out, MosaicConfig(overlap_per_frame=1, batch_size=4, blend="none"), estimator=split(prints), fallback=split(prints))
    assert snapshot(tmp_path) == before  # byte for byte: images, previews and sidecar


def test_stale_parts_of_an_earlier_run_are_removed_and_nothing_else(flight, tmp_path):
    folder, prints = flight
    out = tmp_path / "m.png"
    others = ["m.part3.tif", "m.partial.png", "mm.part3.png", "m.part3.png.bak", "other.part3.png", "m.part0.png", "m.part3.jpg", "notes.txt"]
    for name in ["m.part3.png", "m.part3.preview.jpg", "m.part12.png", *others]:
        (tmp_path / name).write_bytes(b"earlier")
    record_written(*(tmp_path / name for name in ["m.part3.png", "m.part3.preview.jpg", "m.part12.png"]), run=out.name)  # an earlier run's
    report = run_mosaic(folder, out, FAST, estimator=split(prints), fallback=split(prints))
    assert report["summary"]["parts"] == 2
    expected = ["m.json", "m.part1.png", "m.part1.preview.jpg", "m.part2.png", "m.part2.preview.jpg", "m.report.html"]
    assert listed(tmp_path) == sorted(expected + others)

    # Now in one part, without previews: every part file goes, and the single mosaic takes their place.
    reporter = Reporter(quiet=True)
    report = run_mosaic(folder, out, MosaicConfig(overlap_per_frame=1, batch_size=4, preview=False), reporter, estimator=FailOn(prints, lambda a, b: False))
    assert report["summary"]["parts"] == 1
    assert listed(tmp_path) == sorted(["m.json", "m.png", "m.report.html", *others])
    assert json.loads((tmp_path / "m.json").read_text())["parts"][0]["file"] == out.name  # relative to the sidecar

    # Split again: the single mosaic of the run before is not a part file; it stays, with a warning.
    reporter = Reporter(quiet=True)
    run_mosaic(folder, out, MosaicConfig(overlap_per_frame=1, batch_size=4, preview=False), reporter, estimator=split(prints), fallback=split(prints))
    assert listed(tmp_path) == sorted(["m.json", "m.png", "m.part1.png", "m.part2.png", "m.report.html", *others])
    assert any("m.png is left from an earlier run" in w for w in reporter.warnings)


def test_stale_part_files_matches_only_this_outputs_part_names(tmp_path):
    out = tmp_path / "run.v2.tif"
    names = ["run.v2.part1.tif", "run.v2.part2.preview.jpg", "run.v2.part7.tif", "run.v2.part1.png", "run.v2.tif", "run.v2.preview.jpg", "runXv2.part1.tif", "run.v2.part1.tif.json"]
    for name in names:
        (tmp_path / name).write_bytes(b"x")
    record_written(*(tmp_path / name for name in names), run=out.name)
    (tmp_path / "run.v2.part9.tif").mkdir()  # a folder is never removed
    stale = stale_part_files(out, [tmp_path / "run.v2.part1.tif"])
    assert [p.name for p in stale] == ["run.v2.part2.preview.jpg", "run.v2.part7.tif"]


def test_gdal_files_this_run_did_not_write_are_removed_and_nothing_else(tmp_path):
    """A stale NAME.png.aux.xml would put a new mosaic on the map where the old one lay: GDAL reads it first."""
    names = ["m.png.aux.xml", "m.part1.png.aux.xml", "m.part3.png.aux.xml", "m.part3.png.aux.xml.bak", "m.part3.tif.aux.xml", "m.aux.xml"]
    for name in names:
        (tmp_path / name).write_bytes(b"x")
    record_written(*(tmp_path / name for name in names), run="m.png")
    reporter = Reporter(quiet=True)
    remove_stale_files(RunFiles(tmp_path / "m.png"), [tmp_path / "m.part1.png", tmp_path / "m.part1.png.aux.xml"],
                       [tmp_path / "m.png", tmp_path / "m.part1.png"], reporter)
    assert listed(tmp_path) == ["m.aux.xml", "m.part1.png.aux.xml", "m.part3.png.aux.xml.bak", "m.part3.tif.aux.xml"]


def test_staged_files_keep_the_permissions_of_the_file_they_replace(tmp_path):
    final = tmp_path / "m.png"
    final.write_bytes(b"old")
    final.chmod(0o640)
    staged = StagedFiles()
    temporary = staged.path_for(final)
    assert temporary.parent == tmp_path and temporary.name.startswith(".") and temporary.suffix == ".png"
    temporary.write_bytes(b"new")
    staged.publish()
    assert final.read_bytes() == b"new" and final.stat().st_mode & 0o777 == 0o640
    assert [p.name for p in tmp_path.iterdir()] == ["m.png"]


def test_an_output_named_as_an_input_frame_is_refused_before_any_work(flight, tmp_path):
    folder, _ = flight
    frame = sorted(p for p in folder.iterdir() if p.suffix in (".png", ".jpg"))[2]
    before = frame.read_bytes()
    with pytest.raises(UdhError, match="would replace an input file"):
        run_mosaic(folder, frame, FAST)
    assert frame.read_bytes() == before


def test_a_foreign_json_beside_the_output_is_never_replaced(flight, tmp_path):
    folder, _ = flight
    foreign = tmp_path / "package.json"
    foreign.write_text('{"name": "not udh"}')
    with pytest.raises(UdhError, match="did not write"):
        run_mosaic(folder, tmp_path / "package.png", FAST)
    assert foreign.read_text() == '{"name": "not udh"}'
    assert not (tmp_path / "package.png").exists()


def test_temporary_files_of_a_killed_run_are_removed_by_the_next(flight, tmp_path):
    folder, _ = flight
    leftovers = [tmp_path / ".m.0a1b2c3d.staged.png", tmp_path / ".m.json.x7_k2m9q.part", tmp_path / ".m.part2.preview.0a1b2c3d.staged.jpg"]
    unrelated = [tmp_path / ".other.0a1b2c3d.staged.png", tmp_path / "m.part"]
    for path in leftovers + unrelated:
        path.write_bytes(b"x" * 100)
    report = run_mosaic(folder, tmp_path / "m.png", FAST)
    assert report["summary"]["placed"] >= 2
    assert not any(p.exists() for p in leftovers)
    assert all(p.exists() for p in unrelated)
    assert json.loads((tmp_path / "m.json").read_text())["format"].startswith("udh-mosaic/")


def test_the_pair_cache_is_written_only_when_asked_and_the_sidecar_paths_are_relative(flight, tmp_path):
    folder, _ = flight
    run_mosaic(folder, tmp_path / "m.png", FAST)
    assert not (tmp_path / "m.pairs.json").exists()
    sidecar = json.loads((tmp_path / "m.json").read_text())
    assert sidecar["pair_cache"] is None and not Path(sidecar["source"]).is_absolute()
    assert (tmp_path / sidecar["source"]).resolve() == folder.resolve()
    caches = tmp_path / "caches"
    caches.mkdir()
    run_mosaic(folder, tmp_path / "n.png", FAST, cache_dir=caches)
    assert (caches / "n.pairs.json").is_file() and not (tmp_path / "n.pairs.json").exists()
    assert json.loads((tmp_path / "n.json").read_text())["pair_cache"] == "caches/n.pairs.json"
    with pytest.raises(UdhError, match="no such folder"):
        run_mosaic(folder, tmp_path / "o.png", FAST, cache_dir=tmp_path / "missing")


def test_a_live_quick_look_s_fresh_temporary_stays_until_it_is_stale(tmp_path):
    from udh_cli.mosaic.outputs.staging import remove_stale_staged

    staged, fresh_live, old_live = tmp_path / ".m.abcd.staged.png", tmp_path / ".m.live.jpg.x1y2.part", tmp_path / ".m.live.json.x9.part"
    for path in (staged, fresh_live, old_live):
        path.write_bytes(b"x")
    long_ago = time.time() - STALE_AFTER_S - 5
    os.utime(old_live, (long_ago, long_ago))
    assert sorted(remove_stale_staged(tmp_path / "m.png")) == sorted([staged, old_live])  # a killed run's, whatever their age
    assert fresh_live.exists()  # the quick look may be writing it right now


def test_a_mosaic_written_among_its_frames_is_not_stitched_in_by_the_next_run(tmp_path):
    folder = tmp_path / "flight"
    make_flight(folder, SMALL, seed=4)
    first = run_mosaic(folder, folder / "inside.png", FAST)
    assert (folder / "inside.png").is_file() and (folder / "inside.preview.jpg").is_file()
    # A later run under another name: the earlier mosaic and its preview are an earlier run's outputs, not frames.
    second = run_mosaic(folder, tmp_path / "outside.png", FAST)
    assert second["summary"]["frames"] == first["summary"]["frames"] == 8
    skipped = {entry["file"]: entry["reason"] for entry in second["skipped_files"]}
    assert set(skipped) >= {"inside.png", "inside.preview.jpg"} and "inside.json" in skipped["inside.png"]
    # An image beside a JSON that is not a udh sidecar is still a frame.
    (folder / "extra.json").write_text('{"format": "something else"}')
    (folder / "extra.png").write_bytes((folder / "frame_000.jpg").read_bytes())
    third = run_mosaic(folder, tmp_path / "third.png", FAST)
    assert third["summary"]["frames"] == 9


def test_warnings_print_file_names_and_commands_with_brackets_as_they_are(capsys):
    from rich.console import Console

    reporter = Reporter(console=Console(file=None, stderr=True, width=200))
    reporter.warn("georeferencing needs pyproj: pip install '.[geo]'; skipping notes[draft].txt")
    reporter.info("see [bold] here")
    printed = capsys.readouterr().err
    assert "pip install '.[geo]'" in printed and "notes[draft].txt" in printed and "see [bold] here" in printed


def test_a_user_s_file_named_like_a_part_is_neither_removed_nor_replaced(flight, tmp_path):
    folder, prints = flight
    out = tmp_path / "map.png"
    for name in ["map.part1.png", "map.part3.png", "map.part3.preview.jpg"]:
        (tmp_path / name).write_bytes(b"the user's")
    run_mosaic(folder, out, FAST, estimator=FailOn(prints, lambda a, b: False))  # one part: no earlier run of map.png
    assert all((tmp_path / name).read_bytes() == b"the user's" for name in ["map.part1.png", "map.part3.png", "map.part3.preview.jpg"])
    before = snapshot(tmp_path)
    with pytest.raises(UdhError, match=r"map.part1.png: exists and no earlier run to map.png wrote it.*--overwrite"):
        run_mosaic(folder, out, FAST, estimator=split(prints), fallback=split(prints))  # two parts: part 1 is in the way
    assert snapshot(tmp_path) == before


def test_another_run_s_mosaic_named_like_a_part_is_left_to_it(flight, tmp_path):
    folder, prints = flight
    run_mosaic(folder, tmp_path / "m.part1.png", FAST, estimator=FailOn(prints, lambda a, b: False))
    theirs = snapshot(tmp_path)
    assert {"m.part1.png", "m.part1.preview.jpg", "m.part1.json"} <= set(theirs)
    run_mosaic(folder, tmp_path / "m.png", FAST, estimator=FailOn(prints, lambda a, b: False))
    assert all((tmp_path / name).read_bytes() == data for name, data in theirs.items() if name != MANIFEST_NAME)
    with pytest.raises(UdhError, match="m.part1.png: exists and no earlier run to m.png wrote it"):
        run_mosaic(folder, tmp_path / "m.png", FAST, estimator=split(prints), fallback=split(prints))
    assert all((tmp_path / name).read_bytes() == data for name, data in theirs.items() if name != MANIFEST_NAME)


def test_a_run_under_another_suffix_leaves_the_earlier_run_s_sidecar_and_map_files(flight, tmp_path):
    folder, prints = flight
    run_mosaic(folder, tmp_path / "m.png", FAST, estimator=FailOn(prints, lambda a, b: False))
    for name in ["m.prj", "m.cog.tif"]:  # as a georeferenced run writes them
        (tmp_path / name).write_bytes(b"map")
    record_written(tmp_path / "m.prj", tmp_path / "m.cog.tif", run="m.png")
    before = snapshot(tmp_path)
    with pytest.raises(UdhError, match=r"m.json: the sidecar of the mosaic m.png, written by another run than one to m.tif; add --overwrite"):
        run_mosaic(folder, tmp_path / "m.tif", FAST, estimator=FailOn(prints, lambda a, b: False))
    assert snapshot(tmp_path) == before
    # Asked to overwrite: the sidecar and preview go to the new run, the other run's map files stay.
    run_mosaic(folder, tmp_path / "m.tif", FAST, estimator=FailOn(prints, lambda a, b: False), overwrite=True)
    assert (tmp_path / "m.prj").read_bytes() == (tmp_path / "m.cog.tif").read_bytes() == b"map"
    assert json.loads((tmp_path / "m.json").read_text())["parts"][0]["file"] == "m.tif"


def test_an_output_is_never_a_frame_whatever_an_earlier_run_in_the_folder_wrote(tmp_path):
    folder = tmp_path / "flight"
    make_flight(folder, SMALL, seed=4)
    run_mosaic(folder, folder / "frame_000.png", FAST)  # a new name among the frames: allowed
    frame = (folder / "frame_000.jpg").read_bytes()
    for overwrite in (False, True):
        with pytest.raises(UdhError, match="frame_000.jpg: the mosaic would replace an input file"):
            run_mosaic(folder, folder / "frame_000.jpg", FAST, overwrite=overwrite)
    assert (folder / "frame_000.jpg").read_bytes() == frame
    run_mosaic(folder, folder / "frame_000.png", FAST)  # its own earlier output is replaced as before


def test_a_mosaic_in_the_way_that_no_run_to_it_wrote_is_refused_before_any_work(flight, tmp_path):
    folder, prints = flight
    (tmp_path / "m.png").write_bytes(b"the user's")
    with pytest.raises(UdhError, match=r"m.png: exists and no earlier run to m.png wrote it.*--overwrite"):
        run_mosaic(folder, tmp_path / "m.png", FAST, estimator=FailOn(prints, lambda a, b: False))
    assert listed(tmp_path) == ["m.png"] and (tmp_path / "m.png").read_bytes() == b"the user's"
    run_mosaic(folder, tmp_path / "m.png", FAST, estimator=FailOn(prints, lambda a, b: False), overwrite=True)
    assert (tmp_path / "m.png").read_bytes().startswith(b"\x89PNG")
