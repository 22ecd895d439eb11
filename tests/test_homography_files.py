"""Reading and writing 3x3 homography files: text, JSON, OpenCV FileStorage, and broken ones."""

from __future__ import annotations

import json

import numpy as np
import pytest

from udh_cli.errors import UdhError
from udh_cli.homography_files import format_homography, read_homography

# A mild homography with a perspective row, h33 = 1.
H = np.array([[0.9, -0.05, 12.5], [0.04, 1.1, -7.25], [2.5e-4, -1.25e-4, 1.0]])

OPENCV_XML = """<?xml version="1.0"?>
<opencv_storage>
<H13 type_id="opencv-matrix">
  <rows>3</rows>
  <cols>3</cols>
  <dt>d</dt>
  <data>
    {}</data></H13>
</opencv_storage>
"""

OPENCV_YAML = """%YAML:1.0
---
homography: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ {} ]
"""


def test_text_nine_numbers_in_any_layout(tmp_path):
    layouts = {
        "rows.txt": format_homography(H),
        "one_line.txt": " ".join(repr(float(v)) for v in H.ravel()),
        "commas.csv": ",".join(repr(float(v)) for v in H.ravel()) + "\n",
        "no_suffix": "\n".join(repr(float(v)) for v in H.ravel()),
    }
    for name, text in layouts.items():
        (tmp_path / name).write_text(text)
        np.testing.assert_allclose(read_homography(tmp_path / name), H, rtol=1e-9, err_msg=name)


def test_scale_is_normalised_to_h33_one(tmp_path):
    (tmp_path / "scaled.txt").write_text(" ".join(repr(float(v)) for v in (-4.0 * H).ravel()))
    np.testing.assert_allclose(read_homography(tmp_path / "scaled.txt"), H, rtol=1e-12)
    # A tiny overall scale is still the identity, not a "singular" matrix.
    (tmp_path / "tiny.txt").write_text("1e-6 0 0 0 1e-6 0 0 0 1e-6")
    np.testing.assert_allclose(read_homography(tmp_path / "tiny.txt"), np.eye(3))


def test_json_forms(tmp_path):
    forms = {
        "rows.json": H.tolist(),
        "flat.json": H.ravel().tolist(),
        "estimate.json": {"method": "sift", "homography": H.tolist(), "confidence": 0.9},
    }
    for name, data in forms.items():
        (tmp_path / name).write_text(json.dumps(data))
        np.testing.assert_allclose(read_homography(tmp_path / name), H, rtol=1e-12, err_msg=name)


def test_opencv_filestorage_xml_and_yaml(tmp_path):
    numbers = "  ".join(f"{v:.10e}" for v in H.ravel())
    (tmp_path / "H1to3p.xml").write_text(OPENCV_XML.format(numbers))
    np.testing.assert_allclose(read_homography(tmp_path / "H1to3p.xml"), H, rtol=1e-9)
    (tmp_path / "h.yml").write_text(OPENCV_YAML.format(", ".join(repr(float(v)) for v in H.ravel())))
    np.testing.assert_allclose(read_homography(tmp_path / "h.yml"), H, rtol=1e-12)


def test_format_round_trip(tmp_path):
    path = tmp_path / "h.txt"
    path.write_text(format_homography(H))
    np.testing.assert_allclose(read_homography(path), H, rtol=1e-9)
    assert len(format_homography(H).strip().splitlines()) == 3


@pytest.mark.parametrize(
    ("name", "content", "message"),
    [
        ("eight.txt", "1 0 0 0 1 0 0 0", "not a 3x3"),
        ("ten.txt", "1 0 0 0 1 0 0 0 1 5", "not a 3x3"),
        ("words.txt", "one zero zero", "not a 3x3"),
        ("empty.txt", "", "not a 3x3"),
        ("binary.txt", b"\xff\xfe\x00\x01\x80", "not a 3x3"),
        ("nan.txt", "1 0 0 0 nan 0 0 0 1", "not finite"),
        ("inf.txt", "1 0 inf 0 1 0 0 0 1", "not finite"),
        ("h33_zero.txt", "1 0 0 0 1 0 0 0 0", "h33 = 0"),
        ("singular.txt", "1 2 3 2 4 6 0 0 1", "singular"),
        ("bad.json", "{not json", "not a 3x3"),
        ("no_key.json", '{"matrix": [1, 0, 0]}', "not a 3x3"),
        ("ragged.json", "[[1, 0, 0], [0, 1, 0], [0, 0]]", "not a 3x3"),
        ("strings.json", '[[1, 0, 0], [0, 1, 0], [0, 0, "x"]]', "not a 3x3"),
        ("null.json", '{"homography": null}', "not a 3x3"),
        ("broken.xml", "garbage <<< not xml", "not a 3x3"),
        ("no_matrix.xml", '<?xml version="1.0"?><opencv_storage><a>3</a></opencv_storage>', "not a 3x3"),
        ("two_by_two.xml", OPENCV_XML.format("1 0 0 1").replace("<rows>3", "<rows>2").replace("<cols>3", "<cols>2"), "not a 3x3"),
    ],
)
def test_malformed_files_raise_one_line_udh_error(tmp_path, capfd, name, content, message):
    path = tmp_path / name
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    with pytest.raises(UdhError, match=message) as error:
        read_homography(path)
    assert "\n" not in str(error.value) and name in str(error.value)
    assert capfd.readouterr().err == ""


def test_missing_file_and_folder(tmp_path):
    with pytest.raises(UdhError, match="no such homography file"):
        read_homography(tmp_path / "nope.txt")
    with pytest.raises(UdhError, match="folder"):
        read_homography(tmp_path)


def test_real_ground_truth_file(shared_data):
    truth = read_homography(shared_data / "pairs" / "opencv-samples" / "H1to3p.xml")
    assert truth[0, 2] == pytest.approx(225.67123) and truth[2, 0] == pytest.approx(3.4663091e-04)
