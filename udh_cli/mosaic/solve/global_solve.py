"""The global solve of every part: its pairs together (homographies or cameras), contradicted loop pairs
rejected, each pair's consistency, and the plane the part is drawn on."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from udh_cli.errors import UdhError
from udh_cli.mosaic.georef.anchors import Anchors
from udh_cli.mosaic.inputs.frames import FrameSet
from udh_cli.mosaic.inputs.lens_fit import frames_focal
from udh_cli.mosaic.pairs.types import PairResult, PairVerdict
from udh_cli.mosaic.report import Reporter
from udh_cli.mosaic.solve.cameras import solve_cameras
from udh_cli.mosaic.solve.homographies import pair_points, pair_rms_px, solve_with_rejection, summarise
from udh_cli.mosaic.solve.parts import Part
from udh_cli.mosaic.solve.rectify import keep_reference_view, rectifying_homography


@dataclass(frozen=True)
class GlobalSolve:
    """The global solve's settings (:class:`~udh_cli.mosaic.config.MosaicConfig` holds them).

    Attributes:
        model: ``homography`` (a free one per frame) or ``camera`` (a pinhole camera per frame over flat ground).
        huber_px: residuals beyond this many pixels count linearly.
        outlier_px: a loop pair further than this from the joint solution, which improves without it, is rejected.
        rectify: without anchors, draw on the plane the frames look down on (:mod:`.rectify`).
        max_frame_scale: a plane that would draw a frame more than this many times larger or smaller is refused.
    """

    model: str
    huber_px: float
    outlier_px: float
    rectify: bool
    max_frame_scale: float


def _focal_px(frameset: FrameSet, part: Part) -> tuple[float, str]:
    """The focal length the camera-model solve holds for ``part``, pixels, and where it came from: a --camera
    file's, else its frames' EXIF 35 mm equivalent, else :data:`.lens_fit.DEFAULT_FOCAL` of the longer side."""
    longest = max(frameset.frames[part.reference].size)
    if frameset.lens is not None:
        return float(frameset.lens.focal_x * longest), "the --camera file"
    focal, source = frames_focal([frameset.frames[i] for i in part.frames])
    return focal * longest, source


def _solve_cameras(frameset: FrameSet, part: Part, points: list, huber_px: float, reporter: Reporter, anchors: Anchors | None) -> None:
    """--solve camera on one part after its homography solve: ``part.cameras`` and ``part.solved`` from the
    camera model; a part it cannot serve (frames of two sizes, no finite cameras) keeps the homography solve,
    with a warning."""
    sizes = [f.size for f in frameset.frames]
    name = frameset.frames[part.reference].name
    if len({sizes[i] for i in part.frames}) > 1:
        reporter.warn(f"--solve camera: the part of {name} mixes frame sizes, so not one camera; it keeps the homography solve")
        return
    focal, part.focal_source = _focal_px(frameset, part)
    try:
        part.cameras = solve_cameras(part.reference, part.solved, sizes, points, focal, huber_px, anchors=anchors)
    except UdhError as error:
        reporter.warn(f"--solve camera: the part of {name} keeps the homography solve ({error})")
        return
    part.solved = part.cameras.ref_from


@dataclass(frozen=True)
class SolvedPairs:
    """What the global solve says of the pairs: ``pairs`` as given, each pair inside a part judged (its consistency
    figures, and rejected where the other pairs contradict it), and the loop summaries for the sidecar."""

    pairs: list[PairResult]
    loops: dict[str, Any]


def solve_parts(frameset: FrameSet, parts: list[Part], pairs: list[PairResult], settings: GlobalSolve, reporter: Reporter,
                anchors: Anchors | None = None) -> SolvedPairs:
    """Global solve per part (with ``anchors``, :func:`.anchors.solve_anchors`): each part's ``solved`` (and
    ``cameras``, ``rectified``); returns the pairs judged by it, new records where it judged them."""
    sizes = [f.size for f in frameset.frames]
    loops_before, loops_after, all_after = [], [], []
    verdicts: dict[int, PairVerdict] = {}  # index in ``pairs`` -> what the solve found
    multi = [p for p in parts if len(p.frames) > 1]
    with reporter.stage("global solve", len(multi)) as advance:
        for part in multi:
            members = set(part.frames)
            inside = [k for k, p in enumerate(pairs) if p.ok and p.a in members and p.b in members]
            points = [pair_points(pairs[k], sizes[pairs[k].a], sizes[pairs[k].b]) for k in inside]
            in_loop = [id(pairs[k]) not in part.tree for k in inside]
            # From the loop rounds' last solve when there was one (Part.solved starts as the chain).
            part.solved, dropped = solve_with_rejection(
                part.reference, part.solved, sizes, points, [pairs[k].kind == "overlap" or (pairs[k].kind == "gps" and loop) for k, loop in zip(inside, in_loop)],
                settings.huber_px, settings.outlier_px, anchors=anchors
            )
            for i, residual in dropped.items():  # loop pairs the other pairs contradict
                verdicts[inside[i]] = PairVerdict({"before": pair_rms_px(part.chained, points[i]), "after": residual, "loop": True},
                                                  f"contradicted by the other pairs{' and the anchors' if anchors is not None else ''}: "
                                                  f"{residual:.1f} px from the joint solution, which improved without it")
            kept = [i for i in range(len(inside)) if i not in dropped]
            points = [points[i] for i in kept]
            if settings.model == "camera":
                _solve_cameras(frameset, part, points, settings.huber_px, reporter, anchors)
            for i, pts in zip(kept, points):
                before, after = pair_rms_px(part.chained, pts), pair_rms_px(part.solved, pts)
                verdicts[inside[i]] = PairVerdict({"before": before, "after": after, "loop": in_loop[i]})
                all_after.append(after)
                if in_loop[i]:
                    loops_before.append(before)
                    loops_after.append(after)
            # The camera model's ground, whatever --rectify says: the model knows it. Otherwise anchors already put
            # the plane on the ground (solve.solve_part), and without them --rectify puts it there here. Both after
            # the consistency figures, which stay in the reference frame's pixels.
            if part.cameras is not None:
                plane = keep_reference_view(part.cameras.ground_from_ref, part.solved, sizes, part.reference, settings.max_frame_scale)
                if plane is None:
                    reporter.warn(f"--solve camera: drawing the part of {frameset.frames[part.reference].name} on the cameras' ground "
                                  "would fold a frame; it is drawn in its reference frame's view")
            elif settings.rectify and anchors is None:
                plane = rectifying_homography(part.solved, sizes, part.reference, settings.max_frame_scale)
            else:
                plane = None
            if plane is not None:
                part.solved = {i: plane @ h for i, h in part.solved.items()}
                part.rectified = True
            advance(1)
    return SolvedPairs([pair.judged(verdicts[k]) if k in verdicts else pair for k, pair in enumerate(pairs)], {
        "units": "pixels of each part's reference frame at full resolution",
        "loops_before": summarise(loops_before),
        "loops_after": summarise(loops_after),
        "all_pairs_after": summarise(all_after),
    })
