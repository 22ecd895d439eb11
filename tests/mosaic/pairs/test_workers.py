"""Pairs estimated in a process pool or on a Dask cluster give the same mosaic as in this process."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from udh_cli import geometry
from udh_cli.errors import UdhError
from udh_cli.estimators import Estimator
from udh_cli.mosaic import MosaicConfig, run_mosaic
from udh_cli.mosaic.pairs.types import Acceptance
from udh_cli.mosaic.pairs.workers import in_order, judge_opinions

from conftest import textured_image


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    from mosaic_flights import SMALL, make_flight

    folder = tmp_path_factory.mktemp("flight")
    make_flight(folder, SMALL, seed=4)
    return folder


@pytest.fixture(scope="module")
def local(flight, tmp_path_factory):
    return run_mosaic(flight, tmp_path_factory.mktemp("local") / "m.png", MosaicConfig(method="auto", batch_size=4))


def assert_same_pairs(report: dict, reference: dict) -> None:
    assert len(report["pairs"]) == len(reference["pairs"]) >= 10
    for pair, expected in zip(report["pairs"], reference["pairs"], strict=True):
        assert (pair["a"], pair["b"], pair["kind"], pair["status"]) == (expected["a"], expected["b"], expected["kind"], expected["status"])
        if expected["b_from_a"] is not None:
            np.testing.assert_allclose(pair["b_from_a"], expected["b_from_a"], rtol=0, atol=1e-9)
    for frame, expected in zip(report["frames"], reference["frames"], strict=True):
        np.testing.assert_allclose(frame["mosaic_from_frame"], expected["mosaic_from_frame"], rtol=0, atol=1e-9)


def test_a_pool_of_two_processes_gives_the_same_homographies(flight, local, tmp_path):
    report = run_mosaic(flight, tmp_path / "m.png", MosaicConfig(method="auto", batch_size=4, workers=2))
    assert_same_pairs(report, local)
    assert [p["method"] for p in report["pairs"]] == [p["method"] for p in local["pairs"]]
    assert any(p["method"] == "chain+ecc" for p in local["pairs"])  # loop pairs confirmed from the prediction, in the workers too
    assert report["summary"]["placed"] == report["summary"]["frames"]


@pytest.mark.slow
def test_a_dask_cluster_of_two_workers_gives_the_same_homographies(flight, local, tmp_path):
    distributed = pytest.importorskip("distributed")
    # ":0", a free port: with None the scheduler still serves HTTP, on 8787, which another run may hold
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
        report = run_mosaic(flight, tmp_path / "m.png", MosaicConfig(method="auto", batch_size=4, scheduler=cluster.scheduler_address))
    assert_same_pairs(report, local)


def test_a_pool_runs_the_fallback_inside_the_same_job_and_matches_this_process(flight, tmp_path):
    """ORB with a strict confidence floor leaves pairs doubted; SIFT answers them in the worker, as here (every loop
    pair asks ORB, none is confirmed from its prediction)."""
    config = MosaicConfig(method="orb", fallback="sift", min_confidence=0.6, batch_size=4, overlap_per_frame=1, confirm_loops=False)
    here = run_mosaic(flight, tmp_path / "here.png", config)
    pooled = run_mosaic(flight, tmp_path / "pool.png", MosaicConfig(**{**config.__dict__, "workers": 2}))
    assert sum(len(p["estimates"]) == 2 for p in here["pairs"]) >= 1  # the fallback ran
    assert_same_pairs(pooled, here)


class Fixed(Estimator):
    """Answers a fixed shift with a fixed confidence, and counts the pairs it was asked about."""

    verifies_itself = True  # the acceptance then judges by confidence alone

    def __init__(self, name: str, confidence: float):
        self.name, self.fixed_confidence, self.asked = name, confidence, 0

    def _estimate(self, pair):
        self.asked += 1
        return geometry.translation(3.0, 0.0), self.fixed_confidence, {}


def test_each_opinion_is_asked_only_about_the_pairs_every_earlier_one_left_doubted():
    image = textured_image(96, 128, seed=1)
    pairs = [(image, image)] * 3
    doubtful, also_doubtful, sure, never = Fixed("a", 0.1), Fixed("b", 0.15), Fixed("c", 0.9), Fixed("d", 0.9)
    attempts = judge_opinions([doubtful, also_doubtful, sure, never], Acceptance(min_confidence=0.2), pairs)
    assert [opinion.asked for opinion in (doubtful, also_doubtful, sure, never)] == [3, 3, 3, 0]
    for judged in attempts:
        assert [estimate.method for estimate, _, _ in judged] == ["a", "b", "c"]
        assert [doubt is None for _, _, doubt in judged] == [False, False, True]
        assert judged[0][2] == "confidence 0.10 < 0.2"


def test_an_unreachable_or_malformed_scheduler_and_no_workers_are_clear_errors(flight, tmp_path):
    pytest.importorskip("distributed")
    from udh_cli.mosaic.pairs.workers import DaskRunner, EstimatorSpec

    for address in ("tcp://127.0.0.1:9", "http://:abc"):
        with pytest.raises(UdhError, match="cannot reach the Dask scheduler"):
            DaskRunner(EstimatorSpec("sift"), address, timeout_s=1.0)
    with pytest.raises(UdhError, match="--workers 0"):
        run_mosaic(flight, tmp_path / "m.png", MosaicConfig(workers=0))
    assert list(tmp_path.iterdir()) == []


def test_jobs_come_back_in_submission_order_even_when_a_later_one_finishes_first():
    import threading
    from concurrent.futures import Future

    in_flight, most = [0], [0]

    def job(value):
        def start():
            in_flight[0] += 1
            most[0] = max(most[0], in_flight[0])
            done: Future = Future()
            # Later jobs finish sooner: job 0 takes longest.
            threading.Timer(0.01 * (7 - value), done.set_result, args=(value,)).start()
            return done
        return start

    seen = []
    for index, future in in_order([job(v) for v in range(7)], window=3):
        value = future.result()
        seen.append((index, value))
        in_flight[0] -= 1
    assert seen == [(i, i) for i in range(7)] and most[0] == 3


def test_workers_none_means_one_per_core_for_a_long_enough_flight(flight, local, tmp_path, monkeypatch):
    import udh_cli.mosaic.pairs.workers as workers

    assert 1 <= workers.available_cores() <= (workers.os.cpu_count() or 1)
    monkeypatch.setattr(workers, "available_cores", lambda: 8)
    assert workers.automatic_workers(workers.POOL_MIN_FRAMES - 1) == 1  # the pool's start would not pay
    assert workers.automatic_workers(workers.POOL_MIN_FRAMES) == workers.MAX_AUTO_WORKERS == 4
    monkeypatch.setattr(workers, "available_cores", lambda: 2)
    assert workers.automatic_workers(500) == 2
    report = run_mosaic(flight, tmp_path / "m.png", MosaicConfig(method="auto", batch_size=4, workers=None))
    assert report["config"]["workers"] == 1  # the test flight is short
    assert_same_pairs(report, local)


def test_a_script_without_the_main_guard_is_told_so_before_any_worker_starts(tmp_path, monkeypatch):
    """A spawned worker imports the main script again: without the guard it would run the mosaic once more and die,
    which the pool can only call "a worker process died"; the run refuses first, naming the guard."""
    import types

    from udh_cli.mosaic.pairs.workers import EstimatorSpec, PoolRunner, unguarded_script

    bare, guarded = tmp_path / "bare.py", tmp_path / "guarded.py"
    bare.write_text("from udh_cli.mosaic import run_mosaic\nrun_mosaic('frames', 'm.png')\n")
    guarded.write_text("def main():\n    pass\n\nif __name__ == '__main__':\n    main()\n")
    for script, expected in ((bare, str(bare)), (guarded, None)):
        monkeypatch.setitem(sys.modules, "__main__", types.SimpleNamespace(__file__=str(script)))
        assert unguarded_script() == expected
    monkeypatch.setitem(sys.modules, "__main__", types.SimpleNamespace())  # a notebook or an interactive session
    assert unguarded_script() is None
    package_main = types.SimpleNamespace(__file__=str(bare), __spec__=types.SimpleNamespace(name="tool.__main__"))
    monkeypatch.setitem(sys.modules, "__main__", package_main)  # `python -m tool`: multiprocessing does not import it again
    assert unguarded_script() is None
    monkeypatch.setitem(sys.modules, "__main__", types.SimpleNamespace(__file__=str(bare)))
    with pytest.raises(UdhError, match=r"workers=2 starts worker processes, which import .*bare.py again: put the call under "
                                       r"'if __name__ == \"__main__\":'"):
        PoolRunner(EstimatorSpec((("sift", {}),), None), 2)
