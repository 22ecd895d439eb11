"""Learned estimators on onnxruntime: export parity, estimator geometry, bad model files, shipped models."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import export_tiny_network, textured_image, warped_pair
from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.estimators import create_estimator, deep, matching
from udh_cli.estimators.pair import PreparedImage
from udh_cli.models_catalog import SHIPPED_MODELS, models_dir


@pytest.fixture(scope="module")
def tiny_onnx(tmp_path_factory) -> Path:
    return export_tiny_network(tmp_path_factory.mktemp("tiny"), "corr", seed=0)


@pytest.fixture(scope="module")
def tiny_fine_onnx(tmp_path_factory) -> Path:
    """The refinement architecture, exported: its strided stem and 4-px cells go through ONNX too."""
    return export_tiny_network(tmp_path_factory.mktemp("tiny_fine"), "corr-fine", seed=1)


def test_lite_network_exports_with_its_window_index_as_a_constant(tmp_path):
    """corr-lite (the fast coarse network) goes through ONNX with parity, and no network recomputes the
    correlation window from shapes at run time: that was a dozen small ops per batch-1 call."""
    onnx = pytest.importorskip("onnx")
    path = export_tiny_network(tmp_path, "corr-lite", seed=2, fresh=True)
    ops = {node.op_type for node in onnx.load(str(path)).graph.node}
    assert "GatherElements" in ops  # the window gather is there...
    assert not ops & {"Range", "GreaterOrEqual", "Less"}  # ...but not the arithmetic that built its index


def test_export_takes_check_patches_of_another_size(tiny_onnx, tmp_path):
    # `udh export-onnx --check-images` draws 128-px patches whatever the network's input size.
    pytest.importorskip("torch")
    from udh_cli.train.export import export_onnx

    real = np.stack([textured_image(128, 128, seed=1), textured_image(128, 128, seed=2)])[None].astype(np.float32) / 255
    result = export_onnx(tiny_onnx.with_suffix(".pt"), tmp_path / "again.onnx", check_inputs=real)
    assert result["max_abs_diff"] < 1e-4 and (tmp_path / "again.onnx").is_file()


def test_estimate_and_batch_agree_and_return_full_resolution_pixels(tiny_onnx):
    # No searches: an untrained network's answer is doubted, and a search would replace the pass checked here.
    estimator = create_estimator("unsupervised", model=str(tiny_onnx), device="cpu", search=0, heading_search=0)
    a = textured_image(400, 300, seed=3)
    b = textured_image(320, 240, seed=4)
    single = estimator.estimate(a, b)
    batch = estimator.estimate_many([(a, b), (b, a)])
    np.testing.assert_allclose(single.homography, batch[0].homography, atol=1e-9)
    # The network works on 32x32 versions; the answer must be that estimate rescaled exactly.
    small = estimator.predict_small(PreparedImage.of(a).resized((32, 32))[None], PreparedImage.of(b).resized((32, 32))[None])[0]
    expected = geometry.rescale_homography(small, (32, 32), (400, 300), (32, 32), (320, 240))
    np.testing.assert_allclose(single.homography, expected / expected[2, 2], atol=1e-9)
    assert 0.0 <= single.confidence <= 1.0 and single.elapsed_ms > 0


def test_iterations_compose_residuals(tiny_onnx):
    one = create_estimator("unsupervised", model=str(tiny_onnx), device="cpu", iterations=1)
    two = create_estimator("unsupervised", model=str(tiny_onnx), device="cpu", iterations=2)
    a, b = textured_image(64, 64, seed=5), textured_image(64, 64, seed=6)
    assert not np.allclose(one.estimate(a, b).homography, two.estimate(a, b).homography)


def test_refinement_rounds_run_the_second_network_on_the_pre_warped_pair(tiny_onnx, tiny_fine_onnx):
    import cv2

    cascade = create_estimator("unsupervised", model=str(tiny_onnx), refine_model=str(tiny_fine_onnx),
                               refine_rounds=1, device="cpu")
    coarse = create_estimator("unsupervised", model=str(tiny_onnx), device="cpu")
    fine = create_estimator("unsupervised", model=str(tiny_fine_onnx), device="cpu", iterations=1)
    assert coarse.refine_rounds == 0  # a model given alone runs alone
    both = create_estimator("unsupervised", model=str(tiny_onnx), refine_model=str(tiny_fine_onnx), device="cpu")
    assert both.refine_rounds == 2  # a refinement model given is used
    with pytest.raises(UdhError, match="no such model file"):
        create_estimator("unsupervised", model=str(tiny_onnx), refine_model=str(tiny_onnx.with_name("missing.onnx")))
    a, b = textured_image(64, 64, seed=5), textured_image(64, 64, seed=6)
    small_a, small_b = PreparedImage.of(a).resized((32, 32))[None], PreparedImage.of(b).resized((32, 32))[None]
    first = coarse.predict_small(small_a, small_b)[0]
    warped_a = cv2.warpPerspective(small_a[0], first, (32, 32), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    residual = fine.predict_small(warped_a[None], small_b)[0]
    expected = residual @ first
    got = cascade.predict_small(small_a, small_b)[0]
    np.testing.assert_allclose(got / got[2, 2], expected / expected[2, 2], atol=1e-9)
    assert cascade.estimate(a, b).details["refine_rounds"] == 1
    # A cascade can be run in pieces (the large-motion search screens with the first round, then continues).
    rounds = cascade.rounds()
    assert [r.path for r in rounds] == [tiny_onnx] * cascade.iterations + [tiny_fine_onnx]
    continued = cascade.predict_small(small_a, small_b, rounds[1:], start=cascade.predict_small(small_a, small_b, rounds[:1]))[0]
    np.testing.assert_allclose(continued / continued[2, 2], expected / expected[2, 2], atol=1e-9)


def test_a_refinement_network_of_another_input_size_is_refused(tiny_onnx):
    if not (models_dir() / f"{SHIPPED_MODELS['unsupervised-refine']}.onnx").is_file():
        pytest.skip("shipped refinement model not built yet")
    with pytest.raises(UdhError, match="takes 128px inputs"):
        create_estimator("unsupervised", model=str(tiny_onnx), refine_rounds=1, device="cpu")
    with pytest.raises(UdhError, match="refine_rounds .* must be 0 or more"):
        create_estimator("unsupervised", model=str(tiny_onnx), refine_rounds=-1, device="cpu")


def test_bad_model_files_are_refused(tmp_path, tiny_onnx):
    text = tmp_path / "model.onnx"
    text.write_text("not a model")
    with pytest.raises(UdhError, match="not a loadable ONNX"):
        create_estimator("unsupervised", model=str(text))
    with pytest.raises(UdhError, match="no such model"):
        create_estimator("unsupervised", model=str(tmp_path / "missing.onnx"))
    onnx = pytest.importorskip("onnx")
    proto = onnx.load(str(tiny_onnx))
    del proto.metadata_props[:]
    foreign = tmp_path / "foreign.onnx"
    foreign.write_bytes(proto.SerializeToString())
    with pytest.raises(UdhError, match="without udh metadata"):
        create_estimator("unsupervised", model=str(foreign))
    proto = onnx.load(str(tiny_onnx))
    for entry in proto.metadata_props:
        if entry.key == "input_size":
            entry.value = "64"
    mismatched = tmp_path / "mismatched.onnx"
    mismatched.write_bytes(proto.SerializeToString())
    with pytest.raises(UdhError, match="do not fit its metadata"):
        create_estimator("unsupervised", model=str(mismatched))


def test_the_graph_input_is_fed_by_its_own_name(tiny_onnx, tmp_path):
    onnx = pytest.importorskip("onnx")
    proto = onnx.load(str(tiny_onnx))
    old = proto.graph.input[0].name
    proto.graph.input[0].name = "x"
    for node in proto.graph.node:
        node.input[:] = ["x" if name == old else name for name in node.input]
    renamed = tmp_path / "renamed.onnx"
    renamed.write_bytes(proto.SerializeToString())
    a, b = textured_image(64, 64, seed=5), textured_image(64, 64, seed=6)
    original = create_estimator("unsupervised", model=str(tiny_onnx), device="cpu").estimate(a, b)
    again = create_estimator("unsupervised", model=str(renamed), device="cpu").estimate(a, b)
    np.testing.assert_allclose(again.homography, original.homography, atol=1e-9)


def test_zero_rounds_or_batch_are_refused(tiny_onnx):
    # iterations=0 used to answer the identity with a confidence, as if the network had run.
    for options in ({"iterations": 0}, {"batch_size": 0}):
        with pytest.raises(UdhError, match="must be at least 1"):
            create_estimator("unsupervised", model=str(tiny_onnx), device="cpu", **options)


def test_cuda_request_without_cuda_is_a_clear_error(tiny_onnx):
    import onnxruntime

    if "CUDAExecutionProvider" in onnxruntime.get_available_providers():
        pytest.skip("this machine has CUDA")
    with pytest.raises(UdhError, match="no CUDA provider"):
        create_estimator("unsupervised", model=str(tiny_onnx), device="cuda")


@pytest.mark.parametrize("name", ["unsupervised", "supervised"])
def test_shipped_model_recovers_a_pair_it_never_saw(name):
    """The shipped networks on a test-made textured pair with corners moved by up to 12 px at 128x128."""
    if not (models_dir() / f"{SHIPPED_MODELS[name]}.onnx").is_file():
        pytest.skip(f"shipped {name} model not built yet")
    rng = np.random.default_rng(7)
    errors = []
    identity_errors = []
    for seed in range(6):
        offsets_small = rng.uniform(-12, 12, (4, 2))
        small = geometry.homography_from_offsets(offsets_small, 128, 128)
        truth = geometry.rescale_homography(small, (128, 128), (320, 240))
        a, b = warped_pair(truth, 320, 240, seed=seed)
        estimate = create_estimator(name, device="cpu").estimate(a, b)
        assert estimate.ok
        errors.append(geometry.mace(estimate.homography, truth, 320, 240))
        identity_errors.append(geometry.mace(np.eye(3), truth, 320, 240))
    assert np.median(errors) < 0.5 * np.median(identity_errors)


def test_search_finds_a_shift_beyond_the_networks_range():
    """Half a frame of motion: the network alone is lost; the translation search recovers it."""
    if not (models_dir() / f"{SHIPPED_MODELS['unsupervised']}.onnx").is_file():
        pytest.skip("shipped unsupervised model not built yet")
    scene = textured_image(1000, 700, seed=11)
    a = scene[100:500, 50:650]
    dx, dy = 300, 100
    b = scene[100 + dy:500 + dy, 50 + dx:650 + dx]
    truth = geometry.translation(-dx, -dy)  # x_B = x_A - shift
    # The paper-motion network alone (no flight-motion network beside it), without and with the search (the default).
    plain = create_estimator("unsupervised", device="cpu", flight_model="", search=0, matcher_model="").estimate(a, b)
    searched = create_estimator("unsupervised", device="cpu", flight_model="", matcher_model="").estimate(a, b)
    assert geometry.mace(plain.homography, truth, 600, 400) > 50
    assert searched.details["searched"] and geometry.mace(searched.homography, truth, 600, 400) < 10
    assert searched.confidence > plain.confidence + 0.3
    # Without the search, the shipped matcher's global match rescues the doubted pair instead, verified by its cells.
    matched = create_estimator("unsupervised", device="cpu", flight_model="", search=0).estimate(a, b)
    assert matched.details["matched"] and not matched.details["searched"] and matched.verified_by == "matches"
    assert geometry.mace(matched.homography, truth, 600, 400) < 3
    with pytest.raises(UdhError, match="search .* must be 0"):
        create_estimator("unsupervised", device="cpu", search=-1)


def test_the_device_picks_providers_from_onnxruntimes_list(monkeypatch):
    """This machine has no GPU: the provider choice is tested against onnxruntime's provider list."""
    import onnxruntime as ort

    from udh_cli.onnx_model import providers_for

    monkeypatch.setattr(ort, "get_available_providers", lambda: ["CUDAExecutionProvider", "CPUExecutionProvider"])
    assert providers_for("cuda") == ["CUDAExecutionProvider", "CPUExecutionProvider"]
    assert providers_for("auto")[0] == "CUDAExecutionProvider"
    assert providers_for("cpu") == ["CPUExecutionProvider"]
    monkeypatch.setattr(ort, "get_available_providers", lambda: ["CPUExecutionProvider"])
    assert providers_for("auto") == ["CPUExecutionProvider"]
    with pytest.raises(UdhError, match="onnxruntime-gpu"):
        providers_for("cuda")


def test_estimates_say_which_provider_ran():
    from conftest import warped_pair

    a, b = warped_pair(np.array([[1, 0, 4.0], [0, 1, -3.0], [0, 0, 1]]))
    found = create_estimator("unsupervised", device="cpu").estimate(a, b)
    assert found.details["provider"] == "CPUExecutionProvider"


def test_the_flight_network_joins_the_cascade_and_follows_large_whole_frame_motion():
    """Whole frames shifted by 40 % of their width and turned 10 degrees: beyond the paper-motion network's
    training (corners moved by up to 45 px of 128), within the flight network's."""
    from udh_cli.models_catalog import has_shipped

    if not has_shipped("unsupervised-flight", precision=None):
        pytest.skip("shipped flight network not built yet")
    scene = textured_image(1400, 1000, seed=13)
    turn = geometry.translation(700, 500) @ np.array([[np.cos(0.17), -np.sin(0.17), 0], [np.sin(0.17), np.cos(0.17), 0], [0, 0, 1]]) @ geometry.translation(-700, -500)
    a = scene[250:730, 300:940]
    b_from_scene = geometry.translation(-(300 + 256), -250) @ turn
    b = cv2.warpPerspective(scene, b_from_scene, (640, 480))
    truth = b_from_scene @ geometry.translation(300, 250)
    both = create_estimator("unsupervised", device="cpu")
    assert len(both.networks.first) == 2
    found = both.estimate(a, b)
    error = float(geometry.mace(found.homography, truth, 640, 480))
    assert error < 3.0, error
    # The whole-frame networks alone (no tile stage, which can rescue either start): the flight network's
    # answer is the nearer one.
    both_untiled = create_estimator("unsupervised", device="cpu", tiles=False).estimate(a, b)
    paper_untiled = create_estimator("unsupervised", device="cpu", flight_model="", tiles=False).estimate(a, b)
    untiled_error = float(geometry.mace(both_untiled.homography, truth, 640, 480))
    assert not paper_untiled.ok or float(geometry.mace(paper_untiled.homography, truth, 640, 480)) > untiled_error


@pytest.mark.parametrize("used, run, verified", [(1, 3, False), (2, 3, True), (1, 1, True), (0, 2, False)])
def test_an_answer_is_verified_only_when_enough_tile_levels_accept_it(monkeypatch, used, run, verified):
    """One accepted level of three is not a confirmation (on seneca such answers were wrong 9 times in 10):
    the answer is reported unverified, and a mosaic doubts it (pairs.Acceptance). Confirmed, the right answer
    passes the rest of the verdict too (its alignment and round trip)."""
    if not (models_dir() / f"{SHIPPED_MODELS['unsupervised']}.onnx").is_file():
        pytest.skip("shipped unsupervised model not built yet")
    import udh_cli.estimators.deep as deep
    from udh_cli.estimators.tiles import TileResult

    truth = geometry.translation(8.0, -5.0)
    a, b = warped_pair(truth, 600, 400, seed=4)
    monkeypatch.setattr(deep, "refine_pairs_with_tiles", lambda network, pairs, starts, *args, **kwargs: [TileResult(h, used, 0.8, 0.5, run) for h in starts])
    estimate = create_estimator("unsupervised", device="cpu", search=0, matcher_model="").estimate(a, b)
    assert estimate.ok and estimate.details["tile_levels"] == used
    assert estimate.verified is verified


def test_the_rounds_network_runs_the_whole_frame_rounds_and_the_tiles_keep_the_refinement_network(tiny_onnx, tiny_fine_onnx, monkeypatch):
    estimator = create_estimator("unsupervised", model=str(tiny_onnx), refine_model=str(tiny_fine_onnx), rounds_model=str(tiny_onnx),
                                 flight_model="", device="cpu")
    assert [n.path for n in estimator.rounds()] == [tiny_onnx] * estimator.iterations + [tiny_onnx] * estimator.refine_rounds
    assert estimator.networks.tile.path == tiny_fine_onnx and estimator.tiles
    assert estimator.model_files() == sorted({str(tiny_onnx), str(tiny_fine_onnx)})
    used = []
    monkeypatch.setattr(deep, "refine_pairs_with_tiles", lambda network, pairs, *args, **kwargs: used.append(network.path) or [None] * len(pairs))
    a, b = warped_pair(np.eye(3), 320, 240, seed=1)
    estimator.estimate(a, b)
    assert used and set(used) == {tiny_fine_onnx}
    # Without a rounds network the refinement network runs both.
    plain = create_estimator("unsupervised", model=str(tiny_onnx), refine_model=str(tiny_fine_onnx), flight_model="", device="cpu")
    assert plain.rounds()[-1].path == tiny_fine_onnx and plain.networks.tile.path == tiny_fine_onnx


def test_the_tiles_coarse_network_runs_only_the_tile_stage_coarse_level(tiny_onnx, tiny_fine_onnx, tmp_path, monkeypatch):
    tile_coarse = tmp_path / "tile-coarse.onnx"
    tile_coarse.write_bytes(tiny_onnx.read_bytes())
    estimator = create_estimator("unsupervised", model=str(tiny_onnx), refine_model=str(tiny_fine_onnx), tile_coarse_model=str(tile_coarse),
                                 flight_model="", device="cpu")
    assert [n.path for n in estimator.rounds()] == [tiny_onnx] * estimator.iterations + [tiny_fine_onnx] * estimator.refine_rounds
    assert estimator.model_files() == sorted({str(tiny_onnx), str(tiny_fine_onnx), str(tile_coarse)})
    used = []
    monkeypatch.setattr(deep, "refine_pairs_with_tiles", lambda network, pairs, *args, coarse_network=None, **kwargs: used.append((network.path, coarse_network.path)) or [None] * len(pairs))
    a, b = warped_pair(np.eye(3), 320, 240, seed=1)
    estimator.estimate(a, b)
    assert used and set(used) == {(tiny_fine_onnx, tile_coarse)}
    with pytest.raises(UdhError, match="needs a refinement stage"):  # no tile stage to run it in
        create_estimator("unsupervised", model=str(tiny_onnx), tile_coarse_model=str(tile_coarse), flight_model="", device="cpu")
    # Without it the coarse network starts the tiles, as it starts the cascade.
    plain = create_estimator("unsupervised", model=str(tiny_onnx), refine_model=str(tiny_fine_onnx), flight_model="", device="cpu")
    assert plain.networks.tile_coarse.path == tiny_onnx


def test_a_doubted_pair_takes_the_global_match_and_a_confident_match_verifies_itself():
    """Half the frame of motion across (200 px of 384): without the search the cascade is lost; the matcher (here
    the block descriptors of conftest, in place of a trained one) finds the shift, and its answer is marked verified
    by its matches. The translation search is off so that only the matcher can rescue the pair."""
    if not (models_dir() / f"{SHIPPED_MODELS['unsupervised']}.onnx").is_file():
        pytest.skip("shipped unsupervised model not built yet")
    from conftest import BlockDescriptors

    scene = textured_image(700, 500, seed=12)
    a = scene[100:356, 50:434]  # 384 x 256: described at its own size (match_side 384)
    dx, dy = 200, 100
    b = scene[100 + dy : 356 + dy, 50 + dx : 434 + dx]
    truth = geometry.translation(-dx, -dy)
    plain = create_estimator("unsupervised", device="cpu", flight_model="", search=0, matcher_model="")
    before = plain.estimate(a, b)
    assert geometry.mace(before.homography, truth, 384, 256) > 20 and not before.details.get("matched")
    plain.networks = dataclasses.replace(plain.networks, matcher=BlockDescriptors())
    after = plain.estimate(a, b)
    assert after.details["matched"] and after.details["match_inliers"] >= matching.CONFIDENT_INLIERS
    assert geometry.mace(after.homography, truth, 384, 256) < 2.0
    assert after.verified is not False and "match" in after.details["stage_ms"]
    with pytest.raises(UdhError, match="match_side"):
        create_estimator("unsupervised", device="cpu", match_side=10)
    with pytest.raises(UdhError, match="match_escalate_side"):
        create_estimator("unsupervised", device="cpu", match_escalate_side=10)


def test_a_folded_global_match_never_replaces_the_cascades_answer(monkeypatch):
    """However many cells agree, a match that folds the frame is no answer: the cascade's stands, unmarked."""
    if not (models_dir() / f"{SHIPPED_MODELS['unsupervised']}.onnx").is_file():
        pytest.skip("shipped unsupervised model not built yet")
    from udh_cli.estimators.matching import MatchResult

    a, b = warped_pair(geometry.translation(6.0, -4.0), seed=5)
    folded = np.array([[-1.0, 0.0, 100.0], [0.0, 1.0, 0.0], [0.01, 0.0, 1.0]])
    monkeypatch.setattr(matching, "global_match", lambda *args, **kwargs: MatchResult(folded, 400, 500, 0))
    # Every pair doubted, no tiles to outrank the match: only the fold check stands between it and the answer.
    matcher = str(models_dir() / f"{SHIPPED_MODELS['unsupervised-matcher']}.onnx")
    estimator = create_estimator("unsupervised", device="cpu", search=0, search_below=1.0, tiles=False, matcher_model=matcher)
    estimate = estimator.estimate(a, b)
    assert estimate.ok and not estimate.details.get("matched") and estimate.verified_by != "matches"
    assert geometry.mace(estimate.homography, geometry.translation(6.0, -4.0), 320, 240) < 3


def test_a_confident_match_outranks_what_the_tiles_confirmed_and_is_kept_as_matched(monkeypatch):
    """A match hundreds of cells agree on beats a doubted cascade answer that tile levels accepted, and its own
    homography is the answer: without polish_matches it is not tiled."""
    if not (models_dir() / f"{SHIPPED_MODELS['unsupervised']}.onnx").is_file():
        pytest.skip("shipped unsupervised model not built yet")
    from udh_cli.estimators.matching import MatchResult
    from udh_cli.estimators.tiles import TileResult

    truth = geometry.translation(6.0, -4.0)
    a, b = warped_pair(truth, seed=5)
    moved = geometry.translation(30.0, 0.0) @ truth
    tile_calls = []

    def tiles(*args, **kwargs):  # two levels accept the cascade's answer, 30 px off; none accepts anything else
        tile_calls.append(1)
        return [TileResult(moved, 2, 1.0, 0.5, 2) if len(tile_calls) == 1 else TileResult(args[2][0], 0, 0.0, float("nan"), 2)]

    monkeypatch.setattr(deep, "refine_pairs_with_tiles", tiles)
    monkeypatch.setattr(matching, "global_match", lambda *args, **kwargs: MatchResult(truth.copy(), 400, 500, 0))
    matcher = str(models_dir() / f"{SHIPPED_MODELS['unsupervised-matcher']}.onnx")
    estimator = create_estimator("unsupervised", device="cpu", search=0, heading_search=0, search_below=1.0, matcher_model=matcher)
    estimate = estimator.estimate(a, b)
    assert estimate.stage == "match" and estimate.verified_by == "matches"
    assert geometry.mace(estimate.homography, truth, 320, 240) < 1e-6
    # The confident match's answer is not tiled (polish_matches is off by default); the judge runs the tiles on it
    # once, as evidence only, and as none of their levels accepts it here, it is supported by its matches, not verified.
    assert len(tile_calls) == 2 and not estimate.verified and estimate.details["verdict_failed"] == ["match tiles"]
    # Below the confident support, the answer the tile levels confirmed stands.
    tile_calls.clear()
    monkeypatch.setattr(matching, "global_match", lambda *args, **kwargs: MatchResult(truth.copy(), 40, 500, 0))
    estimate = estimator.estimate(a, b)
    assert estimate.stage == "tiles" and geometry.mace(estimate.homography, moved, 320, 240) < 1e-6
    # ...but the verdict sees that the match, an opinion of 40 cells, puts it 30 px elsewhere.
    assert not estimate.verified and "match agrees" in estimate.details["verdict_failed"]


@pytest.mark.parametrize("levels, polish, polished", [(2, True, True), (1, True, False), (2, False, False)])
def test_a_confident_match_takes_the_tile_stages_answer_where_two_levels_accept_it(monkeypatch, levels, polish, polished):
    """With polish_matches, a match's answer 3 px off: the tile stage's answer replaces it where two levels accept
    it, not one; without it (the default), the match's answer stays."""
    if not (models_dir() / f"{SHIPPED_MODELS['unsupervised']}.onnx").is_file():
        pytest.skip("shipped unsupervised model not built yet")
    from udh_cli.estimators.matching import MatchResult
    from udh_cli.estimators.tiles import TileResult

    truth = geometry.translation(6.0, -4.0)
    a, b = warped_pair(truth, seed=5)
    off = geometry.translation(3.0, 0.0) @ truth

    def tiles(network, pairs, starts, **kwargs):  # the cascade's answer confirmed by nothing; a match's moved to the truth
        near = geometry.mace(starts[0], off, 320, 240) < 1e-3
        return [TileResult(truth.copy(), levels, 1.0, 0.3, 2) if near else TileResult(starts[0], 0, 0.0, float("nan"), 2)]

    monkeypatch.setattr(deep, "refine_pairs_with_tiles", tiles)
    monkeypatch.setattr(matching, "global_match", lambda *args, **kwargs: MatchResult(off.copy(), 400, 500, 0))
    matcher = str(models_dir() / f"{SHIPPED_MODELS['unsupervised-matcher']}.onnx")
    estimator = create_estimator("unsupervised", device="cpu", search=0, heading_search=0, search_below=1.0, matcher_model=matcher,
                                 polish_matches=polish)
    estimate = estimator.estimate(a, b)
    assert estimate.details["matched"] and estimate.inliers == 400
    expected, stage = (truth, "tiles") if polished else (off, "match")
    assert estimate.stage == stage and geometry.mace(estimate.homography, expected, 320, 240) < 1e-3


def test_near_its_prior_the_network_keeps_its_networks_and_drops_the_far_searches():
    """A pre-warped loop pair: no shift search, and the global match at B's own heading and first side only;
    the estimator it came from is unchanged."""
    if not (models_dir() / f"{SHIPPED_MODELS['unsupervised']}.onnx").is_file():
        pytest.skip("shipped unsupervised model not built yet")
    full = create_estimator("unsupervised", device="cpu")
    near = full.near_prior()
    assert (near.search, near.match_settings.headings, near.match_settings.escalate_side, near.match_escalate_side) == (0, 1, None, None)
    assert (full.search, full.match_settings.headings, full.match_settings.escalate_side) == (deep.PIPELINE_SEARCH, deep.MATCH_HEADINGS, matching.MAX_MATCH_SIDE)
    assert near.networks is full.networks  # nothing loaded again
    assert near.heading_search == full.heading_search and near.settings() != full.settings()


def _turned_pair(source: np.ndarray, degrees: float, width: int = 480, height: int = 360):
    """A (``width`` x ``height``, the centre of ``source``) and B: the same view turned by ``degrees`` about its
    centre and shifted by (12, -8) px, and the true ``b_from_a``."""
    ox, oy = (source.shape[1] - width) // 2, (source.shape[0] - height) // 2
    centre = geometry.translation(-(width - 1) / 2, -(height - 1) / 2)
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    truth = geometry.translation(12.0, -8.0) @ np.linalg.inv(centre) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]) @ centre
    image_b = cv2.warpPerspective(source, truth @ geometry.translation(-ox, -oy), (width, height), flags=cv2.INTER_LINEAR)
    return source[oy : oy + height, ox : ox + width].copy(), image_b, truth


@pytest.fixture(scope="module")
def shipped_unsupervised():
    if not (models_dir() / f"{SHIPPED_MODELS['unsupervised']}.onnx").is_file():
        pytest.skip("shipped unsupervised model not built yet")
    return create_estimator("unsupervised", device="cpu")


@pytest.mark.parametrize("degrees", [37, 90, 143, 260])
def test_the_network_places_a_pair_turned_by_any_angle(shipped_unsupervised, degrees):
    """A test-made scene turned by 37, 90, 143 and 260 degrees: within 2 px, verified (0.38-1.03 px measured)."""
    image_a, image_b, truth = _turned_pair(textured_image(800, 800, seed=3), degrees)
    estimate = shipped_unsupervised.estimate(image_a, image_b)
    assert estimate.verified and geometry.mace(estimate.homography, truth, 480, 360) < 2.0


@pytest.mark.parametrize("degrees", [37, 90, 143, 260])
def test_a_turned_real_frame_is_placed_by_the_networks_and_the_global_match(shipped_unsupervised, shared_data, degrees):
    """A copr frame turned by each angle, without the heading search: the cascade's half turns, or the global match
    at a quarter turn, polished by the tiles (polish_matches) unless its guards refuse the polish; within 2 px
    (0.10-0.95 px measured), verified."""
    frame = cv2.imread(str(shared_data / "flights" / "copr" / "images" / "IMG_0043.jpg"), cv2.IMREAD_GRAYSCALE)
    image_a, image_b, truth = _turned_pair(cv2.resize(frame, (900, 600), interpolation=cv2.INTER_AREA), degrees)
    estimate = create_estimator("unsupervised", device="cpu", heading_search=0, search=0, polish_matches=True).estimate(image_a, image_b)
    assert estimate.verified and geometry.mace(estimate.homography, truth, 480, 360) < 2.0
    assert estimate.details.get("matched", False) == (degrees in (90, 260))
    assert estimate.stage == "tiles" if degrees not in (90, 260) else estimate.stage in ("tiles", "match")
