"""The global solve on synthetic pair graphs: it removes chaining drift and shrugs off a wrong loop pair."""

from __future__ import annotations

import numpy as np

from udh_cli import geometry
from udh_cli.mosaic.solve.graph import chain_to_reference, connected_parts, overlap_candidates
from udh_cli.mosaic.pairs.types import PairResult
from udh_cli.mosaic.solve.homographies import pair_points, pair_rms_px, solve_part, solve_with_rejection

SIZE = (320, 240)


def _truth(n_per_strip: int = 5) -> dict[int, np.ndarray]:
    """ref_from_frame of two strips flown back and forth, frame 0 is the reference; mild perspective."""
    rng = np.random.default_rng(0)
    out = {}
    for index in range(2 * n_per_strip):
        strip, step = divmod(index, n_per_strip)
        column = step if strip == 0 else n_per_strip - 1 - step
        h = geometry.translation(80.0 * column, 100.0 * strip) @ geometry.homography_from_offsets(rng.uniform(-3, 3, (4, 2)), *SIZE)
        out[index] = h / h[2, 2]
    first = geometry.invert(out[0])
    return {i: first @ h / (first @ h)[2, 2] for i, h in out.items()}


def _pair(truth, a, b, kind, error=np.eye(3)) -> PairResult:
    b_from_a = error @ geometry.invert(truth[b]) @ truth[a]
    return PairResult(a, b, kind, b_from_a=b_from_a / b_from_a[2, 2], status="ok")


def _max_error(ref_from, truth) -> float:
    return max(float(geometry.corner_errors(ref_from[i], truth[i], *SIZE).max()) for i in truth)


def test_solve_removes_drift_of_biased_chain():
    truth = _truth()
    sizes = [SIZE] * len(truth)
    bias = np.array([[1.003, 0.0, 0.4], [0.0, 1.003, -0.3], [0.0, 0.0, 1.0]])  # every consecutive pair slightly off
    pairs = [_pair(truth, i, i + 1, "consecutive", bias) for i in range(len(truth) - 1)]
    parts = connected_parts(len(truth), pairs)
    assert parts == [list(range(len(truth)))]
    chained, tree = chain_to_reference(parts[0], 0, pairs)
    assert len(tree) == len(truth) - 1
    known = {(p.a, p.b) for p in pairs}
    loops = overlap_candidates(parts[0], chained, sizes, known, min_overlap=0.3, per_frame=3)
    assert loops and all(b - a >= 2 for a, b, _ in loops)
    pairs += [_pair(truth, a, b, "overlap") for a, b, _ in loops]  # loop closures measured without bias
    points = [pair_points(p, SIZE, SIZE) for p in pairs]
    solved = solve_part(0, chained, sizes, points)
    drift, remaining = _max_error(chained, truth), _max_error(solved, truth)
    assert drift > 5.0
    assert remaining < drift / 3
    # The loops were inconsistent under the chain and much less so after the solve (the biased consecutive
    # pairs and the exact loop pairs cannot all be met: least squares shares the disagreement out).
    loop_points = points[len(truth) - 1 :]
    before = max(pair_rms_px(chained, p) for p in loop_points)
    after = max(pair_rms_px(solved, p) for p in loop_points)
    assert before > 3.0 and after < before / 3
    np.testing.assert_allclose(solved[0], np.eye(3), atol=1e-12)


def test_exact_pairs_give_the_exact_solution_from_any_reference():
    truth = _truth()
    sizes = [SIZE] * len(truth)
    pairs = [_pair(truth, i, i + 1, "consecutive") for i in range(len(truth) - 1)]
    pairs += [_pair(truth, 1, 8, "overlap"), _pair(truth, 2, 7, "overlap"), _pair(truth, 3, 6, "overlap")]
    chained, tree = chain_to_reference(list(range(len(truth))), 4, pairs)
    assert len(tree) == len(truth) - 1  # loop pairs are never chained along
    to_4 = geometry.invert(truth[4])
    truth_4 = {i: (to_4 @ h) / (to_4 @ h)[2, 2] for i, h in truth.items()}
    # Start the solve away from the answer: it must come back to the truth, with the reference fixed.
    start = {i: (h @ geometry.translation(3.0, -2.0) if i != 4 else h) for i, h in chained.items()}
    solved = solve_part(4, start, sizes, [pair_points(p, SIZE, SIZE) for p in pairs])
    assert _max_error(solved, truth_4) < 1e-3
    np.testing.assert_allclose(solved[4], np.eye(3), atol=1e-12)


def test_a_wrong_loop_closure_is_found_and_dropped():
    truth = _truth()
    sizes = [SIZE] * len(truth)
    rng = np.random.default_rng(1)
    noise = lambda: geometry.homography_from_offsets(rng.normal(0, 0.15, (4, 2)), *SIZE)  # noqa: E731 - honest 0.15 px errors
    pairs = [_pair(truth, i, i + 1, "consecutive", noise()) for i in range(len(truth) - 1)]
    pairs += [_pair(truth, a, b, "overlap", noise()) for a, b in ((1, 8), (2, 7), (0, 2), (5, 7))]
    wrong = len(pairs)
    pairs.append(_pair(truth, 3, 6, "overlap", geometry.translation(30.0, -20.0)))  # matched the wrong place
    chained, _ = chain_to_reference(list(range(len(truth))), 4, pairs)
    points = [pair_points(p, SIZE, SIZE) for p in pairs]
    truth_4 = {i: (geometry.invert(truth[4]) @ h) / (geometry.invert(truth[4]) @ h)[2, 2] for i, h in truth.items()}
    # Huber alone lets the wrong pair bend the chain by many pixels...
    assert _max_error(solve_part(4, chained, sizes, points), truth_4) > 10
    # ...the rejection step finds it, and only it, and the rest solves to sub-pixel accuracy.
    solved, dropped = solve_with_rejection(4, chained, sizes, points, [p.kind == "overlap" for p in pairs])
    assert list(dropped) == [wrong]
    assert _max_error(solved, truth_4) < 1.0
    # With honest pairs only, nothing is dropped.
    honest = points[:wrong]
    _, none_dropped = solve_with_rejection(4, chained, sizes, honest, [p.kind == "overlap" for p in pairs[:wrong]])
    assert none_dropped == {}


def test_loop_pair_inputs_are_cropped_to_the_covered_window():
    """A pre-warped B is cut to a window that is at least 98 % real pixels, so no method sees its empty border."""
    import cv2

    from udh_cli.mosaic.pairs.types import covered_window as _covered_window

    covered = np.zeros((480, 640), np.uint8)
    quad = np.array([[200, 40], [630, 90], [600, 470], [150, 420]], np.int32)
    cv2.fillPoly(covered, [quad], 1)
    x0, y0, x1, y1 = _covered_window(covered > 0)
    window = covered[y0:y1, x0:x1]
    assert window.mean() >= 0.98
    assert (x1 - x0) * (y1 - y0) > 0.5 * covered.sum()  # shrunk only as far as needed
    assert _covered_window(np.zeros((100, 100), bool)) is None


def test_the_sparse_system_solves_as_its_dense_form_does(monkeypatch):
    """The sparse assembly and solve give what a dense solve of the same normal equations gives."""
    import udh_cli.mosaic.solve.homographies as solve_module

    truth = _truth()
    sizes = [SIZE] * len(truth)
    bias = np.array([[1.002, 0.0, 0.3], [0.0, 1.002, -0.2], [0.0, 0.0, 1.0]])
    pairs = [_pair(truth, i, i + 1, "consecutive", bias) for i in range(len(truth) - 1)]
    pairs += [_pair(truth, 0, 9, "overlap"), _pair(truth, 2, 7, "overlap"), _pair(truth, 1, 8, "overlap")]
    chained, _ = chain_to_reference(list(range(len(truth))), 0, pairs[: len(truth) - 1])
    points = [pair_points(p, SIZE, SIZE) for p in pairs]
    sparse_answer = solve_part(0, chained, sizes, points)
    dense_solves = []
    monkeypatch.setattr(solve_module, "solve_symmetric", lambda matrix, rhs: dense_solves.append(1) or np.linalg.solve(matrix.toarray(), rhs))
    dense_answer = solve_part(0, chained, sizes, points)
    assert dense_solves  # the dense solve did replace the sparse one
    assert _max_error(sparse_answer, dense_answer) < 1e-6


def test_a_long_survey_solves_with_memory_that_grows_with_its_pairs():
    """360 frames in 12 strips, every consecutive and cross-strip pair: a dense system would be 2,872 square
    (66 MB of blocks in the dense assembly); the sparse one holds only the pairs' blocks, a few MB at peak."""
    import tracemalloc

    rng = np.random.default_rng(3)
    strips, per_strip = 12, 30
    truth = {}
    for index in range(strips * per_strip):
        strip, step = divmod(index, per_strip)
        column = step if strip % 2 == 0 else per_strip - 1 - step
        truth[index] = geometry.translation(80.0 * column, 100.0 * strip) @ geometry.homography_from_offsets(rng.uniform(-2, 2, (4, 2)), *SIZE)
    first = geometry.invert(truth[0])
    truth = {i: first @ h / (first @ h)[2, 2] for i, h in truth.items()}
    sizes = [SIZE] * len(truth)
    noise = lambda: geometry.homography_from_offsets(rng.normal(0, 0.05, (4, 2)), *SIZE)  # noqa: E731
    pairs = [_pair(truth, i, i + 1, "consecutive", noise()) for i in range(len(truth) - 1)]
    for index in range(len(truth) - per_strip):
        strip, step = divmod(index, per_strip)
        partner = (strip + 2) * per_strip - 1 - step  # the frame above it on the next strip, flown the other way
        pairs.append(_pair(truth, index, partner, "overlap", noise()))
    chained, _ = chain_to_reference(list(range(len(truth))), 0, pairs[: len(truth) - 1])
    points = [pair_points(p, SIZE, SIZE) for p in pairs]
    tracemalloc.start()
    solved = solve_part(0, chained, sizes, points)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 40e6  # the dense assembly alone held (n+1)^2 8x8 blocks: 68 MB here
    loops = points[len(truth) - 1 :]
    before = np.mean([pair_rms_px(chained, p) for p in loops])
    after = np.mean([pair_rms_px(solved, p) for p in loops])
    assert before > 3.0 and after < before / 10  # the cross-strip pairs, off under chaining, agree after the solve


def test_gps_anchors_bound_the_drift_of_a_long_chain_without_loops():
    """A lawn-mower of 3 strips of 12 frames, every consecutive pair slightly off in perspective, no loop pairs:
    the chain drifts and the solve alone cannot see it. GPS fixes (1 px of noise, in metres) pull it back; with
    too few fixes the solve is the plain one."""
    from udh_cli.mosaic.solve.homographies import Anchors

    per_strip, strips = 12, 3
    order = [(column if strip % 2 == 0 else per_strip - 1 - column, strip) for strip in range(strips) for column in range(per_strip)]
    truth = {i: geometry.translation(60.0 * column, 150.0 * strip) for i, (column, strip) in enumerate(order)}
    count = len(truth)
    sizes = [SIZE] * count
    bias = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [2e-5, 1e-5, 1.0]])
    pairs = [_pair(truth, i, i + 1, "sequential", bias) for i in range(count - 1)]
    points = [pair_points(p, SIZE, SIZE) for p in pairs]
    chained = {0: np.eye(3)}
    for p in pairs:
        h = chained[p.a] @ geometry.invert(p.b_from_a)
        chained[p.b] = h / h[2, 2]
    metres = np.array([[0.0, -0.05], [0.05, 0.0]])  # 5 cm a pixel, the frame turned a quarter from north
    rng = np.random.default_rng(1)
    centre = np.array([(SIZE[0] - 1) / 2, (SIZE[1] - 1) / 2])
    fixes = {i: metres @ (truth[i][:2, 2] + centre) + [500_000.0, 4_000_000.0] + rng.normal(0, 0.05, 2) for i in range(count)}
    plain = solve_part(0, chained, sizes, points)
    anchored = solve_part(0, chained, sizes, points, anchors=Anchors.frame_centres(fixes, sizes, 0.05))
    drift, bounded = _max_error(plain, truth), _max_error(anchored, truth)
    assert drift > 100 and bounded < drift / 4
    assert max(pair_rms_px(anchored, p) for p in points) < 2.0  # the pairs still hold
    # Too few anchored frames, or frames along one line, cannot hold the plane: the part is solved from its pairs.
    for kept in ((0, 9), (0, 11, 24, 35), tuple(range(12))):  # two; the four corners; one strip
        few = solve_part(0, chained, sizes, points, anchors=Anchors.frame_centres({i: fixes[i] for i in kept}, sizes, 0.05))
        assert all(np.array_equal(few[i], plain[i]) for i in plain), kept
    sparse = solve_part(0, chained, sizes, points, anchors=Anchors.frame_centres({i: fixes[i] for i in (0, 6, 11, 18, 24, 30, 35)}, sizes, 0.05))
    assert max(pair_rms_px(sparse, p) for p in points) < 2.0 and _max_error(sparse, truth) < drift  # 7 spread fixes: no collapse
