"""A simulated drone flight with exact ground truth: a procedural ground, a nadir camera, JPEG frames.

The ground is an image that this module paints itself (fields with crop rows, roads, trees, buildings and
multi-octave noise), so the example data owes nothing to any outside source. A pinhole camera flies a
lawn-mower path over it at a fixed altitude with small roll, pitch, yaw and altitude jitter; every frame
is an exact planar homography of the ground, then gets an exposure change, sensor noise and JPEG coding.

Geometry (conventions of :mod:`udh_cli.geometry`): the world frame is the ground image's pixel frame
(x right, y down) with Z pointing into the ground, so a camera with identity rotation looks straight down
and its image axes line up with the ground's. A camera centred at ``(X, Y, -altitude)`` with rotation
``R`` and intrinsics ``K`` sees ground pixel ``(x, y)`` at ``K R [[1, 0, -X], [0, 1, -Y], [0, 0, altitude]]
(x, y, 1)``: that product is ``frame_from_ground``.

Run ``udh simulate OUT_FOLDER --seed 7`` to write a flight (``udh simulate --help`` for the options).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.files import check_replaceable, read_side_text, staged_folder, write_output
from udh_cli.generator_settings import FlightConfig, GpsConfig  # defined without NumPy: the command line reads its defaults
from udh_cli.images import atomic_write_bytes

GROUND_TRUTH_FILE = "ground_truth.json"
GROUND_TRUTH_FORMAT = "udh-sim-flight/1"


@dataclass(frozen=True)
class SimFrame:
    """One simulated frame: its pixels (H, W, 3) BGR uint8, ``ground_from_frame`` (3, 3) and pose."""

    image: np.ndarray
    ground_from_frame: np.ndarray
    pose: dict


# ------------------------------------------------------------------------------------------ ground


def _octave_noise(rng: np.random.Generator, size: tuple[int, int], base_cells: int, octaves: int) -> np.ndarray:
    """Multi-octave value noise (H, W) float32 in about [-1, 1]: each octave doubles the frequency and halves
    the amplitude. ``size`` is (width, height)."""
    width, height = size
    total = np.zeros((height, width), np.float32)
    amplitude, norm = 1.0, 0.0
    for octave in range(octaves):
        cells = base_cells * 2**octave
        grid = rng.uniform(-1, 1, (max(2, cells * height // width + 1), cells + 1)).astype(np.float32)
        total += amplitude * cv2.resize(grid, (width, height), interpolation=cv2.INTER_CUBIC)
        norm += amplitude
        amplitude *= 0.5
    return total / norm


def _field_labels(rng: np.random.Generator, size: tuple[int, int], n_fields: int) -> np.ndarray:
    """Voronoi field map (H, W) int32 with wobbly borders: each pixel's nearest of ``n_fields`` seeds."""
    width, height = size
    seeds = rng.uniform([0, 0], [width, height], (n_fields, 2)).astype(np.float32)
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    # Warp the coordinates by smooth noise so that field borders are not straight Voronoi edges.
    xs += 25.0 * _octave_noise(rng, size, 4, 2)
    ys += 25.0 * _octave_noise(rng, size, 4, 2)
    labels = np.zeros((height, width), np.int32)
    best = np.full((height, width), np.inf, np.float32)
    for index, (sx, sy) in enumerate(seeds):
        distance = (xs - sx) ** 2 + (ys - sy) ** 2
        closer = distance < best
        best[closer] = distance[closer]
        labels[closer] = index
    return labels


def make_ground(size: tuple[int, int], seed: int = 0) -> np.ndarray:
    """Paint a textured aerial-looking ground image (H, W, 3) BGR uint8 of ``size`` (width, height).

    Deterministic for a seed. Fields carry crop rows at random angles and periods, plus noise at several
    scales, so that SIFT, ORB, ECC and learned estimators all find texture everywhere.
    """
    rng = np.random.default_rng(seed)
    width, height = size
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    labels = _field_labels(rng, size, max(6, width * height // 90_000))
    palette = np.array([[60, 120, 70], [40, 150, 110], [70, 160, 170], [90, 110, 130], [50, 90, 60], [110, 170, 190], [60, 140, 90]], np.float32)
    ground = np.zeros((height, width, 3), np.float32)
    for field in range(labels.max() + 1):
        mask = labels == field
        colour = palette[rng.integers(len(palette))] * rng.uniform(0.8, 1.2)
        angle = rng.uniform(0, math.pi)
        period = rng.uniform(5.0, 14.0)
        rows = np.sin((xs[mask] * math.cos(angle) + ys[mask] * math.sin(angle)) * 2 * math.pi / period)
        strength = rng.uniform(0.05, 0.2)
        ground[mask] = colour[None, :] * (1.0 + strength * rows[:, None])
    # Noise at several scales: soil moisture at large scales, grain at small ones.
    ground *= 1.0 + 0.25 * _octave_noise(rng, size, 3, 6)[..., None]
    ground += 3.0 * rng.standard_normal((height, width, 1)).astype(np.float32)
    ground = cv2.GaussianBlur(ground, (0, 0), 0.8)
    _draw_features(rng, ground, size)
    return np.clip(ground, 0, 255).astype(np.uint8)


def _draw_features(rng: np.random.Generator, ground: np.ndarray, size: tuple[int, int]) -> None:
    """Roads, trees and buildings, drawn in place on the float ground (H, W, 3)."""
    width, height = size
    for _ in range(max(2, (width + height) // 700)):  # roads: gentle polylines across the ground
        start = rng.uniform([0, 0], [width, height])
        heading = rng.uniform(0, 2 * math.pi)
        points = [start]
        for _ in range(12):
            heading += rng.normal(0, 0.25)
            points.append(points[-1] + 150.0 * np.array([math.cos(heading), math.sin(heading)]))
        poly = np.round(np.array(points)).astype(np.int32)
        thickness = int(rng.integers(8, 16))
        cv2.polylines(ground, [poly], False, (95, 100, 105), thickness, cv2.LINE_AA)
        cv2.polylines(ground, [poly], False, (200, 205, 210), 1, cv2.LINE_AA)
    for _ in range(width * height // 2500):  # trees and bushes: dark blobs with a lit side
        centre = rng.uniform([0, 0], [width, height])
        radius = float(rng.uniform(3, 11))
        c = tuple(int(v) for v in centre)
        cv2.circle(ground, c, int(radius), (25, 55, 30), -1, cv2.LINE_AA)
        cv2.circle(ground, (c[0] - int(radius / 3), c[1] - int(radius / 3)), max(1, int(radius / 2)), (45, 95, 55), -1, cv2.LINE_AA)
    for _ in range(width * height // 60_000):  # buildings: rotated rectangles with a roof ridge
        centre = tuple(float(v) for v in rng.uniform([0, 0], [width, height]))
        dims = tuple(float(v) for v in rng.uniform(15, 45, 2))
        box = cv2.boxPoints((centre, dims, float(rng.uniform(0, 180)))).astype(np.int32)
        roof = rng.uniform(90, 220)
        cv2.fillConvexPoly(ground, box, (roof * 0.8, roof * 0.85, roof), cv2.LINE_AA)
        cv2.line(ground, tuple(((box[0] + box[1]) // 2).tolist()), tuple(((box[2] + box[3]) // 2).tolist()), (roof * 0.5,) * 3, 2, cv2.LINE_AA)


# ------------------------------------------------------------------------------------------ camera


def _rotation(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """World-to-camera rotation (3, 3) from angles in radians: yaw about Z, then pitch about X, roll about Y."""
    cr, sr, cp, sp, cy, sy = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
    r_yaw = np.array([[cy, sy, 0], [-sy, cy, 0], [0, 0, 1]])
    r_pitch = np.array([[1, 0, 0], [0, cp, sp], [0, -sp, cp]])
    r_roll = np.array([[cr, 0, -sr], [0, 1, 0], [sr, 0, cr]])
    return r_roll @ r_pitch @ r_yaw


def frame_from_ground(x: float, y: float, altitude: float, roll: float, pitch: float, yaw: float, focal_px: float, frame_size: tuple[int, int]) -> np.ndarray:
    """(3, 3) homography from ground pixels to the pixels of a camera at ground position ``(x, y)``.

    ``altitude`` is in ground pixels, angles in radians, ``focal_px`` in frame pixels; the principal point is
    the frame's centre ``((w - 1) / 2, (h - 1) / 2)``.
    """
    w, h = frame_size
    intrinsics = np.array([[focal_px, 0, (w - 1) / 2], [0, focal_px, (h - 1) / 2], [0, 0, 1]])
    plane = np.array([[1.0, 0, -x], [0, 1.0, -y], [0, 0, altitude]])
    out = intrinsics @ _rotation(roll, pitch, yaw) @ plane
    return out / out[2, 2]


def plan_path(config: FlightConfig, rng: np.random.Generator) -> tuple[list[dict], tuple[int, int]]:
    """Camera poses along a lawn-mower path and the ground size (width, height) that contains them all.

    Each pose is a dict with ``x``, ``y`` (ground pixels), ``altitude`` (ground pixels) and ``roll_deg``,
    ``pitch_deg``, ``yaw_deg``, ``gain``. The heading stays fixed between lines, as mapping apps fly.
    """
    w, h = config.frame_size
    foot_w, foot_h = w * config.ground_px_per_frame_px, h * config.ground_px_per_frame_px
    step_x = (1 - config.forward_overlap) * foot_w
    step_y = (1 - config.side_overlap) * foot_h
    margin = 0.3 * max(foot_w, foot_h)
    ground_w = int(math.ceil(foot_w + step_x * (config.frames_per_strip - 1) + 2 * margin))
    ground_h = int(math.ceil(foot_h + step_y * (config.strips - 1) + 2 * margin))
    poses = []
    for strip in range(config.strips):
        columns = range(config.frames_per_strip)
        for column in columns if strip % 2 == 0 else reversed(columns):
            jitter = config.position_jitter * rng.uniform(-1, 1, 2) * np.array([step_x, step_y])
            poses.append(
                {
                    "x": float(margin + foot_w / 2 + column * step_x + jitter[0]),
                    "y": float(margin + foot_h / 2 + strip * step_y + jitter[1]),
                    "altitude": float(config.focal_px * config.ground_px_per_frame_px * (1 + config.altitude_jitter * rng.uniform(-1, 1))),
                    "roll_deg": float(rng.uniform(-1, 1) * config.tilt_deg),
                    "pitch_deg": float(rng.uniform(-1, 1) * config.tilt_deg),
                    "yaw_deg": float(rng.uniform(-1, 1) * config.yaw_deg),
                    "gain": float(rng.uniform(*config.exposure_range)),
                }
            )
    return poses, (ground_w, ground_h)


def render_frame(ground: np.ndarray, pose: dict, config: FlightConfig, rng: np.random.Generator) -> SimFrame:
    """Photograph ``ground`` from ``pose``: exact warp, then exposure gain, vignetting and sensor noise."""
    w, h = config.frame_size
    radians = {k: math.radians(pose[f"{k}_deg"]) for k in ("roll", "pitch", "yaw")}
    to_frame = frame_from_ground(pose["x"], pose["y"], pose["altitude"], focal_px=config.focal_px, frame_size=config.frame_size, **radians)
    ground_from_frame = geometry.invert(to_frame)
    footprint = geometry.transform_points(ground_from_frame, geometry.image_corners(w, h))
    gh, gw = ground.shape[:2]
    if footprint.min() < 0 or footprint[:, 0].max() > gw - 1 or footprint[:, 1].max() > gh - 1:
        raise UdhError("a simulated frame leaves the ground; lower tilt_deg or position_jitter")
    image = cv2.warpPerspective(ground, to_frame, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT).astype(np.float32)
    # Mild vignetting, as real lenses have; it also makes exposure differ across one frame.
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    radius2 = ((xs - (w - 1) / 2) ** 2 + (ys - (h - 1) / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
    image *= (pose["gain"] * (1.0 - 0.15 * radius2))[..., None]
    image += config.noise_sigma * rng.standard_normal(image.shape).astype(np.float32)
    return SimFrame(np.clip(image + 0.5, 0, 255).astype(np.uint8), ground_from_frame, pose)


GROUND_BYTES_PER_PIXEL = 64  # make_ground's float32 layers, coordinates and labels at once
RENDER_BYTES_PER_PIXEL = 48  # render_frame's float32 copies of one frame


def check_flight_memory(config: FlightConfig) -> None:
    """Raise :class:`UdhError`, naming the options to lower, when :func:`simulate_flight` would not fit in memory
    (:func:`udh_cli.budget.check_memory`): the ground, every frame kept, and one frame's rendering copies."""
    from udh_cli.budget import check_memory

    _, (ground_w, ground_h) = plan_path(config, np.random.default_rng(0))
    width, height = config.frame_size
    frames = config.strips * config.frames_per_strip
    needed = ground_w * ground_h * GROUND_BYTES_PER_PIXEL + width * height * (3 * frames + RENDER_BYTES_PER_PIXEL)
    check_memory(needed, f"a {width}x{height} flight of {frames} frames (ground {ground_w}x{ground_h})",
                 "lower --width and --height, --strips or --frames-per-strip, or raise the overlaps")


def simulate_flight(config: FlightConfig = FlightConfig(), seed: int = 0) -> tuple[list[SimFrame], np.ndarray]:
    """The frames of a simulated flight, in flight order, and the ground image they were taken of."""
    rng = np.random.default_rng(seed)
    poses, ground_size = plan_path(config, rng)
    ground = make_ground(ground_size, seed=int(rng.integers(2**31)))
    return [render_frame(ground, pose, config, rng) for pose in poses], ground


EARTH_RADIUS_M = 6_371_008.8  # mean radius: the flights are a few hundred metres, where a sphere is exact to mm


def gps_of(ground_xy: np.ndarray, gps: GpsConfig) -> tuple[float, float]:
    """(latitude, longitude) of a ground-image point. Why not pyproj: over a flight's few hundred metres the
    local tangent plane on a sphere is exact to millimetres, and the simulator then needs nothing more."""
    theta = math.radians(gps.heading_deg)
    x, y = float(ground_xy[0]) * gps.metres_per_pixel, float(ground_xy[1]) * gps.metres_per_pixel
    # The x axis points along the bearing theta; image y points 90 degrees clockwise of it (down the image).
    east = x * math.sin(theta) + y * math.cos(theta)
    north = x * math.cos(theta) - y * math.sin(theta)
    latitude = gps.latitude + math.degrees(north / EARTH_RADIUS_M)
    longitude = gps.longitude + math.degrees(east / (EARTH_RADIUS_M * math.cos(math.radians(gps.latitude))))
    return latitude, longitude


def _jpeg_with_gps(image: np.ndarray, quality: int, latitude: float, longitude: float, focal_35mm: int) -> bytes:
    """JPEG bytes of a BGR frame with EXIF GPS and the 35 mm equivalent focal length, as a drone's camera writes
    them (Pillow: OpenCV writes no EXIF)."""
    import io

    from PIL import Image

    def dms(value: float) -> tuple[float, float, float]:
        degrees = int(value)
        minutes = int((value - degrees) * 60)
        return float(degrees), float(minutes), (value - degrees - minutes / 60) * 3600

    exif = Image.Exif()
    exif.get_ifd(0x8825).update({1: "N" if latitude >= 0 else "S", 2: dms(abs(latitude)), 3: "E" if longitude >= 0 else "W",
                                 4: dms(abs(longitude))})
    exif.get_ifd(0x8769)[0xA405] = focal_35mm  # FocalLengthIn35mmFilm: focal length over the longer side x 36 mm
    buffer = io.BytesIO()
    Image.fromarray(cv2.cvtColor(image, cv2.COLOR_BGR2RGB)).save(buffer, "JPEG", quality=quality, exif=exif)
    return buffer.getvalue()


def write_flight(folder: str | Path, config: FlightConfig = FlightConfig(), seed: int = 0, ground_preview: bool = False,
                 gps: GpsConfig | None = None, overwrite: bool = False) -> Path:
    """Simulate a flight and write ``frame_NNN.jpg`` (more digits past 1,000 frames) plus ``ground_truth.json``
    into ``folder``.

    The ground truth holds every frame's ``ground_from_frame`` and every consecutive pair's ``b_from_a``
    (pixels of frame a to pixels of frame b); with ``gps``, the frames carry EXIF GPS of their centres
    (with the configured noise) and the truth records each frame's exact ``gps``. With ``ground_preview``, the
    whole ground goes to ``FOLDER_ground.jpg`` beside the folder, replacing a file there only when udh wrote it,
    or with ``overwrite``. Returns the path of the ground-truth file.
    """
    folder = Path(folder)
    if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
        raise UdhError(f"{folder}: exists and is not an empty folder; the simulator writes only into a new or empty one")
    preview = folder.parent / f"{folder.name}_ground.jpg"
    if ground_preview:
        check_replaceable(preview, overwrite)
    check_flight_memory(config)
    with staged_folder(folder) as staging:  # all or none: a full disk leaves no half flight to block the rerun
        _write_flight_into(staging, config, seed, gps, preview if ground_preview else None, overwrite)
    return folder / GROUND_TRUTH_FILE


def _write_flight_into(folder: Path, config: FlightConfig, seed: int, gps: GpsConfig | None, preview: Path | None,
                       overwrite: bool) -> None:
    """:func:`write_flight`'s work, into ``folder`` (its staging folder); ``preview``: where the ground goes, if anywhere."""
    frames, ground = simulate_flight(config, seed)
    records = []
    noise = np.random.default_rng([seed, 17])
    width, height = config.frame_size
    digits = max(3, len(str(len(frames) - 1)))  # names sort in flight order however many frames there are
    for index, frame in enumerate(frames):
        name = f"frame_{index:0{digits}d}.jpg"
        record = {"file": name, "ground_from_frame": frame.ground_from_frame.tolist(), "pose": frame.pose}
        if gps is None:
            ok, data = cv2.imencode(".jpg", frame.image, [cv2.IMWRITE_JPEG_QUALITY, config.jpeg_quality])
            if not ok:
                raise UdhError(f"{name}: OpenCV could not encode the frame as JPEG")
            data = data.tobytes()
        else:
            centre = geometry.transform_points(frame.ground_from_frame, np.array([[(width - 1) / 2, (height - 1) / 2]]))[0]
            record["gps"] = dict(zip(("latitude", "longitude"), gps_of(centre, gps)))
            jitter = noise.normal(0.0, gps.noise_m, 2) / gps.metres_per_pixel if gps.noise_m > 0 else np.zeros(2)
            data = _jpeg_with_gps(frame.image, config.jpeg_quality, *gps_of(centre + jitter, gps), round(36 * config.focal_px / max(width, height)))
        atomic_write_bytes(folder / name, data)
        records.append(record)
    pairs = []
    for a, b in zip(frames[:-1], frames[1:]):
        b_from_a = geometry.invert(b.ground_from_frame) @ a.ground_from_frame
        pairs.append({"a": records[len(pairs)]["file"], "b": records[len(pairs) + 1]["file"], "b_from_a": (b_from_a / b_from_a[2, 2]).tolist()})
    if preview is not None:
        ok, data = cv2.imencode(".jpg", ground, [cv2.IMWRITE_JPEG_QUALITY, 85])
        write_output(preview, data.tobytes(), overwrite)
    truth = {
        "format": GROUND_TRUTH_FORMAT,
        "conventions": "pixel centres at integer (x, y); b_from_a maps pixels of a to pixels of b (x_b ~ H x_a); ground_from_frame maps frame pixels to ground-image pixels",
        "generator": "udh_cli.simulate",
        "seed": seed,
        "config": asdict(config),
        "frame_size": list(config.frame_size),
        "ground_size": [int(ground.shape[1]), int(ground.shape[0])],
        "frames": records,
        "consecutive_pairs": pairs,
    }
    atomic_write_bytes(folder / GROUND_TRUTH_FILE, (json.dumps(truth, indent=1) + "\n").encode())


def load_ground_truth(path: str | Path) -> dict:
    """Read a simulator ground-truth file; homographies come back as (3, 3) float64 arrays keyed by file name.

    Returns ``{"frame_size": (w, h), "ground_from_frame": {file: H}, "consecutive_pairs": [(a, b, H)]}``.
    Raises :class:`UdhError` when the file is not one this module wrote.
    """
    path = Path(path)
    try:
        data = json.loads(read_side_text(path))
    except (OSError, ValueError) as exc:
        raise UdhError(f"{path}: cannot read the ground truth ({exc})") from None
    except RecursionError:  # absurdly nested JSON
        raise UdhError(f"{path}: not a udh simulated-flight ground truth (its JSON nests too deeply)") from None
    if not isinstance(data, dict) or data.get("format") != GROUND_TRUTH_FORMAT:
        raise UdhError(f"{path}: not a udh simulated-flight ground truth (format {GROUND_TRUTH_FORMAT})")
    try:
        truth = {
            "frame_size": tuple(int(v) for v in data["frame_size"]),
            "ground_from_frame": {str(r["file"]): _homography(r["ground_from_frame"]) for r in data["frames"]},
            "consecutive_pairs": [(str(p["a"]), str(p["b"]), _homography(p["b_from_a"])) for p in data["consecutive_pairs"]],
        }
    except (KeyError, TypeError, ValueError):
        raise UdhError(f"{path}: the ground truth is damaged (missing keys, or homographies that are not finite, invertible "
                       f"3x3 matrices)") from None
    if len(truth["frame_size"]) != 2:
        raise UdhError(f"{path}: the ground truth's frame_size is not [width, height]")
    return truth


def _homography(values) -> np.ndarray:
    """A stored 3x3 homography; ValueError unless it is a finite, invertible 3x3 matrix."""
    matrix = np.asarray(values, np.float64)
    if matrix.shape != (3, 3) or not np.isfinite(matrix).all():
        raise ValueError("not a finite 3x3 matrix")
    if abs(np.linalg.det(matrix)) <= 1e-12 * max(1.0, float(np.abs(matrix).max())) ** 3:  # errors need its inverse
        raise ValueError("a singular matrix")
    return matrix
