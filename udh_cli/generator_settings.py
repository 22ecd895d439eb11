"""The data generators' settings: how a simulated flight is made (:mod:`udh_cli.simulate`) and the flight motion
of training pairs (:mod:`udh_cli.flight_motion`).

They live apart from the generators, free of NumPy and OpenCV, because the command line reads its option
defaults from them when it starts; the generators re-export them.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class FlightConfig:
    """How a simulated flight is made.

    Attributes:
        frame_size: (width, height) of every frame, pixels.
        strips: number of parallel flight lines (lawn-mower path, flown back and forth).
        frames_per_strip: frames taken along each line.
        forward_overlap: share of a frame's width that the next frame on the same line sees again.
        side_overlap: share of a frame's height that neighbouring lines share.
        ground_px_per_frame_px: ground sampling: ground pixels covered by one frame pixel at nadir
            (1.0 renders the ground at its own resolution; above 1 would alias).
        focal_px: focal length in frame pixels (600 px on 640 px is a 56 degree horizontal field of view).
        tilt_deg: largest roll and pitch of the camera, degrees (the perspective jitter).
        yaw_deg: largest yaw jitter around the flight heading, degrees.
        altitude_jitter: largest relative change of altitude between frames.
        position_jitter: largest offset of a frame from its planned position, as a share of the step.
        exposure_range: (low, high) of the per-frame gain.
        noise_sigma: standard deviation of the Gaussian sensor noise, in 8-bit grey levels.
        jpeg_quality: JPEG quality of the written frames.
    """

    frame_size: tuple[int, int] = (640, 480)
    strips: int = 3
    frames_per_strip: int = 6
    forward_overlap: float = 0.75
    side_overlap: float = 0.6
    ground_px_per_frame_px: float = 1.0
    focal_px: float = 600.0
    tilt_deg: float = 2.0
    yaw_deg: float = 2.0
    altitude_jitter: float = 0.02
    position_jitter: float = 0.08
    exposure_range: tuple[float, float] = (0.8, 1.2)
    noise_sigma: float = 2.0
    jpeg_quality: int = 90


@dataclass(frozen=True)
class GpsConfig:
    """GPS written into the simulated frames' EXIF, as a drone's receiver would.

    Attributes:
        latitude, longitude: WGS84 degrees of the ground image's top-left corner.
        metres_per_pixel: ground size of one ground-image pixel.
        heading_deg: the bearing of the ground image's x axis, degrees clockwise from north (90: x points east).
        noise_m: standard deviation of each fix's horizontal error, metres (a small drone's GPS: 1-3 m).
    """

    latitude: float
    longitude: float
    metres_per_pixel: float = 0.05
    heading_deg: float = 90.0
    noise_m: float = 2.0  # a small drone's GPS: 1-3 m


@dataclass(frozen=True)
class MotionConfig:
    """The distribution of flight motion between two views. Defaults: the ``flight`` preset.

    Attributes:
        max_heading: largest rotation, degrees either way (180: the whole circle).
        scale_range: (smallest, largest) scale of A's footprint relative to B's, drawn log-uniformly.
        max_shift: largest translation of the footprint centre, as a fraction of the frame's width and height.
        perspective: corner jitter after the similarity, pixels of the P x P view (the paper's rho).
        min_overlap: smallest share of B's view that A's footprint must cover.
        lighting: probability of each real-flight lighting effect (shadow, vignette, blur, noise, JPEG).
        residual: 0 for the motion itself (a first round's view). Above 0, the pairs a later round of the
            cascade sees: A is shown pre-warped into B's view by a wrong answer, with
            :data:`udh_cli.flight_motion.PREWARP_BORDER` outside its frame, and the label is what is left, a corner perturbation
            of up to ``residual`` px of the P x P view.
    """

    # Measured on real consecutive pairs (SIFT references): copr and brighton-beach turn by at most 27 degrees
    # and shift by up to 0.45-0.8 of the frame; the half turns of a survey's strip ends are left to the
    # estimator's heading search (DeepEstimator.headings).
    max_heading: float = 30.0
    scale_range: tuple[float, float] = (1 / 1.35, 1.35)
    max_shift: float = 0.6
    perspective: float = 12.0
    min_overlap: float = 0.3
    lighting: float = 0.3
    residual: float = 0.0

    def scaled(self, amount: float) -> "MotionConfig":
        """The same distribution with every motion shrunk by ``amount`` in [0, 1] (for small-motion pairs)."""
        low, high = self.scale_range
        return MotionConfig(self.max_heading * amount, (low**amount, high**amount), self.max_shift * amount,
                            self.perspective * amount, self.min_overlap, self.lighting, self.residual)
