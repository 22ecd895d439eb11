"""NAME.report.html: one self-contained page per run, drawn from the sidecar's dict, readable for long flights."""

from __future__ import annotations

import re

import numpy as np
import pytest

from udh_cli.mosaic.report_page import MAX_ROWS, build_report_page, overlap_counts, pair_style, residual_colour, source_label


def test_overlap_counts_add_up_the_outlines():
    square = np.array([[0, 0], [9, 0], [9, 9], [0, 9]], np.float64)
    counts = overlap_counts([square, square + [5, 0]], (10, 20))
    assert counts[5, 2] == 1 and counts[5, 7] == 2 and counts[5, 12] == 1 and counts[5, 17] == 0


def test_pairs_are_named_by_what_they_did():
    assert pair_style({"status": "failed", "kind": "consecutive"}) == "failed"
    assert pair_style({"status": "rejected", "kind": "overlap"}) == "rejected"
    assert pair_style({"status": "ok", "kind": "bridge"}) == "bridged"
    assert pair_style({"status": "ok", "kind": "overlap", "consistency_px": {"loop": True}}) == "loop closure"
    assert pair_style({"status": "ok", "kind": "consecutive", "consistency_px": {"loop": False}}) == "chain"
    assert residual_colour(0.0, 5.0) == "#00ff30" and residual_colour(9.0, 5.0) == "#ff0030"


def test_the_title_names_the_source_without_the_steps_out_of_the_output_folder():
    assert source_label("../../work/shared/data/flights/copr/images") == "copr/images"
    assert source_label("flight") == "flight" and source_label("/data/survey") == "data/survey"
    page = build_report_page(_long_flight_report(30, 0, 0) | {"source": "../../data/flights/seneca/images"}, {})
    assert "<title>udh mosaic of seneca/images</title>" in page


def test_the_sequence_strip_lists_only_the_kinds_of_pair_it_shows():
    page = build_report_page(_long_flight_report(30, 0, 0), {})
    strip = page[page.index('class="sequence"'):]
    caption = strip[strip.index("<figcaption>"):strip.index("</figcaption>")]
    assert "chain 29" in caption and "loop closure" not in caption  # the strip shows consecutive pairs only


def test_a_run_writes_its_report_beside_the_mosaic_with_every_picture_inline(tmp_path):
    from mosaic_flights import SMALL, make_flight
    from udh_cli.mosaic import MosaicConfig, run_mosaic

    make_flight(tmp_path / "flight", SMALL, seed=3)
    report = run_mosaic(tmp_path / "flight", tmp_path / "map.png", MosaicConfig(method="sift", overlap_per_frame=1))
    page = (tmp_path / "map.report.html").read_text()
    assert report["report_page"] == "map.report.html"
    assert not re.search(r'(src|href)="(https?:)?//', page)  # nothing fetched: every picture is a data URI or SVG
    assert page.count("data:image/jpeg;base64,") == 1 and page.count('<use href="#preview-1"/>') == 1  # the preview, drawn twice
    placed = [r for r in report["frames"] if r["status"] == "placed"]
    assert page.count('class="outline"') == len(placed)  # each frame's outline on the mosaic, and its number
    for record in placed:
        assert f">{record['index']}</text>" in page
    loops = sum(pair_style(p) == "loop closure" for p in report["pairs"])
    assert f"{loops} loops" in page and f"loop closure {loops}" in page
    for stage in report["timings_s"]:
        assert f"<td>{stage}</td>" in page or stage == "total"
    assert "Every frame is in the mosaic." in page and "<th>blend</th>" in page


def _long_flight_report(frames: int, unplaced: int, warnings: int) -> dict:
    """A sidecar-shaped dict of a long survey: ``frames`` frames of 100x80 px in strips of 25, 60 px apart
    along a strip and 50 px across."""
    records = []
    for i in range(frames):
        placed = i >= unplaced
        records.append({"index": i, "file": f"f{i:04d}.jpg", "width": 100, "height": 80, "status": "placed" if placed else "unplaced",
                        "reason": None if placed else f"no pair with it succeeded (f{i:04d}.jpg->f{i + 1:04d}.jpg: too few matches)",
                        "part": 1 if placed else None, "metadata": {},
                        "mosaic_from_frame": [[1, 0, 60.0 * (i % 25)], [0, 1, 50.0 * (i // 25)], [0, 0, 1]] if placed else None})
    pairs = [{"a": i, "b": i + 1, "kind": "consecutive", "status": "ok", "consistency_px": {"before": 0, "after": 0.5, "loop": False}}
             for i in range(frames - 1)]
    pairs += [{"a": i, "b": i + 25, "kind": "overlap", "status": "ok" if i % 7 else "rejected",
               "consistency_px": {"before": 2.0, "after": 0.1 * (i % 60), "loop": True} if i % 7 else None} for i in range(frames - 25)]
    width, height = 60 * 24 + 100, 50 * ((frames - 1) // 25) + 80
    loops = {"count": frames - 25, "mean_px": 1.0, "max_px": 5.9}
    return {"source": "flight", "udh_version": "test", "method": "sift", "fallback": None, "config": {"outlier_px": 5.0, "blend": "multiband"},
            "parts": [{"part": 1, "file": "m.png", "preview": None, "width": width, "height": height, "plane": "reference frame",
                       "frames": list(range(unplaced, frames))}],
            "frames": records, "skipped_files": [], "pairs": pairs,
            "loop_consistency": {"loops_before": loops, "loops_after": loops},
            "summary": {"frames": frames, "placed": frames - unplaced, "skipped_files": 0, "parts": 1},
            "warnings": [f"warning {k}" for k in range(warnings)], "timings_s": {"pairs": 10.0, "total": 12.0}}


def test_a_500_frame_flight_gives_a_page_of_bounded_lists():
    """The pictures grow with the flight (one outline, one number per frame), the lists do not."""
    page = build_report_page(_long_flight_report(500, unplaced=120, warnings=900), {1: None})
    assert page.count('class="outline"') == 380
    assert page.count("<li>") == MAX_ROWS + 1 and "and 860 more (see the sidecar)" in page  # warnings
    assert "and 80 more (see the sidecar)" in page  # unplaced frames: MAX_ROWS shown of 120
    assert "Unplaced frames: 120" in page
    assert page.count('height="16" fill="#111"') == 120  # the sequence strip: one cell per frame, black where unplaced
    assert len(page) < 3_000_000


def test_the_report_page_opens_in_a_browser(tmp_path):
    """With headless Chromium installed, the page of a 500-frame flight renders (a screenshot is written)."""
    import shutil
    import subprocess

    browser = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    if browser is None:
        pytest.skip("no headless Chromium here")
    page = tmp_path / "long.report.html"
    page.write_text(build_report_page(_long_flight_report(500, unplaced=10, warnings=10), {1: None}))
    shot = tmp_path / "shot.png"
    subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", f"--screenshot={shot}", "--window-size=1200,2000",
                    page.as_uri()], capture_output=True, timeout=120)
    assert shot.is_file() and shot.stat().st_size > 10_000
