"""Fuzzing the command line: bad inputs and faults over every command, each ending in one line and an exit code.

Every case of the table runs the CLI in-process (``conftest.run_main``) and checks: the exit code; that stderr
is ONE line starting with ``error:`` and naming the problem; that there is no traceback; and that nothing was
written or left behind: the output folder and the shared inputs are exactly as before (no output file, no
hidden ``.part`` / ``.staged`` temporary, no input replaced). After the table: damaged pair caches under
``udh mosaic --resume`` (a warning, and their pairs estimated again) and a mosaic killed by SIGTERM, then resumed.

Exit codes: 0 done, 1 error, 2 usage error (Click's), 3 ``udh estimate``'s unverified answer, 130 interrupted.
"""

from __future__ import annotations

import copy
import importlib
import json
import os
import pickle
import shutil
import signal
import struct
import subprocess
import sys
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import pytest

from udh_cli import geometry

from conftest import export_tiny_network, run_main, textured_image, warped_pair
from mosaic_flights import SMALL, make_flight

IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0
LONG = "m" * 245  # a name the file system takes, but not with the suffixes and temporary names a run adds


def png_declaring(path: Path, width: int, height: int) -> None:
    """A small PNG whose header declares ``width`` x ``height`` (a decompression bomb, as far as a decoder knows)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    rows = zlib.compress(b"\x00" * (width + 1) * 4)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
                     + chunk(b"IDAT", rows) + chunk(b"IEND", b""))


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, Path]:
    """Small inputs, good and bad, shared by every case (which must leave them exactly as they are)."""
    folder = tmp_path_factory.mktemp("fuzz-inputs")
    image_a, image_b = warped_pair(geometry.translation(6.0, -4.0), 160, 120, seed=5, margin=20)
    paths = {"in": folder, "a": folder / "a.png", "b": folder / "b.png"}
    cv2.imwrite(str(paths["a"]), image_a)
    cv2.imwrite(str(paths["b"]), image_b)
    paths["empty"] = folder / "empty.png"
    paths["empty"].write_bytes(b"")
    paths["text"] = folder / "text.png"
    paths["text"].write_text("not an image\n")
    paths["trunc"] = folder / "truncated.png"
    paths["trunc"].write_bytes(paths["a"].read_bytes()[:2000])
    paths["bomb"] = folder / "bomb.png"
    png_declaring(paths["bomb"], 32000, 32000)
    ok, small_jpeg = cv2.imencode(".jpg", image_a[:16, :16])
    forged = bytearray(small_jpeg.tobytes())
    start = forged.find(b"\xff\xc0") + 5  # the frame header's height and width
    forged[start:start + 4] = struct.pack(">HH", 15000, 15000)
    paths["jpeg_bomb"] = folder / "bomb.jpg"
    paths["jpeg_bomb"].write_bytes(bytes(forged))
    ok, whole = cv2.imencode(".jpg", image_a)
    flipped = bytearray(whole.tobytes())
    middle = len(flipped) // 2
    flipped[middle:middle + 64] = bytes(v ^ 0xFF for v in flipped[middle:middle + 64])  # bits flipped in the coded data
    paths["flipped"] = folder / "flipped.jpg"
    paths["flipped"].write_bytes(bytes(flipped))
    paths["deep"] = folder / "deep.json"
    paths["deep"].write_text("[" * 100_000 + "]" * 100_000)
    paths["horizon"] = folder / "horizon.txt"
    paths["horizon"].write_text("1 0 0\n0 1 0\n-0.01 0 1\n")  # w = 1 - 0.01 x: A's right-hand corners lie past the horizon
    paths["csv_npz"] = folder / "pairs.npz"
    paths["csv_npz"].write_text("img1,img2,H\na.png,b.png,1 0 0 0 1 0 0 0 1\n")
    paths["bad_csv"] = folder / "bad.csv"
    paths["bad_csv"].write_text("x,y\n1,2\n")
    paths["video"] = folder / "clip.mp4"
    paths["video"].write_text("not a video\n")
    paths["frames"] = folder / "frames"
    paths["frames"].mkdir()
    make_flight(paths["frames"], SMALL, seed=4)
    paths["frame"] = paths["frames"] / "frame_000.jpg"
    paths["no_images"] = folder / "no_images"
    paths["no_images"].mkdir()
    paths["one"] = folder / "one"
    paths["one"].mkdir()
    shutil.copy(paths["a"], paths["one"] / "a.png")
    paths["pool"] = folder / "pool"
    paths["pool"].mkdir()
    for i in range(6):
        cv2.imwrite(str(paths["pool"] / f"{i}.png"), textured_image(160, 120, seed=10 + i))
    return paths


@pytest.fixture(scope="module")
def models(inputs, tmp_path_factory) -> dict[str, Path]:
    """A tiny trained-format checkpoint and its ONNX export, and damaged variants of both (needs torch)."""
    torch = pytest.importorskip("torch")
    pytest.importorskip("onnx")
    import io

    from udh_cli.train.checkpoint import CHECKPOINT_FORMAT

    folder = tmp_path_factory.mktemp("fuzz-models")
    paths = {"good_onnx": export_tiny_network(folder, "corr", seed=0), "good_pt": folder / "corr.pt"}
    state = torch.load(paths["good_pt"], weights_only=True)

    def variant(name: str, **changes) -> None:
        buffer = io.BytesIO()
        torch.save({**state, "format": CHECKPOINT_FORMAT, **changes}, buffer)
        paths[name] = folder / f"{name}.pt"
        paths[name].write_bytes(buffer.getvalue())

    config = state["config"]
    variant("no_arch", config={k: v for k, v in config.items() if k != "arch"})
    variant("patch_text", config={**config, "patch_size": "abc"})
    variant("patch_huge", config={**config, "patch_size": 100000})
    variant("config_list", config=[1, 2])
    variant("norm_text", normalization={"mean": "a", "std": 1.0})
    variant("wrong_size", config={**config, "patch_size": 64})  # 32-pixel weights
    paths["corrupt_pt"] = folder / "corrupt.pt"
    paths["corrupt_pt"].write_bytes(np.random.default_rng(0).bytes(4096))
    paths["pickle_pt"] = folder / "pickled.pt"  # a plain pickle (protocol 4): torch warns about it before refusing it
    paths["pickle_pt"].write_bytes(pickle.dumps({"format": CHECKPOINT_FORMAT, "model": {}}, protocol=4))
    paths["text_onnx"] = folder / "text.onnx"
    paths["text_onnx"].write_text("not a model\n")

    import onnx
    from onnx import numpy_helper

    proto = onnx.load(str(paths["good_onnx"]))
    for init in proto.graph.initializer:  # one bias of NaN: every output becomes NaN
        values = numpy_helper.to_array(init)
        if values.dtype == np.float32 and values.ndim == 1:
            init.CopyFrom(numpy_helper.from_array(np.full_like(values, np.nan), init.name))
            break
    paths["nan_onnx"] = folder / "nan.onnx"
    onnx.save(proto, str(paths["nan_onnx"]))

    from onnx import TensorProto, helper

    good = onnx.load(str(paths["good_onnx"]))
    metadata = {entry.key: entry.value for entry in good.metadata_props}
    huge = copy.deepcopy(good)
    for dim in huge.graph.input[0].type.tensor_type.shape.dim[2:]:
        dim.dim_value = 8192
    for entry in huge.metadata_props:
        if entry.key == "input_size":
            entry.value = "8192"
    paths["huge_onnx"] = folder / "huge.onnx"
    onnx.save(huge, str(paths["huge_onnx"]))
    # Loads, and fails when run: 2 x 32 x 32 values cannot be reshaped to (7, 4, 2).
    graph = helper.make_graph([helper.make_node("Reshape", ["patches", "shape"], ["offsets"])], "fails",
                              [helper.make_tensor_value_info("patches", TensorProto.FLOAT, ["N", 2, 32, 32])],
                              [helper.make_tensor_value_info("offsets", TensorProto.FLOAT, ["N", 4, 2])],
                              [numpy_helper.from_array(np.array([7, 4, 2], np.int64), "shape")])
    failing = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    failing.ir_version = good.ir_version
    for key, value in metadata.items():
        failing.metadata_props.add(key=key, value=value)
    paths["failing_onnx"] = folder / "failing.onnx"
    onnx.save(failing, str(paths["failing_onnx"]))
    return paths


# ---------------------------------------------------------------------------------------------- setups


def foreign_json(out: Path, paths: dict) -> None:
    (out / "package.json").write_text('{"name": "my-app", "version": "1.0.0"}\n')


def users_report_page(out: Path, paths: dict) -> None:
    (out / "m.report.html").write_text("<html>my notes</html>\n")


def users_gdal_metadata(out: Path, paths: dict) -> None:
    (out / "m.png.aux.xml").write_text("<PAMDataset/>\n")


def foreign_pair_cache(out: Path, paths: dict) -> None:
    (out / "m.pairs.json").write_text("[1, 2, 3]\n")


def huge_pair_cache(out: Path, paths: dict) -> None:
    with open(out / "m.pairs.json", "wb") as handle:
        handle.truncate(257 * 2**20)  # sparse: the size is what matters


def existing_run(out: Path, paths: dict) -> None:
    (out / "run").mkdir()
    (out / "run" / "checkpoint.pt").write_bytes(b"an earlier run's weights")
    (out / "run" / "metrics.jsonl").write_text('{"step": 10}\n')


def checkpoint_named_onnx(out: Path, paths: dict) -> None:
    shutil.copy(paths["good_pt"], out / "model.onnx")


def read_only_folder(out: Path, paths: dict) -> None:
    (out / "ro").mkdir()
    (out / "ro").chmod(0o555)


def a_file(out: Path, paths: dict) -> None:
    (out / "file.txt").write_text("a file\n")


def users_bench_results(out: Path, paths: dict) -> None:
    (out / "b").mkdir()
    (out / "b" / "results.md").write_text("# my notes on the results\n")
    (out / "b" / "results.json").write_text('{"mine": true}\n')


def users_npz(out: Path, paths: dict) -> None:
    np.savez(out / "p.npz", mine=np.arange(3))


def data_folder_with_users_config(out: Path, paths: dict) -> None:
    for image in paths["pool"].iterdir():
        shutil.copy(image, out / image.name)
    (out / "config.json").write_text('{"my": "settings"}\n')


def model_with_users_int8(out: Path, paths: dict) -> None:
    shutil.copy(paths["good_onnx"], out / "model.onnx")
    (out / "model-int8.onnx").write_bytes(b"the int8 model I tuned by hand")


def users_picture(out: Path, paths: dict) -> None:
    (out / "v.png").write_bytes(b"my holiday picture")


def users_onnx(out: Path, paths: dict) -> None:
    (out / "m.onnx").write_bytes(b"the model I trained last week")


def users_ground_preview(out: Path, paths: dict) -> None:
    (out / "s_ground.jpg").write_bytes(b"my photo of the ground")


def gcp_file(text: str) -> Callable:
    def setup(out: Path, paths: dict) -> None:
        (out / "gcp.txt").write_text(text)

    return setup


def camera_fifo(out: Path, paths: dict) -> None:
    os.mkfifo(out / "cameras.json")  # no writer: opening it to read would wait for ever


def camera_deep(out: Path, paths: dict) -> None:
    (out / "cameras.json").write_text('{"cam": ' + "[" * 100_000 + "]" * 100_000 + "}")


def truth_singular(out: Path, paths: dict) -> None:
    from udh_cli.simulate import GROUND_TRUTH_FORMAT

    (out / "truth.json").write_text(json.dumps({"format": GROUND_TRUTH_FORMAT, "frame_size": [160, 120], "consecutive_pairs": [],
                                                "frames": [{"file": "frame_000.jpg", "ground_from_frame": [[1, 0, 0], [0, 0, 0], [0, 0, 1]]}]}))


# ----------------------------------------------------------------------------------------------- cases


@dataclass
class Case:
    """``args`` are formatted with the paths of ``inputs`` (and ``models``) and ``out``, the case's empty folder."""

    id: str
    args: list[str]
    code: int
    message: str
    needs: str | None = None  # "torch" or "pyproj": skipped without it; "user": skipped when running as root
    setup: Callable | None = None
    forbid: tuple[str, ...] = ()  # "module:attribute" that must not be called (work that must not start)
    absent: tuple[str, ...] = ()  # extra words stderr must not hold
    env: dict[str, str] | None = None  # environment variables for the case (e.g. a small UDH_MEMORY_BUDGET)


CASES = [
    # ------------------------------------------------------------------ estimate
    Case("estimate-missing-file", ["estimate", "{in}/missing.png", "{a}"], 1, "no such file"),
    Case("estimate-folder-as-image", ["estimate", "{in}", "{a}"], 1, "is a folder"),
    Case("estimate-empty-file", ["estimate", "{empty}", "{a}"], 1, "the file is empty"),
    Case("estimate-text-as-png", ["estimate", "{a}", "{text}"], 1, "not a readable image"),
    Case("estimate-truncated-png", ["estimate", "{trunc}", "{a}"], 1, "not a readable image"),
    Case("estimate-decompression-bomb", ["estimate", "{bomb}", "{a}"], 1, "32000x32000 pixels", forbid=("cv2:imdecode",)),
    Case("estimate-jpeg-declaring-15000-squared", ["estimate", "{jpeg_bomb}", "{a}", "--full-resolution"], 1, "truncated or damaged",
         forbid=("cv2:imdecode",)),
    Case("estimate-full-resolution-over-the-memory-budget", ["estimate", "{a}", "{b}", "-m", "sift", "--full-resolution"], 1,
         "leave out --full-resolution", env={"UDH_MEMORY_BUDGET": "1e6"}, forbid=("udh_cli.estimators.base:require_ok",)),
    Case("estimate-onnx-declaring-input-8192", ["estimate", "{a}", "{b}", "-m", "supervised", "--model", "{huge_onnx}"], 1,
         "udh networks take 16 to 512 px", "torch"),
    Case("estimate-onnx-failing-inside-onnxruntime", ["estimate", "{a}", "{b}", "-m", "supervised", "--model", "{failing_onnx}"], 1,
         "failed inside onnxruntime", "torch"),
    Case("estimate-bit-flipped-jpeg", ["estimate", "{flipped}", "{a}", "-m", "sift"], 1, "the file is damaged (the decoder says: Corrupt JPEG data",
         forbid=("udh_cli.estimators.base:require_ok",)),
    Case("estimate-path-over-4096-bytes", ["estimate", "{in}/" + "x/" * 2100 + "a.png", "{a}"], 1, "File name too long"),
    Case("estimate-viz-onto-input", ["estimate", "{a}", "{b}", "-m", "sift", "--viz", "{a}"], 1, "one of the input images"),
    Case("estimate-viz-over-a-users-picture", ["estimate", "{a}", "{b}", "-m", "sift", "--viz", "{out}/v.png"], 1, "add --overwrite",
         setup=users_picture, forbid=("udh_cli.images:read_image",)),
    Case("estimate-viz-missing-folder", ["estimate", "{a}", "{b}", "--viz", "{out}/no/v.png"], 1, "does not exist"),
    Case("estimate-viz-name-too-long", ["estimate", "{a}", "{b}", "-m", "sift", "--viz", "{out}/" + LONG + ".png"], 1, "too long"),
    Case("estimate-viz-unwritable-folder", ["estimate", "{a}", "{b}", "--viz", "{out}/ro/v.png"], 1, "not writable", "user", read_only_folder),
    Case("estimate-unknown-method", ["estimate", "{a}", "{b}", "-m", "surf"], 2, "'surf' is not one of"),  # a choice: usage error
    Case("estimate-option-of-another-method", ["estimate", "{a}", "{b}", "-m", "ecc", "--best-features", "5"], 1, "does not take"),
    Case("estimate-iterations-zero", ["estimate", "{a}", "{b}", "-m", "ecc", "--iterations", "0"], 2, "--iterations"),
    Case("estimate-iterations-huge", ["estimate", "{a}", "{b}", "-m", "ecc", "--iterations", "100000000"], 2, "--iterations"),
    Case("estimate-work-size-tiny", ["estimate", "{a}", "{b}", "--work-size", "5"], 1, "--work-size 5"),
    Case("estimate-not-a-number", ["estimate", "{a}", "{b}", "--best-features", "many"], 2, "--best-features"),
    Case("estimate-unknown-precision", ["estimate", "{a}", "{b}", "-m", "unsupervised", "--precision", "int9"], 1, "unknown precision"),
    Case("estimate-gt-missing", ["estimate", "{a}", "{b}", "--gt", "{in}/missing.txt"], 1, "no such homography file"),
    Case("estimate-gt-dev-zero", ["estimate", "{a}", "{b}", "--gt", "/dev/zero"], 1, "--gt /dev/zero: not a regular file"),
    Case("estimate-gt-deeply-nested-json", ["estimate", "{a}", "{b}", "--gt", "{deep}"], 1, "not a 3x3 homography"),
    Case("estimate-gt-through-the-horizon", ["estimate", "{a}", "{b}", "-m", "sift", "--gt", "{horizon}"], 1, "through the horizon",
         forbid=("udh_cli.estimators.base:require_ok",)),
    # ------------------------------------------------------------------ mosaic
    Case("mosaic-missing-folder", ["mosaic", "{in}/missing", "-o", "{out}/m.png"], 1, "no such folder or video"),
    Case("mosaic-folder-without-images", ["mosaic", "{no_images}", "-o", "{out}/m.png"], 1, "no image files found"),
    Case("mosaic-one-image", ["mosaic", "{one}", "-o", "{out}/m.png", "--quiet"], 1, "only one readable image"),
    Case("mosaic-path-over-4096-bytes", ["mosaic", "{in}/" + "x/" * 2100 + "f", "-o", "{out}/m.png"], 1, "the path is too long"),
    Case("mosaic-single-image-as-source", ["mosaic", "{a}", "-o", "{out}/m.png"], 1, "is a single image"),
    Case("mosaic-text-as-video", ["mosaic", "{video}", "-o", "{out}/m.png"], 1, "cannot open this as a video"),
    Case("mosaic-output-onto-a-frame", ["mosaic", "{frames}", "-o", "{frame}", "-m", "sift"], 1, "would replace an input file",
         forbid=("udh_cli.mosaic.run:open_frames",)),
    Case("mosaic-foreign-json-beside-output", ["mosaic", "{frames}", "-o", "{out}/package.png", "-m", "sift"], 1, "udh did not write",
         setup=foreign_json, forbid=("udh_cli.mosaic.run:open_frames",)),
    Case("mosaic-over-a-users-report-page", ["mosaic", "{frames}", "-o", "{out}/m.png", "-m", "sift"], 1, "report page would replace a file udh did not write",
         setup=users_report_page, forbid=("udh_cli.mosaic.run:open_frames",)),
    Case("mosaic-over-a-users-gdal-metadata", ["mosaic", "{frames}", "-o", "{out}/m.png", "-m", "sift"], 1, "GDAL metadata file would replace a file udh did not write",
         setup=users_gdal_metadata, forbid=("udh_cli.mosaic.run:open_frames",)),
    Case("mosaic-foreign-pair-cache", ["mosaic", "{frames}", "-o", "{out}/m.png", "-m", "sift", "--resume"], 1, "udh did not write",
         setup=foreign_pair_cache),
    Case("mosaic-pair-cache-past-256-mb", ["mosaic", "{frames}", "-o", "{out}/m.png", "-m", "sift", "--resume"], 1,
         "larger than any sidecar or pair cache udh writes", setup=huge_pair_cache, forbid=("udh_cli.mosaic.run:open_frames",)),
    Case("mosaic-output-name-too-long", ["mosaic", "{frames}", "-o", "{out}/" + LONG + ".png", "-m", "sift"], 1, "too long",
         forbid=("udh_cli.mosaic.run:open_frames", "udh_cli.mosaic.pairs.plan:estimate_pairs")),
    Case("mosaic-output-unknown-type", ["mosaic", "{frames}", "-o", "{out}/m.gif"], 1, "unknown image type"),
    Case("mosaic-output-missing-folder", ["mosaic", "{frames}", "-o", "{out}/no/m.png"], 1, "does not exist"),
    Case("mosaic-output-unwritable-folder", ["mosaic", "{frames}", "-o", "{out}/ro/m.png"], 1, "not writable", "user", read_only_folder),
    Case("mosaic-unknown-method", ["mosaic", "{frames}", "-o", "{out}/m.png", "-m", "surf"], 2, "'surf' is not one of"),
    Case("mosaic-unknown-blend", ["mosaic", "{frames}", "-o", "{out}/m.png", "--blend", "soft"], 2, "'soft' is not one of"),
    Case("mosaic-work-size-tiny", ["mosaic", "{frames}", "-o", "{out}/m.png", "--work-size", "4"], 1, "--work-size"),
    Case("mosaic-every-zero", ["mosaic", "{frames}", "-o", "{out}/m.png", "--every", "0"], 1, "--every"),
    Case("mosaic-confidence-above-one", ["mosaic", "{frames}", "-o", "{out}/m.png", "--min-confidence", "2"], 1, "--min-confidence"),
    Case("mosaic-method-option-not-key-value", ["mosaic", "{frames}", "-o", "{out}/m.png", "-O", "junk"], 1, "KEY=VALUE"),
    # A value too nested for JSON is kept as text; the unknown key is then the one-line error.
    Case("mosaic-method-option-deeply-nested", ["mosaic", "{frames}", "-o", "{out}/m.png", "-O", "x=" + "[" * 5000 + "]" * 5000], 1,
         "no method here takes 'x'"),
    Case("mosaic-negative-threads", ["mosaic", "{frames}", "-o", "{out}/m.png", "-m", "unsupervised", "-O", "threads=-1"], 1, "threads -1"),
    Case("mosaic-camera-fifo-without-writer", ["mosaic", "{frames}", "-o", "{out}/m.png", "--camera", "{out}/cameras.json"], 1,
         "not a regular file", setup=camera_fifo, forbid=("udh_cli.mosaic.run:open_frames",)),
    Case("mosaic-camera-dev-zero", ["mosaic", "{frames}", "-o", "{out}/m.png", "--camera", "/dev/zero"], 1, "--camera /dev/zero: not a regular file",
         forbid=("udh_cli.mosaic.run:open_frames",)),
    Case("mosaic-camera-deeply-nested", ["mosaic", "{frames}", "-o", "{out}/m.png", "--camera", "{out}/cameras.json"], 1, "nests too deeply",
         setup=camera_deep, forbid=("udh_cli.mosaic.run:open_frames",)),
    Case("mosaic-gcp-dev-zero", ["mosaic", "{frames}", "-o", "{out}/m.png", "--gcp", "/dev/zero"], 1, "--gcp /dev/zero: not a regular file",
         needs="pyproj", forbid=("udh_cli.mosaic.run:open_frames",)),
    Case("mosaic-gcp-header-only", ["mosaic", "{frames}", "-o", "{out}/m.png", "--gcp", "{out}/gcp.txt"], 1, "no ground-control points",
         needs="pyproj", setup=gcp_file("EPSG:32611\n"), forbid=("udh_cli.mosaic.run:open_frames",)),
    Case("mosaic-gcp-wgs84-over-utm", ["mosaic", "{frames}", "-o", "{out}/m.png", "--gcp", "{out}/gcp.txt"], 1,
         "not longitude and latitude degrees", needs="pyproj", setup=gcp_file("WGS84\n500000 4100000 10 5 5 frame_000.jpg g1\n"),
         forbid=("udh_cli.mosaic.run:open_frames",)),
    Case("mosaic-gcp-easting-1e300", ["mosaic", "{frames}", "-o", "{out}/m.png", "--gcp", "{out}/gcp.txt"], 1, "no place on Earth",
         needs="pyproj", setup=gcp_file("EPSG:32611\n1e300 4100000 10 5 5 frame_000.jpg g1\n"), forbid=("udh_cli.mosaic.run:open_frames",)),
    Case("mosaic-gcp-all-at-one-spot", ["mosaic", "{frames}", "-o", "{out}/m.png", "--gcp", "{out}/gcp.txt"], 1, "lie at one spot",
         needs="pyproj", setup=gcp_file("EPSG:32611\n" + "".join(f"500000 4100000 10 {10 * i} 5 frame_00{i}.jpg g{i}\n" for i in range(4))),
         forbid=("udh_cli.mosaic.run:open_frames",)),
    Case("mosaic-gt-dev-urandom", ["mosaic", "{frames}", "-o", "{out}/m.png", "--gt", "/dev/urandom"], 1, "/dev/urandom: not a regular file",
         forbid=("udh_cli.mosaic.run:open_frames",)),
    Case("mosaic-gt-singular-matrix", ["mosaic", "{frames}", "-o", "{out}/m.png", "--gt", "{out}/truth.json"], 1, "invertible",
         setup=truth_singular, forbid=("udh_cli.mosaic.run:open_frames",)),
    Case("mosaic-gt-deeply-nested-json", ["mosaic", "{frames}", "-o", "{out}/m.png", "--gt", "{deep}"], 1, "nests too deeply"),
    # ------------------------------------------------------------------ bench
    Case("bench-csv-renamed-npz", ["bench", "synthetic", "--load-pairs", "{csv_npz}", "--out", "{out}/b"], 1, "not an .npz archive",
         absent=("allow_pickle", "pickle")),
    Case("bench-missing-pair-set", ["bench", "synthetic", "--load-pairs", "{in}/missing.npz", "--out", "{out}/b"], 1, "not a udh pair set"),
    Case("bench-missing-images", ["bench", "synthetic", "--images", "{in}/missing", "--out", "{out}/b"], 1, "no such folder"),
    Case("bench-bad-rho", ["bench", "synthetic", "--images", "{pool}", "--rho", "abc", "--out", "{out}/b"], 1, "--rho"),
    Case("bench-zero-pairs", ["bench", "synthetic", "--images", "{pool}", "--n", "0", "--out", "{out}/b"], 1, "--n 0"),
    Case("bench-unknown-method", ["bench", "synthetic", "--images", "{pool}", "-m", "surf", "--out", "{out}/b"], 1, "unknown method"),
    Case("bench-bad-option", ["bench", "synthetic", "--images", "{pool}", "--option", "junk", "--out", "{out}/b"], 1, "KEY=VALUE"),
    Case("bench-out-is-a-file", ["bench", "synthetic", "--images", "{pool}", "--out", "{a}"], 1, "is a file"),
    Case("bench-save-pairs-onto-an-input-image", ["bench", "synthetic", "--images", "{pool}", "--save-pairs", "{frame}", "--out", "{out}/b"],
         1, "unknown file type '.jpg'", forbid=("udh_cli.bench.suite:held_out_sources",)),
    Case("bench-save-pairs-onto-a-users-npz", ["bench", "synthetic", "--images", "{pool}", "--save-pairs", "{out}/p.npz", "--out", "{out}/b"],
         1, "udh did not write it", setup=users_npz, forbid=("udh_cli.bench.suite:held_out_sources",)),
    Case("bench-out-holds-users-results", ["bench", "synthetic", "--images", "{pool}", "--out", "{out}/b"], 1, "add --overwrite",
         setup=users_bench_results, forbid=("udh_cli.bench.suite:held_out_sources",)),
    Case("bench-pairs-out-holds-users-results", ["bench", "pairs", "{bad_csv}", "--out", "{out}/b"], 1, "udh did not write it",
         setup=users_bench_results),
    Case("bench-n-beyond-the-memory-budget", ["bench", "synthetic", "--images", "{pool}", "--n", "100000000", "--out", "{out}/b"], 1,
         "lower --n", env={"UDH_MEMORY_BUDGET": "8e9"}, forbid=("udh_cli.bench.suite:held_out_sources",)),
    Case("bench-pairs-missing-csv", ["bench", "pairs", "{in}/missing.csv", "--out", "{out}/b"], 1, "no such file"),
    Case("bench-pairs-foreign-csv", ["bench", "pairs", "{bad_csv}", "--out", "{out}/b"], 1, "missing column"),
    # ------------------------------------------------------------------ train
    Case("train-negative-lr", ["train", "-d", "{pool}", "-o", "{out}/run", "--lr", "-1"], 1, "--lr -1", "torch"),
    Case("train-nan-lr", ["train", "-d", "{pool}", "-o", "{out}/run", "--lr", "nan"], 1, "--lr nan", "torch"),
    Case("train-negative-threads", ["train", "-d", "{pool}", "-o", "{out}/run", "--threads", "-1"], 1, "--threads -1", "torch"),
    Case("train-negative-small-motion", ["train", "-d", "{pool}", "-o", "{out}/run", "--small-motion", "-1"], 1, "--small-motion", "torch"),
    Case("train-unknown-mode", ["train", "-d", "{pool}", "-o", "{out}/run", "--mode", "semi"], 1, "unknown --mode", "torch"),
    Case("train-missing-data", ["train", "-d", "{in}/missing", "-o", "{out}/run"], 1, "no such data folder", "torch"),
    Case("train-out-is-a-file", ["train", "-d", "{pool}", "-o", "{out}/file.txt"], 1, "is a file", "torch", a_file),
    Case("train-into-an-existing-run", ["train", "-d", "{pool}", "-o", "{out}/run"], 1, "holds a run", "torch", existing_run),
    Case("train-overwrite-with-a-bad-lr-keeps-the-run", ["train", "-d", "{pool}", "-o", "{out}/run", "--overwrite", "--lr", "-1"], 1, "--lr",
         "torch", existing_run),
    Case("train-out-is-the-data-with-users-config", ["train", "-d", "{out}", "-o", "{out}"], 1, "config.json: exists and udh did not write it",
         "torch", data_folder_with_users_config),
    Case("train-resume-without-a-run", ["train", "-d", "{pool}", "-o", "{out}/run", "--resume"], 1, "no checkpoint", "torch"),
    Case("train-init-corrupt-checkpoint", ["train", "-d", "{pool}", "-o", "{out}/run", "--init", "{corrupt_pt}"], 1,
         "not a readable udh checkpoint", "torch"),
    Case("train-init-dev-zero", ["train", "-d", "{pool}", "-o", "{out}/run", "--init", "/dev/zero"], 1, "/dev/zero: not a regular file", "torch"),
    Case("train-init-config-without-arch", ["train", "-d", "{pool}", "-o", "{out}/run", "--init", "{no_arch}"], 1, "lacks 'arch'", "torch"),
    # ------------------------------------------------------------------ export-onnx
    Case("export-missing-checkpoint", ["export-onnx", "{in}/missing.pt", "-o", "{out}/m.onnx"], 1, "no such checkpoint", "torch"),
    Case("export-checkpoint-dev-zero", ["export-onnx", "/dev/zero", "-o", "{out}/m.onnx"], 1, "/dev/zero: not a regular file", "torch"),
    Case("export-corrupt-checkpoint", ["export-onnx", "{corrupt_pt}", "-o", "{out}/m.onnx"], 1, "not a readable udh checkpoint", "torch"),
    Case("export-plain-pickle-checkpoint", ["export-onnx", "{pickle_pt}", "-o", "{out}/m.onnx"], 1, "not a readable udh checkpoint", "torch"),
    Case("export-image-as-checkpoint", ["export-onnx", "{a}", "-o", "{out}/m.onnx"], 1, "not a readable udh checkpoint", "torch"),
    Case("export-config-without-arch", ["export-onnx", "{no_arch}", "-o", "{out}/m.onnx"], 1, "lacks 'arch'", "torch"),
    Case("export-config-not-a-dict", ["export-onnx", "{config_list}", "-o", "{out}/m.onnx"], 1, "config is not a dict", "torch"),
    Case("export-patch-size-text", ["export-onnx", "{patch_text}", "-o", "{out}/m.onnx"], 1, "patch_size 'abc'", "torch"),
    Case("export-patch-size-absurd", ["export-onnx", "{patch_huge}", "-o", "{out}/m.onnx"], 1, "patch_size 100000", "torch",
         forbid=("udh_cli.train.export:create_model",)),
    Case("export-normalisation-text", ["export-onnx", "{norm_text}", "-o", "{out}/m.onnx"], 1, "normalisation", "torch"),
    Case("export-weights-of-another-size", ["export-onnx", "{wrong_size}", "-o", "{out}/m.onnx"], 1, "do not fit", "torch"),
    Case("export-onto-its-checkpoint", ["export-onnx", "{out}/model.onnx", "-o", "{out}/model.onnx"], 1, "is the checkpoint being exported",
         "torch", checkpoint_named_onnx),
    Case("export-over-a-users-model", ["export-onnx", "{good_pt}", "-o", "{out}/m.onnx"], 1, "udh did not write it", "torch", users_onnx,
         forbid=("udh_cli.train.export:create_model",)),
    Case("export-output-not-onnx", ["export-onnx", "{good_pt}", "-o", "{out}/m.txt"], 1, ".onnx name", "torch"),
    Case("export-check-images-missing", ["export-onnx", "{good_pt}", "-o", "{out}/m.onnx", "--check-images", "{in}/missing"], 1,
         "no such folder", "torch"),
    # ------------------------------------------------------------------ quantize
    Case("quantize-nan-network", ["quantize", "{nan_onnx}", "-d", "{pool}", "--pairs", "2", "--images", "4", "-o", "{out}/q.onnx"], 1,
         "NaN or infinite", "torch"),
    Case("quantize-missing-model", ["quantize", "{in}/missing.onnx", "-d", "{pool}", "-o", "{out}/q.onnx"], 1, "no such model file", "torch"),
    Case("quantize-text-as-model", ["quantize", "{text_onnx}", "-d", "{pool}", "-o", "{out}/q.onnx"], 1, "not a loadable ONNX model", "torch"),
    Case("quantize-onto-its-source", ["quantize", "{good_onnx}", "-d", "{pool}", "-o", "{good_onnx}"], 1, "would replace", "torch"),
    Case("quantize-default-output-is-users-int8", ["quantize", "{out}/model.onnx", "-d", "{pool}"], 1, "add --overwrite", "torch",
         model_with_users_int8),
    Case("quantize-missing-data", ["quantize", "{good_onnx}", "-d", "{in}/missing", "-o", "{out}/q.onnx"], 1, "no such folder", "torch"),
    Case("quantize-zero-pairs", ["quantize", "{good_onnx}", "-d", "{pool}", "--pairs", "0", "-o", "{out}/q.onnx"], 1, "--pairs", "torch"),
    # ------------------------------------------------------------------ simulate
    Case("simulate-ground-preview-over-users-file", ["simulate", "{out}/s", "--ground-preview", "--width", "64", "--height", "64"], 1,
         "s_ground.jpg: exists and udh did not write it", setup=users_ground_preview, forbid=("udh_cli.simulate:simulate_flight",)),
    Case("simulate-frames-beyond-the-memory-budget", ["simulate", "{out}/s", "--width", "8000", "--height", "6000"], 1,
         "lower --width and --height", env={"UDH_MEMORY_BUDGET": "8e9"}, forbid=("udh_cli.simulate:simulate_flight",)),
    # ------------------------------------------------------------------ usage
    Case("usage-unknown-command", ["frobnicate"], 2, "No such command"),
    Case("usage-unknown-option", ["estimate", "{a}", "{b}", "--frobnicate"], 2, "--frobnicate"),
    Case("usage-missing-argument", ["estimate", "{a}"], 2, "Missing argument"),
]


def snapshot(folder: Path) -> dict[str, tuple[int, int]]:
    """Every file under ``folder`` (hidden ones too), with its size and modification time."""
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(folder.rglob("*")) if p.is_file()}


def _forbidden(target: str) -> Callable:
    def called(*args, **kwargs):
        raise AssertionError(f"{target} was called: the error must come before this work")

    return called


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input_fails_in_one_line_and_leaves_nothing(case: Case, inputs, tmp_path, monkeypatch, capfd, request):
    paths = dict(inputs)
    if case.needs == "torch":
        pytest.importorskip("torch")
        paths.update(request.getfixturevalue("models"))
    if case.needs == "pyproj":
        pytest.importorskip("pyproj")
    if case.needs == "user" and IS_ROOT:
        pytest.skip("root can write into read-only folders")
    out = tmp_path / "out"
    out.mkdir()
    if case.setup is not None:
        case.setup(out, paths)
    for name, value in (case.env or {}).items():
        monkeypatch.setenv(name, value)
    for target in case.forbid:
        module, attribute = target.split(":")
        monkeypatch.setattr(importlib.import_module(module), attribute, _forbidden(target))
    args = [arg.format_map({**{k: str(v) for k, v in paths.items()}, "out": str(out)}) for arg in case.args]
    watched = [out, inputs["in"]] + ([paths["good_pt"].parent] if "good_pt" in paths else [])
    before = [snapshot(folder) for folder in watched]
    try:
        code, stdout, stderr = run_main(monkeypatch, capfd, *args)
    finally:
        if (out / "ro").exists():
            (out / "ro").chmod(0o755)

    lines = [line for line in stderr.splitlines() if line.strip()]
    assert code == case.code, stderr
    assert len(lines) == 1 and lines[0].startswith("error: "), stderr
    assert case.message in lines[0], lines[0]
    assert "Traceback" not in stderr + stdout and "internal error" not in stderr
    assert not any(word in lines[0] for word in case.absent), lines[0]
    assert stdout.strip() == ""
    assert [snapshot(folder) for folder in watched] == before  # no output, no temporary, no input replaced or touched
    leftovers = [p.name for folder in watched for p in folder.rglob(".*") if p.name.endswith(".part") or ".staged" in p.name]
    assert leftovers == []


def test_a_refused_checkpoint_comes_without_torchs_pickle_warning(models, tmp_path, monkeypatch, capfd):
    """torch warns about a pickle protocol it did not write before it refuses the file; udh's line is the only one."""
    import warnings

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        code, _, err = run_main(monkeypatch, capfd, "export-onnx", str(models["pickle_pt"]), "-o", str(tmp_path / "m.onnx"))
    assert code == 1 and err.strip().startswith("error:") and len(err.strip().splitlines()) == 1, err
    assert [str(w.message) for w in caught if "pickle" in str(w.message).lower()] == []


# ------------------------------------------------------------------------------------ frames skipped, and why


def with_corrupt_exif(jpeg: bytes) -> bytes:
    """``jpeg`` with an EXIF block whose tags point past its end (Pillow warns "Corrupt EXIF data")."""
    tiff = (b"II*\x00" + struct.pack("<IH", 8, 2) + struct.pack("<HHII", 0x010F, 2, 400, 5000) + struct.pack("<HHII", 0x8769, 4, 1, 26)
            + struct.pack("<IH", 0, 50))
    app1 = b"Exif\x00\x00" + tiff
    return jpeg[:2] + b"\xff\xe1" + struct.pack(">H", len(app1) + 2) + app1 + jpeg[2:]


def test_frames_skipped_say_why_and_library_noise_stays_off_stderr(inputs, tmp_path, monkeypatch, capfd):
    """A NaN float frame is "NaN", an unreadable one "Permission denied" (not "corrupt"), a bit-flipped JPEG is damaged
    (not composited with the decoder's grey), and a frame whose EXIF is damaged is used without Pillow's warning."""
    frames = tmp_path / "frames"
    shutil.copytree(inputs["frames"], frames)
    (frames / "ground_truth.json").unlink(missing_ok=True)
    nan = np.full((120, 160), 0.5, np.float32)
    nan[5, 5] = np.nan
    cv2.imwrite(str(frames / "zz_nan.tiff"), nan)
    last = sorted(frames.glob("frame_*.jpg"))[-1]
    last.write_bytes(with_corrupt_exif(last.read_bytes()))
    shutil.copy(inputs["flipped"], frames / "zz_flipped.jpg")
    if not IS_ROOT:
        shutil.copy(frames / "frame_000.jpg", frames / "zz_locked.jpg")
        (frames / "zz_locked.jpg").chmod(0)
    code, _, err = run_main(monkeypatch, capfd, "mosaic", str(frames), "-o", str(tmp_path / "m.png"), "-m", "sift", "--quiet")
    assert code == 0, err
    assert "skipping zz_nan.tiff: cannot be decoded (the image holds NaN or infinite values)" in err
    assert "skipping zz_flipped.jpg: cannot be decoded (the file is damaged (the decoder says: Corrupt JPEG data" in err
    assert IS_ROOT or "skipping zz_locked.jpg: cannot be decoded (cannot read it (Permission denied)" in err
    assert "corrupt or not an image" not in err and "Corrupt EXIF" not in err and "UserWarning" not in err
    report = json.loads((tmp_path / "m.json").read_text())
    assert last.name in [frame["file"] for frame in report["frames"]]


# ------------------------------------------------------------------------------------ damaged pair caches


@pytest.fixture(scope="module")
def finished_run(inputs, tmp_path_factory):
    """A finished mosaic of the small flight with sift (as `udh mosaic -m sift --overlap-pairs 1`): its pair
    cache and sidecar, read back."""
    from udh_cli.mosaic import MosaicConfig, run_mosaic

    folder = tmp_path_factory.mktemp("fuzz-mosaic")
    run_mosaic(inputs["frames"], folder / "m.png", MosaicConfig(method="sift", overlap_per_frame=1), resume=True)
    return json.loads((folder / "m.pairs.json").read_text()), json.loads((folder / "m.json").read_text())


def resume_mosaic(monkeypatch, capfd, frames: Path, output: Path) -> tuple[int, str, str]:
    return run_main(monkeypatch, capfd, "mosaic", str(frames), "-o", str(output), "-m", "sift", "--quiet", "--overlap-pairs", "1", "--resume")


def _nan(pairs: list) -> None:
    pairs[0]["b_from_a"] = [[float("nan")] * 3] * 3


def _singular(pairs: list) -> None:
    pairs[1]["estimates"][-1]["homography"] = [[1, 0, 0], [0, 0, 0], [0, 0, 1]]
    pairs[1]["b_from_a"] = [[1, 0, 0], [0, 0, 0], [0, 0, 1]]


def _shape(pairs: list) -> None:
    pairs[2]["b_from_a"] = [1.0, 2.0, 3.0]


def _altered(pairs: list) -> None:  # a valid homography, but not the one its estimate gives
    pairs[3]["b_from_a"][0][2] += 50.0


def _not_dicts(pairs: list) -> None:
    pairs[4] = "a pair"
    pairs[5]["estimates"] = ["an estimate"]


def _types(pairs: list) -> None:
    pairs[0]["method"] = 42
    pairs[1]["estimates"][0]["confidence"] = "high"
    pairs[2]["key"] = ["not", "a", "key"]


def _deep_record(pairs: list) -> None:
    pairs[0]["estimates"][0]["details"] = json.loads("[" * 500 + "]" * 500)


def _status(pairs: list) -> None:
    pairs[0]["b_from_a"] = None  # "ok" without a homography
    pairs[1]["verified"] = float("nan")


DAMAGE = {"nan-homography": (_nan, 1), "singular-homography": (_singular, 1), "wrong-shape": (_shape, 1), "altered-homography": (_altered, 1),
          "non-dict-entries": (_not_dicts, 2), "wrong-types": (_types, 3), "deeply-nested-record": (_deep_record, 1),
          "inconsistent-status": (_status, 2)}


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_a_damaged_pair_cache_is_a_warning_and_its_pairs_are_estimated_again(damage, inputs, finished_run, tmp_path, monkeypatch, capfd):
    cache, sidecar = finished_run
    damaged = copy.deepcopy(cache)
    spoil, count = DAMAGE[damage]
    spoil(damaged["pairs"])
    output = tmp_path / "m.png"
    (tmp_path / "m.pairs.json").write_text(json.dumps(damaged))
    code, _, err = resume_mosaic(monkeypatch, capfd, inputs["frames"], output)
    assert code == 0, err
    assert "Traceback" not in err and "internal error" not in err and "warning: --resume" in err
    report = json.loads((tmp_path / "m.json").read_text())
    total = len(sidecar["pairs"])
    assert report["summary"]["pairs_from_cache"] == total - count
    assert report["summary"]["placed"] == report["summary"]["frames"] == sidecar["summary"]["placed"]  # no frame silently unplaced
    for mine, reference in zip(report["frames"], sidecar["frames"], strict=True):
        np.testing.assert_allclose(mine["mosaic_from_frame"], reference["mosaic_from_frame"], atol=1e-6)
    for mine, reference in zip(report["pairs"], sidecar["pairs"], strict=True):  # cached or estimated again, the same answers
        assert (mine["status"], mine["method"], mine["verified"]) == (reference["status"], reference["method"], reference["verified"])
        for got, expected in zip(mine["estimates"], reference["estimates"], strict=True):
            assert {k: v for k, v in got.items() if k not in ("homography", "elapsed_ms")} == \
                   {k: v for k, v in expected.items() if k not in ("homography", "elapsed_ms")}
            np.testing.assert_allclose(got["homography"], expected["homography"], atol=1e-9)
    rewritten = json.loads((tmp_path / "m.pairs.json").read_text())  # rewritten whole and sound
    assert len(rewritten["pairs"]) == total and all(isinstance(p, dict) for p in rewritten["pairs"])


UNREADABLE = {
    "deeply-nested-file": '{"format": "udh-mosaic-pairs/1", "pairs": ' + "[" * 100_000 + "]" * 100_000 + "}",
    "pairs-not-a-list": '{"format": "udh-mosaic-pairs/1", "pairs": 5}',
    "cut-short": '{"format":"udh-mosaic-pairs/1","pairs":[{"key":',
}


@pytest.mark.parametrize("text", list(UNREADABLE.values()), ids=list(UNREADABLE))
def test_an_unreadable_pair_cache_of_ours_is_a_warning_and_every_pair_is_estimated(text, inputs, finished_run, tmp_path, monkeypatch, capfd):
    _, sidecar = finished_run
    (tmp_path / "m.pairs.json").write_text(text)
    code, _, err = resume_mosaic(monkeypatch, capfd, inputs["frames"], tmp_path / "m.png")
    assert code == 0, err
    assert "Traceback" not in err and "internal error" not in err and "cannot use the pair cache" in err
    report = json.loads((tmp_path / "m.json").read_text())
    assert report["summary"]["pairs_from_cache"] == 0 and report["summary"]["placed"] == sidecar["summary"]["placed"]


# ------------------------------------------------------------------------------------ SIGTERM and --resume


def test_a_mosaic_killed_by_sigterm_keeps_its_pairs_and_resumes(tmp_path):
    """SIGTERM is handled as Ctrl-C: exit code 130, `error: interrupted`, the pair cache kept, nothing else left."""
    from udh_cli.simulate import FlightConfig

    frames = tmp_path / "frames"
    frames.mkdir()
    make_flight(frames, FlightConfig(frame_size=(320, 240), strips=2, frames_per_strip=16, focal_px=300.0), seed=4)  # 32 frames
    out = tmp_path / "out"
    out.mkdir()
    output, cache = out / "m.png", out / "m.pairs.json"
    args = [sys.executable, "-m", "udh_cli", "mosaic", str(frames), "-o", str(output), "-m", "sift", "--quiet", "--resume"]
    env = dict(os.environ, OMP_NUM_THREADS="1", COLUMNS="200")
    process = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    deadline = time.time() + 120
    while not cache.exists() and process.poll() is None and time.time() < deadline:
        time.sleep(0.005)  # the cache appears after the first batch of pairs, of about 75
    assert process.poll() is None, "the mosaic ended before it could be interrupted"
    process.send_signal(signal.SIGTERM)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 130, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines[-1] == "error: interrupted" and "Traceback" not in err
    assert "--resume" in err  # the warning says how to go on
    assert sorted(p.name for p in out.iterdir()) == ["m.pairs.json"]  # no mosaic, no sidecar, no temporary
    kept = len(json.loads(cache.read_text())["pairs"])
    assert kept >= 1  # at least the first batch (its size depends on the workers: pairs.estimate.even_batch_size)

    resumed = subprocess.run(args, capture_output=True, text=True, env=env, timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    report = json.loads((out / "m.json").read_text())
    assert report["summary"]["pairs_from_cache"] == kept
    assert f"{kept} of {len(report['pairs'])} pair estimates taken from" in resumed.stderr
    assert report["summary"]["placed"] == report["summary"]["frames"] == 32
