"""`udh bench hard` on pairs the test makes: the sources it finds, a set per kind of motion, the scoring of
udh's verdicts (a right answer, a wrong one called verified), the reliability bins and the diagram."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from udh_cli import cli, geometry
from udh_cli.bench import runner
from udh_cli.bench.hard import KINDS, build_sets, run_hard_bench
from udh_cli.bench.hard_pairs import FLIGHT_GROUP, PAIRS_GROUP, _stored_to_shown, find_pairs
from udh_cli.bench.hard_report import markdown_table, write_hard_outputs
from udh_cli.bench.motions import MOTION_KINDS
from udh_cli.bench.verdicts import ALL_KINDS, kind_scores, reliabilities, reliability, verified
from udh_cli.errors import UdhError
from udh_cli.estimators import Estimate
from udh_cli.estimators.base import Estimator, is_verified
from udh_cli.estimators.pair import PreparedImage

from conftest import warped_pair

MOTIONS = [geometry.translation(12.0, -8.0), np.array([[1.02, 0.03, -6.0], [-0.02, 0.99, 9.0], [1e-5, 0.0, 1.0]])]


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    """A folder with a pairs CSV (img1,img2,H) of two textured 320x240 pairs, as a flight's consecutive pairs."""
    folder = tmp_path_factory.mktemp("sources") / "flight"
    folder.mkdir()
    lines = ["img1,img2,ransac_inliers,H_sift_ransac_1to2"]
    for k, truth in enumerate(MOTIONS):
        image_a, image_b = warped_pair(truth, seed=k)
        cv2.imwrite(str(folder / f"a{k}.png"), image_a)
        cv2.imwrite(str(folder / f"b{k}.png"), image_b)
        lines.append(f"a{k}.png,b{k}.png,200,{' '.join(f'{v:.17g}' for v in truth.ravel())}")
    lines.append("a0.png,b1.png,12,1 0 0 0 1 0 0 0 1")  # too few inliers: left out
    (folder / "consecutive_pairs_sift_reference.csv").write_text("\n".join(lines) + "\n")
    return folder


class Oracle(Estimator):
    """Answers the truth of each pair (looked up by B's pixels), moved by ``error_px`` along x, with a verdict."""

    name = "oracle"

    def __init__(self, truths: dict[bytes, np.ndarray], error_px: float = 0.0, verdict: bool | None = None,
                 confidence: float = 0.9):
        self.truths, self.error_px, self.verdict, self.confidence = truths, error_px, verdict, confidence

    def _estimate(self, pair):
        truth = self.truths[pair.b.grey.tobytes()]
        details = {} if self.verdict is None else {"verified": self.verdict}
        return geometry.translation(self.error_px, 0.0) @ truth, self.confidence, details


@pytest.fixture(scope="module")
def sets(source):
    pairs, notes = find_pairs([source.parent])  # a folder of sources, searched one level down
    assert len(pairs) == 2 and all(p.group == FLIGHT_GROUP for p in pairs)
    made, short = build_sets(pairs, count=3, seed=0)
    return made, short


def test_a_set_per_kind_with_the_composed_truth(sets):
    made, short = sets
    assert [s.name for s in made] == [FLIGHT_GROUP] + list(MOTION_KINDS)  # no "real pairs" source given
    assert f"{FLIGHT_GROUP}: 2 pairs, fewer than --n 3" in short
    flight = made[0]
    np.testing.assert_allclose(sorted(flight.truths[:, 0, 2]), sorted(m[0, 2] for m in MOTIONS), atol=1e-9)
    for pair_set in made[1:]:
        assert len(pair_set) == 3 and all("turn" in label for label in pair_set.labels)
        for a, b, truth in zip(pair_set.images_a, pair_set.images_b, pair_set.truths):
            # The truth explains B from A: warping A by it matches B where both see the plane.
            back = cv2.warpPerspective(a, truth, (b.shape[1], b.shape[0]), flags=cv2.INTER_LINEAR)
            seen = cv2.erode((cv2.warpPerspective(np.full_like(a, 255), truth, (b.shape[1], b.shape[0])) == 255).astype(np.uint8),
                             np.ones((9, 9), np.uint8)).astype(bool) & (b > 0)
            assert seen.sum() > 2000 and np.median(np.abs(back[seen].astype(int) - b[seen].astype(int))) < 4


def test_sets_are_reproducible_from_the_seed(source, sets):
    again, _ = build_sets(find_pairs([source])[0], count=3, seed=0)
    assert all(np.array_equal(x.truths, y.truths) and x.labels == y.labels for x, y in zip(sets[0], again))


def _truths(pair_sets) -> dict[bytes, np.ndarray]:
    return {PreparedImage.of(b).grey.tobytes(): t for s in pair_sets for b, t in zip(s.images_b, s.truths)}


def test_the_truth_scores_no_failure_and_a_verified_wrong_answer_is_counted(sets):
    made, _ = sets
    truths = _truths(made)
    jobs = [runner.Job("truth", "image", Oracle(truths)),
            runner.Job("liar", "image", Oracle(truths, error_px=30.0, verdict=True)),
            runner.Job("doubter", "image", Oracle(truths, error_px=30.0, verdict=False)),
            runner.Job("unsure", "image", Oracle(truths, error_px=30.0, confidence=0.1))]
    runs = runner.run_jobs(jobs, made, show_progress=False)
    scores = {(s.kind, s.method): s for s in kind_scores(runs)}
    n = sum(len(s) for s in made)
    truth, liar = scores[(ALL_KINDS, "truth")], scores[(ALL_KINDS, "liar")]
    assert (truth.pairs, truth.failures, truth.verified, truth.verified_wrong, truth.median_px) == (n, 0, n, 0, pytest.approx(0, abs=1e-6))
    assert (liar.failures, liar.verified, liar.verified_wrong, liar.wrong_among_verified) == (n, n, n, 1.0)
    assert liar.median_px == pytest.approx(30.0)
    for method in ("doubter", "unsure"):  # wrong, but not called verified
        assert (scores[(ALL_KINDS, method)].failures, scores[(ALL_KINDS, method)].verified_wrong) == (n, 0)
    assert scores[("scale", "liar")].verified_wrong == 3
    curves = {c.method: c for c in reliabilities(runs)}
    assert curves["truth"].counts[9] == n and curves["truth"].fraction_right[9] == 1.0
    assert curves["unsure"].counts[1] == n and curves["unsure"].fraction_right[1] == 0.0


@pytest.mark.parametrize("verdict,confidence", [(None, 0.19), (None, 0.2), (True, 0.05), (False, 0.95)])
def test_verified_follows_udh_estimate(verdict, confidence):
    estimate = Estimate("x", np.eye(3), confidence, 1.0, verified=verdict)
    run = runner.MethodRun("s", None, "x", "image", np.zeros(1), np.zeros(1), np.ones(1, bool), np.ones(1), [""], 1.0,
                           None, confidence=np.array([confidence]), verdicts=np.array([-1 if verdict is None else int(verdict)]))
    assert bool(verified(run)[0]) == is_verified(estimate)


def test_reliability_bins():
    curve = reliability("m", np.array([0.05, 0.05, 0.95, 1.0, 0.42]), np.array([True, False, True, True, False]))
    assert curve.counts.tolist() == [2, 0, 0, 0, 1, 0, 0, 0, 0, 2]
    assert curve.fraction_right[0] == 0.5 and curve.fraction_right[4] == 0.0 and curve.fraction_right[9] == 1.0
    assert np.isnan(curve.fraction_right[1]) and curve.mean_confidence[9] == pytest.approx(0.975)


@pytest.mark.parametrize("orientation,rotate", [(3, cv2.ROTATE_180), (6, cv2.ROTATE_90_CLOCKWISE),
                                                (8, cv2.ROTATE_90_COUNTERCLOCKWISE)])
def test_exif_orientation_turns_the_reference_with_the_pixels(orientation, rotate):
    stored = np.arange(5 * 7, dtype=np.uint8).reshape(5, 7)  # 7 wide, 5 high
    shown = cv2.rotate(stored, rotate)
    matrix = _stored_to_shown(orientation, 7, 5)
    for x, y in [(0, 0), (6, 0), (6, 4), (2, 3)]:
        sx, sy = geometry.transform_points(matrix, np.array([[x, y]], float))[0].round().astype(int)
        assert shown[sy, sx] == stored[y, x]
    with pytest.raises(UdhError, match="mirrored"):
        _stored_to_shown(2, 7, 5)


def test_outputs_and_the_diagram_decode(source, tmp_path):
    result = run_hard_bench([source], methods=["identity"], count=2, seed=1, show_progress=False)
    assert [s.kind for s in result.scores] == [FLIGHT_GROUP] + list(MOTION_KINDS) + [ALL_KINDS]
    written = write_hard_outputs(result, tmp_path)
    assert {p.name for p in written} == {"results.md", "results.json", "reliability.png"}
    diagram = cv2.imread(str(tmp_path / "reliability.png"))
    assert diagram is not None and diagram.shape[0] > 300 and diagram.shape[1] > 500
    data = json.loads((tmp_path / "results.json").read_text())
    assert len(data["pairs"]) == sum(s.pairs for s in result.scores if s.kind != ALL_KINDS)
    assert data["reliability"][0]["counts"][0] == len(data["pairs"])  # the identity answers with confidence 0
    assert "| **all kinds** | identity |" in markdown_table(result)
    assert KINDS[1] == PAIRS_GROUP


def test_the_command_writes_its_files_and_bad_sources_fail_in_one_line(source, tmp_path):
    out = tmp_path / "out"
    ok = CliRunner().invoke(cli.app, ["bench", "hard", str(source), "-m", "identity", "--n", "1", "--out", str(out)])
    assert ok.exit_code == 0, ok.output
    assert (out / "reliability.png").is_file() and "| scale | identity | 1 |" in ok.output
    missing = CliRunner().invoke(cli.app, ["bench", "hard", str(tmp_path / "nowhere"), "-m", "identity"])
    assert missing.exit_code != 0 and isinstance(missing.exception, UdhError) and "no such file" in str(missing.exception)
    empty = tmp_path / "empty"
    empty.mkdir()
    nothing = CliRunner().invoke(cli.app, ["bench", "hard", str(empty), "-m", "identity", "--out", str(tmp_path / "o2")])
    assert isinstance(nothing.exception, UdhError) and "no pairs" in str(nothing.exception)
    assert not (tmp_path / "o2").exists()


def test_the_shared_flights_references_fit_their_images_as_read(shared_data):
    """boruszyn-kite is stored unrotated with EXIF orientation 8 and its references are in the stored pixels: turned
    with the images, SIFT on the pair as read agrees with the reference."""
    from udh_cli.estimators import create_estimator

    pairs, _ = find_pairs([shared_data / "flights" / "boruszyn-kite"])
    pair = next(p for p in pairs if p.label == "img_4854.jpg->img_4858.jpg")
    assert pair.orientation == (8, 8)
    image_a, image_b, truth = pair.load()
    assert max(image_a.shape) == 800 and image_a.shape[0] > image_a.shape[1]  # portrait, as a viewer shows it
    estimate = create_estimator("sift").estimate(image_a, image_b)
    assert geometry.mace(estimate.homography, truth, image_a.shape[1], image_a.shape[0]) < 3.0
