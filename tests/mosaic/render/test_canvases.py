"""Planning the canvases returns the plan: frames past the horizon left out with a reason, the solved parts untouched."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.mosaic.outputs.files import RunFiles
from udh_cli.mosaic.render.canvases import Drawing, on_canvas, plan_canvases
from udh_cli.mosaic.solve.parts import Part

SIZE = (320, 240)
DRAWING = Drawing("feather", "none", "central", 3.0, None, 2**30, 1, False)
PAST_THE_HORIZON = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-0.01, 0.0, 1.0]])  # w = 0 at x = 100


def _frameset(n: int):
    return SimpleNamespace(frames=[SimpleNamespace(index=i, size=SIZE, name=f"f{i}.png") for i in range(n)], is_video=False)


def _part(number: int, frames: list[int], solved: dict[int, np.ndarray]) -> Part:
    return Part(number, list(frames), frames[0], dict(solved), dict(solved), set())


def test_a_frame_past_the_horizon_is_left_out_of_the_plan_and_its_part_is_untouched(tmp_path):
    part = _part(1, [0, 1, 2], {0: np.eye(3), 1: geometry.translation(100.0, 0.0), 2: PAST_THE_HORIZON})
    lone = _part(0, [3], {3: np.eye(3)})

    plan = plan_canvases(_frameset(4), [part, lone], RunFiles(tmp_path / "m.png"), DRAWING)

    assert [(p.number, p.frames, p.file.name) for p in plan.parts] == [(1, [0, 1], "m.png")]
    assert list(plan.dropped) == [2] and "degenerate" in plan.dropped[2]
    assert part.frames == [0, 1, 2] and part.number == 1  # the solve's record is left as it was
    drawn = on_canvas(plan)
    assert drawn[0].mosaic_from_frame[1][2, 2] == 1.0
    corner = drawn[0].mosaic_from_frame[1] @ np.array([0.0, 0.0, 1.0])
    origin = drawn[0].mosaic_from_frame[0] @ np.array([0.0, 0.0, 1.0])
    assert corner[0] - origin[0] == pytest.approx(100.0)  # frame 1 drawn 100 px right of frame 0


def test_parts_are_numbered_and_named_in_order_when_the_run_splits(tmp_path):
    parts = [_part(1, [0, 1], {0: np.eye(3), 1: geometry.translation(50.0, 0.0)}),
             _part(2, [2, 3], {2: np.eye(3), 3: geometry.translation(0.0, 50.0)})]
    plan = plan_canvases(_frameset(4), parts, RunFiles(tmp_path / "m.png"), DRAWING)
    assert [(p.number, p.file.name) for p in plan.parts] == [(1, "m.part1.png"), (2, "m.part2.png")]


def test_nothing_to_draw_is_one_error(tmp_path):
    with pytest.raises(UdhError, match="no pair of frames could be matched"):
        plan_canvases(_frameset(2), [_part(0, [0], {0: np.eye(3)}), _part(0, [1], {1: np.eye(3)})], RunFiles(tmp_path / "m.png"), DRAWING)
