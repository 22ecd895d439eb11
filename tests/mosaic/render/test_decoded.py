"""The decoded-frame cache shared by the small copies and the tiles."""

from __future__ import annotations

import numpy as np
import pytest

from udh_cli import geometry
from udh_cli.mosaic.inputs.frames import FrameSet, open_frames
from udh_cli.mosaic.render.composite import composite
from udh_cli.mosaic.render.decoded import DecodedFrames
from udh_cli.mosaic.render.small import draw_small
from udh_cli.mosaic.report import Reporter
from udh_cli.simulate import load_ground_truth

from mosaic_flights import SMALL, make_flight


@pytest.fixture(scope="module")
def placed_flight(tmp_path_factory):
    folder = tmp_path_factory.mktemp("decoded")
    make_flight(folder, SMALL, seed=5)
    frames = open_frames(folder, 800)
    truth = load_ground_truth(folder / "ground_truth.json")
    to_ground = {f.index: np.asarray(truth["ground_from_frame"][f.name]) for f in frames.frames}
    corners = np.concatenate([geometry.transform_points(h, geometry.image_corners(*frames.frames[i].size)) for i, h in to_ground.items()])
    return frames, to_ground, tuple(int(v) + 1 for v in np.ceil(corners.max(0)))


def _counting_reads(monkeypatch) -> list[int]:
    read = []
    real = FrameSet.full_images

    def full_images(self, indices):
        for index, image in real(self, indices):
            read.append(index)
            yield index, image

    monkeypatch.setattr(FrameSet, "full_images", full_images)
    return read


def test_the_small_copies_and_the_tiles_decode_each_frame_once(placed_flight, monkeypatch):
    frames, to_ground, size = placed_flight
    alone = composite(frames, to_ground, size, "multiband", Reporter(quiet=True), tile_side=128)
    read = _counting_reads(monkeypatch)
    decoded = DecodedFrames(frames)
    small = draw_small(frames, to_ground, 1.0, Reporter(quiet=True), decoded=decoded)
    shared = composite(frames, to_ground, size, "multiband", Reporter(quiet=True), tile_side=128, decoded=decoded)
    assert sorted(read) == sorted(to_ground) == small.indices  # every frame read once, for both stages
    assert (shared == alone).all()


def test_a_cache_over_its_budget_drops_the_least_recently_used(placed_flight, monkeypatch):
    frames, _, _ = placed_flight
    one_frame = 320 * 240 * 3
    decoded = DecodedFrames(frames, budget_bytes=2 * one_frame)
    read = _counting_reads(monkeypatch)
    assert [i for i, _ in decoded.get([0, 1, 2])] == [0, 1, 2]
    assert list(decoded.kept) == [1, 2] and decoded.kept_bytes == 2 * one_frame
    assert [i for i, _ in decoded.get([1, 0])] == [0, 1]
    assert read == [0, 1, 2, 0]  # 1 was kept, 0 was read again


def test_frames_decoded_before_are_not_read_again(placed_flight, monkeypatch):
    frames, to_ground, size = placed_flight
    alone = composite(frames, to_ground, size, "multiband", Reporter(quiet=True), tile_side=128)
    first_two = dict(frames.full_images([0, 1]))
    read = _counting_reads(monkeypatch)
    decoded = DecodedFrames(frames, already=first_two)
    given = composite(frames, to_ground, size, "multiband", Reporter(quiet=True), tile_side=128, decoded=decoded)
    assert sorted(set(read)) == sorted(set(to_ground) - {0, 1})
    assert np.array_equal(given, alone)


def test_a_part_takes_its_kept_frames_in_a_budget_less_what_the_other_parts_still_hold(placed_flight):
    from udh_cli.mosaic.render.decoded import DECODED_CACHE_BYTES

    folder = placed_flight[0].source
    frames = open_frames(folder, 800, keep_decoded_bytes=DECODED_CACHE_BYTES)
    one_frame = 320 * 240 * 3
    assert frames.decoded_bytes() == len(frames.frames) * one_frame
    decoded = DecodedFrames.taken_from(frames, [0, 1, 2])
    assert list(decoded.kept) == [0, 1, 2] and sorted(frames.decoded_while_reading) == list(range(3, len(frames.frames)))
    assert decoded.budget_bytes + frames.decoded_bytes() == DECODED_CACHE_BYTES  # the two together stay in one budget
    frames.drop_decoded([3])
    assert list(frames.decoded_while_reading) == [3]
