"""Live mode's sidecar and report page: written once by the final run, from its results, with the flight's record;
a last refresh that became the final mosaic is published again from its own report, never read back."""

from __future__ import annotations

import json
import shutil

from mosaic_flights import SMALL, make_flight
from udh_cli.mosaic import MosaicConfig, run_mosaic
from udh_cli.mosaic.live.run import _publish_last_refresh
from udh_cli.mosaic.outputs.files import RunFiles


def test_a_final_run_given_the_flight_s_record_writes_it_last_in_its_sidecar_and_on_its_page(tmp_path):
    make_flight(tmp_path / "flight", SMALL, seed=3)
    live = {"refreshes": 2, "frames": 8, "ended_by": "sentinel", "final": "a final run"}
    for out in ("out", "plain"):
        (tmp_path / out).mkdir()
    report = run_mosaic(tmp_path / "flight", tmp_path / "out" / "m.png", MosaicConfig(method="sift"), live=live)
    text = (tmp_path / "out" / "m.json").read_text()
    written = json.loads(text)
    assert list(written)[-2:] == ["report_page", "live"] and written["live"] == live and written["source"] == "../flight"
    assert text == json.dumps({k: v for k, v in report.items() if k != "sidecar"}, indent=1) + "\n"  # the run's own results
    page = (tmp_path / "out" / "m.report.html").read_text()
    assert "8 frames, 2 refreshes, ended by sentinel; the final mosaic is a final run" in page
    assert "<title>udh mosaic of flight</title>" in page
    plain = run_mosaic(tmp_path / "flight", tmp_path / "plain" / "m.png", MosaicConfig(method="sift"))
    assert "live" not in json.loads((tmp_path / "plain" / "m.json").read_text()) and "live mode" not in (tmp_path / "plain" / "m.report.html").read_text()
    assert plain["summary"] == report["summary"]


def test_a_last_refresh_that_became_the_final_mosaic_is_published_from_its_report_naming_the_followed_folder(tmp_path):
    frames = make_flight(tmp_path / "flight", SMALL, seed=3)
    staging = tmp_path / "out" / ".udh-follow-1"  # the refreshes read links to the complete frames
    staging.mkdir(parents=True)
    for frame in frames:
        (staging / frame.name).symlink_to(frame)
    report = run_mosaic(staging, tmp_path / "out" / "m.png", MosaicConfig(method="sift"))
    refreshed = json.loads((tmp_path / "out" / "m.json").read_text())
    assert refreshed["source"] == ".udh-follow-1"
    shutil.rmtree(staging)
    report["live"] = {"refreshes": 1, "frames": 8, "ended_by": "idle timeout", "final": "the last refresh"}
    _publish_last_refresh(report, tmp_path / "flight", RunFiles(tmp_path / "out" / "m.png"))
    written = json.loads((tmp_path / "out" / "m.json").read_text())
    assert written == {**refreshed, "source": "../flight", "live": report["live"]} and list(written)[-1] == "live"
    assert "sidecar" not in written and report["source"] == "../flight"
    page = (tmp_path / "out" / "m.report.html").read_text()
    assert "8 frames, 1 refresh, ended by idle timeout; the final mosaic is the last refresh" in page
    assert "<title>udh mosaic of flight</title>" in page
    assert page.count("data:image/jpeg;base64,") == 1  # the preview, read from the published files
    recorded = json.loads((tmp_path / "out" / ".udh-written.json").read_text())["files"]
    assert recorded["m.json"]["size"] == (tmp_path / "out" / "m.json").stat().st_size and recorded["m.json"]["run"] == "m.png"
