"""Lens distortion: a camera model read from OpenSfM/OpenDroneMap's ``cameras.json``, used to undistort frames.

One homography per frame holds only for a pinhole camera: a lens that bends straight lines (barrel distortion,
usual on drone cameras) leaves every pair a residual that grows towards the frame's corners. With
``udh mosaic --camera cameras.json`` every frame is undistorted as it is read, for the estimators and for
compositing, and ground-control pixels are undistorted the same way; the mosaic is then one of pinhole frames.

The model is OpenSfM's (which OpenDroneMap writes as ``cameras.json``): pixel coordinates are normalised by the
frame's longer side, ``x_n = (x + 0.5 - w / 2) / max(w, h)``; ``focal_x``, ``focal_y`` (or ``focal``) and the
principal point offsets ``c_x``, ``c_y`` are in those units; ``k1, k2, p1, p2, k3`` are OpenCV's radial and
tangential coefficients. ``perspective`` and ``brown`` projections are supported; ``fisheye`` and
``spherical`` are refused.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from udh_cli.errors import UdhError
from udh_cli.files import read_side_text

SUPPORTED_PROJECTIONS = ("perspective", "brown")
ASPECT_TOLERANCE = 0.01  # a camera calibrated on frames of another shape is another camera


@dataclass
class Lens:
    """A camera's intrinsics and distortion (OpenSfM units, see the module docstring).

    Attributes:
        width, height: the frame size the camera was calibrated on, pixels (frames of the same shape at
            another resolution use it scaled).
        focal_x, focal_y: focal lengths over the longer side.
        c_x, c_y: principal point offset from the frame centre, over the longer side.
        k1, k2, p1, p2, k3: OpenCV's distortion coefficients.
        name: the camera's key in ``cameras.json``.
    """

    width: int
    height: int
    focal_x: float
    focal_y: float
    c_x: float = 0.0
    c_y: float = 0.0
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0
    name: str = ""
    _maps: dict = field(default_factory=dict, repr=False, compare=False)

    def matrix(self, size: tuple[int, int]) -> np.ndarray:
        """(3, 3) camera matrix K in pixels of a frame of ``size`` (w, h), pixel centres at integers."""
        width, height = size
        longest = max(width, height)
        return np.array([[self.focal_x * longest, 0.0, width / 2 - 0.5 + self.c_x * longest],
                         [0.0, self.focal_y * longest, height / 2 - 0.5 + self.c_y * longest], [0.0, 0.0, 1.0]])

    def coefficients(self) -> np.ndarray:
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3])

    def check(self, size: tuple[int, int], what: str) -> None:
        """Refuse frames whose shape is not the calibrated one (a camera model for another sensor or crop)."""
        width, height = size
        if abs(width / height - self.width / self.height) > ASPECT_TOLERANCE * self.width / self.height:
            raise UdhError(f"--camera: camera '{self.name}' was calibrated on {self.width}x{self.height} frames, but {what} "
                           f"is {width}x{height} (another shape); give the cameras.json of the camera that took these frames")

    def undistort(self, image: np.ndarray) -> np.ndarray:
        """The image as a pinhole camera with the same K would have seen it, same size and type. The same K
        keeps every frame's geometry (GPS, ground-control pixels, ground truth) where it was; a barrel lens then
        fills the whole frame, and a pincushion lens leaves the rim beyond its field repeated from its edge
        (for the estimators; compositing leaves it out, :meth:`valid_mask`)."""
        height, width = image.shape[:2]
        if (width, height) not in self._maps:
            k = self.matrix((width, height))
            self._maps[(width, height)] = cv2.initUndistortRectifyMap(k, self.coefficients(), None, k, (width, height), cv2.CV_32FC2)
        map_xy, _ = self._maps[(width, height)]
        return cv2.remap(image, map_xy, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def valid_mask(self, size: tuple[int, int]) -> np.ndarray:
        """(h, w) float32: 1 where :meth:`undistort` has real pixels of a frame of ``size``, 0 on the rim a
        pincushion lens leaves beyond its field (all ones for a barrel lens)."""
        width, height = size
        if (width, height) not in self._maps:
            self.undistort(np.zeros((height, width), np.uint8))
        map_xy, _ = self._maps[(width, height)]
        inside = (map_xy[..., 0] >= -0.5) & (map_xy[..., 0] <= width - 0.5) & (map_xy[..., 1] >= -0.5) & (map_xy[..., 1] <= height - 0.5)
        return inside.astype(np.float32)

    def undistort_points(self, points: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        """(N, 2) pixels of a distorted frame of ``size`` -> where :meth:`undistort` puts them."""
        k = self.matrix(size)
        found = cv2.undistortPoints(np.asarray(points, np.float64).reshape(-1, 1, 2), k, self.coefficients(), P=k)
        return found.reshape(-1, 2)

    def to_cameras_json(self) -> dict:
        """This camera as OpenSfM/OpenDroneMap's ``cameras.json`` (:func:`read_cameras` reads it back)."""
        key = f"v2 udh {self.name or 'camera'} {self.width} {self.height} brown {self.focal_x:.4f}"
        return {key: {"projection_type": "brown", "width": self.width, "height": self.height, "focal_x": self.focal_x,
                      "focal_y": self.focal_y, "c_x": self.c_x, "c_y": self.c_y, "k1": self.k1, "k2": self.k2, "p1": self.p1,
                      "p2": self.p2, "k3": self.k3}}

    def to_json(self) -> dict:
        return {"name": self.name, "width": self.width, "height": self.height, "focal_x": self.focal_x, "focal_y": self.focal_y,
                "c_x": self.c_x, "c_y": self.c_y, "k1": self.k1, "k2": self.k2, "p1": self.p1, "p2": self.p2, "k3": self.k3}


MAX_CAMERAS_BYTES = 2**20  # one camera's parameters take a few hundred bytes


def read_cameras(path: str | Path) -> Lens:
    """The one camera of an OpenSfM/OpenDroneMap ``cameras.json`` (a file with several cameras is refused:
    which frames each took is not in the file)."""
    path = Path(path)
    try:
        data = json.loads(read_side_text(path, "--camera", MAX_CAMERAS_BYTES))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UdhError(f"--camera {path}: not a cameras.json ({exc})") from None
    except RecursionError:
        raise UdhError(f"--camera {path}: not a cameras.json (its JSON nests too deeply)") from None
    if not isinstance(data, dict) or not data:
        raise UdhError(f"--camera {path}: expected a JSON object of cameras, as OpenDroneMap writes in cameras.json")
    if len(data) > 1:
        raise UdhError(f"--camera {path}: {len(data)} cameras ({', '.join(list(data)[:3])}); keep the one that took these frames")
    name, camera = next(iter(data.items()))
    if not isinstance(camera, dict):
        raise UdhError(f"--camera {path}: camera '{name}' is not an object of parameters")
    projection = camera.get("projection_type", "perspective")
    if projection not in SUPPORTED_PROJECTIONS:
        raise UdhError(f"--camera {path}: camera '{name}' has a {projection} projection; udh undistorts "
                       f"{' and '.join(SUPPORTED_PROJECTIONS)} cameras only")

    def number(key: str, default: float | None = None) -> float:
        value = camera.get(key, default)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise UdhError(f"--camera {path}: camera '{name}' needs a finite number for '{key}', got {value!r}")
        return float(value)

    focal = camera.get("focal")
    focal_x = number("focal_x", focal)
    focal_y = number("focal_y", focal)
    width, height = number("width"), number("height")
    if width < 1 or height < 1 or width != int(width) or height != int(height):
        raise UdhError(f"--camera {path}: camera '{name}' has no usable width and height ({width:g}x{height:g})")
    if not 0.05 < focal_x < 20 or not 0.05 < focal_y < 20:
        raise UdhError(f"--camera {path}: camera '{name}' has focal lengths {focal_x:g}, {focal_y:g}; OpenSfM gives them "
                       "over the frame's longer side (about 0.5-1.5 for drone cameras), not in millimetres or pixels")
    lens = Lens(int(width), int(height), focal_x, focal_y, number("c_x", 0.0), number("c_y", 0.0), number("k1", 0.0),
                number("k2", 0.0), number("p1", 0.0), number("p2", 0.0), number("k3", 0.0), name=str(name))
    if max(abs(lens.k1), abs(lens.k2), abs(lens.k3)) > 10 or max(abs(lens.p1), abs(lens.p2)) > 1:
        raise UdhError(f"--camera {path}: camera '{name}' has distortion coefficients far beyond any real lens; check the file")
    return lens
