"""Compositing: tiles, bounded memory, and every blend against the simulated ground."""

from __future__ import annotations

import tracemalloc

import cv2
import numpy as np
import pytest

from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.mosaic.render.composite import BYTES_PER_PIXEL, OUTPUT_BYTES_PER_PIXEL, composite, composite_tiles, plan_canvas
from udh_cli.mosaic.inputs.frames import open_frames
from udh_cli.mosaic.report import Reporter
from udh_cli.simulate import load_ground_truth

from mosaic_flights import SMALL, make_flight


@pytest.fixture(scope="module")
def small_flight(tmp_path_factory):
    folder = tmp_path_factory.mktemp("small")
    make_flight(folder, SMALL, seed=4)
    return folder


def _true_placement(folder):
    frames = open_frames(folder, 800)
    truth = load_ground_truth(folder / "ground_truth.json")
    to_ground = {f.index: truth["ground_from_frame"][f.name] for f in frames.frames}
    corners = np.concatenate([geometry.transform_points(h, geometry.image_corners(*frames.frames[i].size)) for i, h in to_ground.items()])
    size = tuple(int(v) + 1 for v in np.ceil(corners.max(0)))
    return frames, to_ground, size


@pytest.mark.parametrize("blend", ["feather", "none", "multiband"])
def test_tiles_give_the_canvas_blended_whole(small_flight, blend):
    frames, to_ground, size = _true_placement(small_flight)
    whole = composite(frames, to_ground, size, blend, Reporter(quiet=True))
    tiles = list(composite_tiles(frames, to_ground, size, blend, Reporter(quiet=True), tile_side=96))
    assert len(tiles) == -(-size[0] // 96) * -(-size[1] // 96) > 20
    tiled = composite(frames, to_ground, size, blend, Reporter(quiet=True), tile_side=96)
    for (x0, y0, x1, y1), tile in tiles:
        assert tile.shape == (y1 - y0, x1 - x0, 4)
    assert (tiled[..., 3] == whole[..., 3]).all()  # the same coverage
    difference = np.abs(tiled.astype(np.int16) - whole.astype(np.int16))[..., :3]
    # A frame warped into a tile rather than the whole canvas lands within OpenCV's 1/32 px fixed-point
    # rounding; multiband also blends each tile with a margin. Either way: within a grey level, nearly all identical.
    assert difference.max() <= 1 and (difference == 0).mean() > 0.99


@pytest.mark.parametrize("blend", ["feather", "multiband"])
def test_tiles_blended_in_threads_are_the_same_tiles_in_the_same_order(small_flight, blend, monkeypatch):
    frames, to_ground, size = _true_placement(small_flight)
    import threading

    import udh_cli.mosaic.render.composite as composite_module

    one = list(composite_tiles(frames, to_ground, size, blend, Reporter(quiet=True), tile_side=96))
    threads, caches = set(), set()
    real = composite_module._blend_region

    def blend_region(decoded, *args):
        threads.add(threading.current_thread().name)
        caches.add(id(decoded))
        return real(decoded, *args)

    monkeypatch.setattr(composite_module, "_blend_region", blend_region)
    three = list(composite_tiles(frames, to_ground, size, blend, Reporter(quiet=True), tile_side=96, workers=3))
    assert len(threads) == 3 and all(name.startswith("udh-composite") for name in threads)
    assert len(caches) == 1  # one decoded-frame cache for all threads: a frame two tiles need is decoded once
    assert len(three) == len(one) > 20
    assert [box for box, _ in three] == [box for box, _ in one]
    assert all((a == b).all() for (_, a), (_, b) in zip(one, three))


def test_frames_evicted_from_the_decoded_cache_are_read_again(small_flight, monkeypatch):
    import udh_cli.mosaic.render.decoded as decoded_module

    frames, to_ground, size = _true_placement(small_flight)
    whole = composite(frames, to_ground, size, "feather", Reporter(quiet=True))
    monkeypatch.setattr(decoded_module, "DECODED_CACHE_BYTES", 320 * 240 * 3 * 2)  # two frames: evictions mid-tile
    tiled = composite(frames, to_ground, size, "feather", Reporter(quiet=True), tile_side=96)
    assert np.abs(tiled.astype(int) - whole.astype(int)).max() <= 1


def test_a_tile_no_frame_reaches_is_transparent(small_flight):
    frames, _, _ = _true_placement(small_flight)
    # Two frames far apart: the tiles between them see no frame.
    to_mosaic = {0: np.eye(3), 1: geometry.translation(2000.0, 0.0)}
    tiles = list(composite_tiles(frames, to_mosaic, (2320, 240), "multiband", Reporter(quiet=True), tile_side=256))
    empty = [tile for (x0, _, x1, _), tile in tiles if x0 >= 768 and x1 <= 1536]  # not even their margins reach a frame
    assert len(empty) == 3 and all((tile == 0).all() for tile in empty)
    assert tiles[0][1][..., 3].mean() > 200  # the first frame's tile is covered


@pytest.mark.parametrize("blend", ["feather", "none"])
def test_tiled_memory_follows_the_tile_not_the_canvas(small_flight, blend):
    frames = open_frames(small_flight, 800)
    # Frames spread along a canvas 40 tiles long: streaming its tiles must hold one tile's working set, whatever the canvas.
    to_mosaic = {i: geometry.translation(150.0 * i, 40.0 * (i % 2)) for i in range(len(frames.frames))}
    size = (150 * len(frames.frames) + 340, 300)
    tile_side = 64
    tracemalloc.start()
    covered = sum(int((tile[..., 3] > 0).sum()) for _, tile in composite_tiles(frames, to_mosaic, size, blend, Reporter(quiet=True), tile_side=tile_side))
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert covered > 0.8 * size[0] * size[1] * 240 / 300
    frame_bytes = 320 * 240 * 3 * 4  # one frame as float32 colour
    kept_frames = 320 * 240 * 3 * len(frames.frames)  # every decoded frame (uint8) fits the cache here
    assert peak < BYTES_PER_PIXEL[blend] * tile_side * tile_side + kept_frames + 4 * frame_bytes
    assert peak < 0.5 * BYTES_PER_PIXEL[blend] * size[0] * size[1]  # far less than blending the canvas whole


def test_the_canvas_limit_counts_only_what_is_held(small_flight):
    ref_from = {0: np.eye(3), 1: geometry.translation(60000.0, 0.0)}
    sizes = [(640, 480), (640, 480)]
    needed = 60640 * 480 * OUTPUT_BYTES_PER_PIXEL
    with pytest.raises(UdhError, match="--max-size .* or write a .tif"):
        plan_canvas(ref_from, sizes, "multiband", max_bytes=needed - 1)
    assert plan_canvas(ref_from, sizes, "multiband", max_bytes=needed - 1, assembled=False).size == (60640, 480)
    with pytest.raises(UdhError, match="homographies place sensibly"):  # a streamed canvas still has a sanity limit
        plan_canvas({0: np.eye(3), 1: geometry.translation(1e9, 1e3)}, sizes, "multiband", assembled=False)


@pytest.mark.parametrize("blend", ["feather", "none"])
def test_compositing_memory_is_the_canvas_plus_one_frame(small_flight, blend):
    frames = open_frames(small_flight, 800)
    # Spread the frames far apart on a large canvas: peak memory must follow the canvas, not frames x canvas.
    to_mosaic = {i: geometry.translation(150.0 * i, 40.0 * (i % 2)) for i in range(len(frames.frames))}
    size = (150 * len(frames.frames) + 340, 300)
    tracemalloc.start()
    out = composite(frames, to_mosaic, size, blend, Reporter(quiet=True))
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert out.shape == (300, size[0], 4) and out[..., 3].mean() > 100
    frame_bytes = 320 * 240 * 3 * 4  # one frame as float32 colour
    assert peak < BYTES_PER_PIXEL[blend] * size[0] * size[1] + 12 * frame_bytes


@pytest.mark.parametrize("blend, seam_finder", [("feather", None), ("multiband", None), ("none", None), ("multiband", "dp"), ("none", "graphcut")])
def test_every_blend_reproduces_the_ground_with_true_homographies(small_flight, blend, seam_finder):
    from udh_cli.mosaic.render.gains import exposure_gains
    from udh_cli.mosaic.render.seams import find_seams
    from udh_cli.mosaic.render.small import draw_small
    from udh_cli.simulate import simulate_flight

    frames = open_frames(small_flight, 800)
    truth = load_ground_truth(small_flight / "ground_truth.json")
    ground = simulate_flight(SMALL, seed=4)[1]
    to_ground = {f.index: truth["ground_from_frame"][f.name] for f in frames.frames}
    size = (ground.shape[1], ground.shape[0])
    gains = seams = None
    if seam_finder is not None:  # OpenCV's seams and per-channel gains, found on the part drawn small
        small = draw_small(frames, to_ground, 1.0, Reporter(quiet=True))
        gains, seams = exposure_gains("channels", small), find_seams(seam_finder, small)
        assert small.scale == 1.0 and len(seams.masks) == len(frames.frames)  # 320x240 frames are small already
    out = composite(frames, to_ground, size, blend, Reporter(quiet=True), gains=gains, seams=seams)
    covered = cv2.erode(out[..., 3], np.ones((9, 9), np.uint8)) > 0
    assert covered.mean() > 0.3
    mosaic_grey = cv2.cvtColor(out[..., :3], cv2.COLOR_BGR2GRAY)[covered].astype(np.float32)
    ground_grey = cv2.cvtColor(ground, cv2.COLOR_BGR2GRAY)[covered].astype(np.float32)
    assert np.corrcoef(mosaic_grey, ground_grey)[0, 1] > 0.9
    # The alpha channel is exactly the union of the frames' footprints (up to a pixel of edge).
    union = np.zeros(out.shape[:2], np.uint8)
    for f in frames.frames:
        union |= cv2.warpPerspective(np.full((f.size[1], f.size[0]), 255, np.uint8), to_ground[f.index], size, flags=cv2.INTER_NEAREST)
    kernel = np.ones((5, 5), np.uint8)
    assert (out[..., 3][cv2.erode(union, kernel) > 0] == 255).all()
    assert (out[..., 3][cv2.dilate(union, kernel) == 0] == 0).all()


def _seams_and_gains(frames, to_ground, exposure):
    from udh_cli.mosaic.render.gains import exposure_gains
    from udh_cli.mosaic.render.seams import find_seams
    from udh_cli.mosaic.render.small import draw_small

    small = draw_small(frames, to_ground, 1.0, Reporter(quiet=True))
    return exposure_gains(exposure, small), find_seams("dp", small)


@pytest.mark.parametrize("exposure", ["channels", "blocks"])
def test_a_frame_cut_to_what_it_owns_blends_as_the_whole_frame(small_flight, exposure, monkeypatch):
    import udh_cli.mosaic.render.composite as composite_module

    frames, to_ground, size = _true_placement(small_flight)
    gains, seams = _seams_and_gains(frames, to_ground, exposure)
    fed = []
    real = composite_module._warp
    monkeypatch.setattr(composite_module, "_warp", lambda image, h, box, *a: (image.ndim == 3 and fed.append(box)) or real(image, h, box, *a))
    monkeypatch.setattr(composite_module, "FEED_MARGIN", 10**6)
    whole = composite(frames, to_ground, size, "multiband", Reporter(quiet=True), gains=gains, seams=seams)
    whole_area = sum((x1 - x0) * (y1 - y0) for x0, y0, x1, y1 in fed)
    fed.clear()
    monkeypatch.setattr(composite_module, "FEED_MARGIN", 64)  # under the 320x240 frames' size on the canvas, so frames are cut
    cut = composite(frames, to_ground, size, "multiband", Reporter(quiet=True), gains=gains, seams=seams)
    cut_area = sum((x1 - x0) * (y1 - y0) for x0, y0, x1, y1 in fed)
    assert cut_area < 0.9 * whole_area  # the frames were cut
    assert (cut[..., 3] == whole[..., 3]).all()
    difference = np.abs(cut.astype(np.int16) - whole.astype(np.int16))[..., :3]
    # At half of FEED_MARGIN (5 bands reach about 128 px) nearly every pixel is still within 1 grey level.
    assert difference.max() <= 2 and (difference <= 1).mean() > 0.9999 and (difference == 0).mean() > 0.99


@pytest.mark.parametrize("gain", [np.array([0.8, 1.0, 1.37]), np.full((3, 4, 3), 1.2) * np.linspace(0.7, 1.3, 4)[None, :, None]])
def test_gains_scale_the_fed_pixels_as_the_float_path_truncates(gain):
    from udh_cli.mosaic.render.composite import _scaled
    from udh_cli.mosaic.render.gains import apply_gain

    warped = np.random.default_rng(0).integers(0, 256, (40, 60, 3), np.uint8)
    expected = np.clip(apply_gain(warped.astype(np.float32), gain), 0, 255).astype(np.int16)
    scaled = _scaled(warped, gain, (10, 20, 70, 60), (0, 0, 60, 40))
    assert scaled.dtype == np.int16 and scaled.min() >= 0 and scaled.max() == 255
    assert np.abs(scaled - expected).max() <= 1 and (scaled == expected).mean() > 0.999
    assert (_scaled(warped, None, (0, 0, 60, 40), (0, 0, 60, 40)) == warped).all()


def test_tiles_are_as_few_as_the_side_allows_of_even_sizes_on_the_blenders_grid():
    from udh_cli.mosaic.render.composite import TILE_ALIGN, tile_boxes

    tiles = tile_boxes(3297, 6425, 2048)  # copr's canvas: no thin last row (the plain grid's was 281 px)
    assert len(tiles) == 8 and {x1 - x0 for x0, _, x1, _ in tiles} <= {1664, 1633} and min(y1 - y0 for _, y0, _, y1 in tiles) >= 1500
    assert all(x0 % TILE_ALIGN == 0 and y0 % TILE_ALIGN == 0 for x0, y0, _, _ in tiles)
    assert all(x1 - x0 <= 2048 and y1 - y0 <= 2048 for x0, y0, x1, y1 in tiles)
    covered = np.zeros((6425, 3297), np.uint8)
    for x0, y0, x1, y1 in tiles:
        covered[y0:y1, x0:x1] += 1
    assert (covered == 1).all()  # every canvas pixel in exactly one tile
    assert tile_boxes(100, 50, 2048) == [(0, 0, 100, 50)]
