"""One radial distortion coefficient k1 for a whole flight, estimated from the flight itself (``--camera estimate``).

Why: most flights come without a calibration, and a barrel lens bends every pair by pixels towards the frame
corners (a simulated k1 of -0.15 left a 21 px mean corner error in an 18-frame mosaic). Between two frames of a
pinhole camera over flat ground, matched points are related by one homography exactly; through a lens they are
not, and the misfit grows with the distortion. So k1 is the value whose undistortion lets one homography per
pair fit its matches best:

1. SIFT matches (ratio test, a loose RANSAC homography that keeps the distorted inliers) on up to
   :data:`MAX_PAIRS` consecutive pairs of work copies, spread over the flight;
2. for each k1 on a grid, then scipy's bounded scalar minimisation around the best, the matches are
   undistorted (OpenCV's model, the frame's own camera matrix) and each pair's homography is refitted by
   least squares; the cost is the RMS of their residuals over all pairs.

The focal length scales the distortion (OpenCV's model acts on ``r / f``), and it trades with k1: a wrong focal
length gives another k1 with nearly the same undistortion in pixels. It comes from EXIF's 35 mm equivalent when
the frames have it, else :data:`DEFAULT_FOCAL` (a typical drone camera); the sidecar records both.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from udh_cli.errors import UdhError
from udh_cli.estimators.features import keypoint_points, ratio_test_points
from udh_cli.mosaic.inputs.lens import Lens

DEFAULT_FOCAL = 0.7  # focal length over the longer side: a 24-25 mm (35 mm equivalent) drone camera
K1_RANGE = (-0.5, 0.3)  # beyond these a lens is a fisheye, which this model does not describe
MAX_PAIRS = 24  # pairs spread over the flight: enough matches to pin k1 to about 0.005, in a second or two
MIN_MATCHES = 30  # per pair, after RANSAC
MIN_PAIRS = 3
RANSAC_PX = 6.0  # loose: a distorted pair misfits one homography by pixels at the corners
MIN_GAIN = 0.05  # the RMS must fall by this share below k1 = 0 for a lens to be reported (else k1 = 0)


@dataclass(frozen=True)
class K1Fit:
    """What the fit found: ``k1`` for ``focal`` (over the longer side, and where it came from), the matches'
    RMS homography residual in work-copy pixels at k1 = 0 and at ``k1``, and the pairs and matches used."""

    k1: float
    focal: float
    focal_source: str
    rms_without_px: float
    rms_with_px: float
    pairs: int
    matches: int

    def lens(self, size: tuple[int, int]) -> Lens:
        return Lens(size[0], size[1], self.focal, self.focal, k1=self.k1, name="estimated")

    def to_json(self) -> dict:
        return {"k1": round(self.k1, 5), "focal": round(self.focal, 4), "focal_source": self.focal_source,
                "rms_without_px": round(self.rms_without_px, 3), "rms_with_px": round(self.rms_with_px, 3),
                "pairs": self.pairs, "matches": self.matches}


def focal_from_exif(focal_length_35mm: float | None) -> tuple[float, str]:
    """Focal length over the frame's longer side from EXIF's 35 mm equivalent (36 mm long), else the default."""
    if focal_length_35mm is not None and 8.0 <= focal_length_35mm <= 400.0:
        return focal_length_35mm / 36.0, "EXIF 35 mm equivalent"
    return DEFAULT_FOCAL, f"assumed ({DEFAULT_FOCAL} of the longer side; no EXIF 35 mm focal length)"


def frames_focal(frames) -> tuple[float, str]:
    """:func:`focal_from_exif` of the first of ``frames`` (:class:`~udh_cli.mosaic.inputs.frames.Frame`) whose EXIF gives a
    35 mm equivalent focal length: over the longer side, and where it came from."""
    metadata = next((f.metadata for f in frames if f.metadata is not None and f.metadata.focal_length_35mm), None)
    return focal_from_exif(metadata.focal_length_35mm if metadata is not None else None)


def pair_matches(grey_a: np.ndarray, grey_b: np.ndarray, sift) -> tuple[np.ndarray, np.ndarray] | None:
    """(N, 2) matched pixels in A and in B (RANSAC inliers of a loose homography), or None when too few."""
    keys_a, desc_a = sift.detectAndCompute(grey_a, None)
    keys_b, desc_b = sift.detectAndCompute(grey_b, None)
    if desc_a is None or desc_b is None or len(keys_a) < MIN_MATCHES or len(keys_b) < MIN_MATCHES:
        return None
    points_a, points_b = ratio_test_points(cv2.BFMatcher().knnMatch(desc_a, desc_b, k=2), keypoint_points(keys_a), keypoint_points(keys_b), 0.75)
    if len(points_a) < MIN_MATCHES:
        return None
    _, inliers = cv2.findHomography(points_a, points_b, cv2.RANSAC, RANSAC_PX)
    if inliers is None or inliers.sum() < MIN_MATCHES:
        return None
    keep = inliers.ravel().astype(bool)
    return points_a[keep], points_b[keep]


def _residual_rms(matches: Sequence[tuple[np.ndarray, np.ndarray]], size: tuple[int, int], focal: float, k1: float) -> float:
    """RMS over every pair of the least-squares homography residual of the matches undistorted with ``k1``, in
    the frames' own pixels: each residual is divided by the undistortion's radial magnification at its point,
    since a barrel lens's undistortion stretches the rim, and with it the matches' noise, which would
    otherwise favour a weaker lens."""
    lens = Lens(size[0], size[1], focal, focal, k1=k1)
    centre = np.array([(size[0] - 1) / 2, (size[1] - 1) / 2])
    squares, count = 0.0, 0
    for points_a, points_b in matches:
        a, b = lens.undistort_points(points_a, size), lens.undistort_points(points_b, size)
        h, _ = cv2.findHomography(a, b, 0)
        if h is None:
            return math.inf
        projected = cv2.perspectiveTransform(a.reshape(-1, 1, 2), h).reshape(-1, 2)
        radius = np.linalg.norm(points_b - centre, axis=1)
        magnification = np.where(radius > 1.0, np.linalg.norm(b - centre, axis=1) / np.maximum(radius, 1.0), 1.0)
        squares += float(((np.linalg.norm(projected - b, axis=1) / magnification) ** 2).sum())
        count += len(a)
    return math.sqrt(squares / max(count, 1))


def fit_k1(greys: Sequence[np.ndarray], focal: float, focal_source: str = "given") -> K1Fit:
    """k1 for frames whose work copies ``greys`` (all of one size, in flight order) are given; see the module.

    Raises :class:`UdhError` when fewer than :data:`MIN_PAIRS` consecutive pairs give enough matches.
    """
    if len(greys) < 2:
        raise UdhError("--camera estimate: needs at least two frames")
    size = (greys[0].shape[1], greys[0].shape[0])
    if any((g.shape[1], g.shape[0]) != size for g in greys):
        raise UdhError("--camera estimate: the frames differ in size; one lens is estimated for frames of one camera and size")
    starts = np.unique(np.linspace(0, len(greys) - 2, min(MAX_PAIRS, len(greys) - 1)).round().astype(int))
    sift = cv2.SIFT_create(nfeatures=2000)
    matches = [found for i in starts if (found := pair_matches(greys[i], greys[i + 1], sift)) is not None]
    if len(matches) < MIN_PAIRS:
        raise UdhError(f"--camera estimate: only {len(matches)} consecutive pairs gave {MIN_MATCHES}+ matches (need {MIN_PAIRS}); "
                       "give the camera's cameras.json instead")
    cost = lambda k: _residual_rms(matches, size, focal, k)  # noqa: E731
    grid = np.linspace(*K1_RANGE, 17)
    costs = [cost(k) for k in grid]
    best = int(np.argmin(costs))
    bracket = (grid[max(best - 1, 0)], grid[min(best + 1, len(grid) - 1)])
    from scipy.optimize import minimize_scalar  # here: importing scipy.optimize costs every udh command 0.25 s

    k1 = float(minimize_scalar(cost, bounds=bracket, method="bounded", options={"xatol": 1e-4}).x)
    without, with_k1 = cost(0.0), cost(k1)
    if not with_k1 < (1 - MIN_GAIN) * without:  # no lens to speak of: do not resample the frames for nothing
        k1, with_k1 = 0.0, without
    return K1Fit(float(k1), focal, focal_source, without, with_k1, len(matches), int(sum(len(a) for a, _ in matches)))


CAMERA_ESTIMATE = "estimate"  # `--camera estimate`: fit k1 from the flight instead of reading a cameras.json


def undistort_by_fitted_lens(frames, reporter) -> K1Fit:
    """Fit k1 on a :class:`~udh_cli.mosaic.inputs.frames.FrameSet`'s work copies (:func:`fit_k1`) and, when a lens is
    found, undistort those copies in place and set ``frames.lens`` (so that compositing undistorts the
    full-resolution frames as it reads them) and ``frames.lens_fit``. Returns the fit."""
    focal, source = frames_focal(frames.frames)
    fit = fit_k1([f.work for f in frames.frames], focal, source)
    frames.lens_fit = fit.to_json()
    if fit.k1 == 0.0:
        reporter.info(f"--camera estimate: no lens distortion found (the matches fit one homography per pair to "
                      f"{fit.rms_without_px:.2f} px RMS); the frames are used as they are")
        return fit
    lens = fit.lens(frames.frames[0].size)
    for frame in frames.frames:  # the work copies were made from the distorted frames: undistort them too
        frame.work = lens.undistort(frame.work)
    for index, image in frames.decoded_while_reading.items():  # and the kept decodes, one at a time: no second copy of them all
        frames.decoded_while_reading[index] = lens.undistort(image)
    frames.lens = lens
    reporter.info(f"--camera estimate: k1 = {fit.k1:.4f} for a focal length of {fit.focal:.3f} of the longer side ({fit.focal_source}); "
                  f"the pairs' match residual {fit.rms_without_px:.2f} -> {fit.rms_with_px:.2f} px RMS over {fit.pairs} pairs")
    return fit
