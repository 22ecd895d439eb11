"""conftest's :class:`SessionCache`: parallel workers that need the same folder build it once, and a failed build
leaves nothing behind."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from conftest import SessionCache


def test_two_workers_asking_for_one_folder_at_once_build_it_once_and_both_get_it(tmp_path):
    root = tmp_path / "shared"
    root.mkdir()
    builds = []

    def build(folder: Path) -> None:
        builds.append(folder)
        time.sleep(0.2)  # the other worker asks while this one is still writing
        (folder / "frame.txt").write_text("whole")

    workers = [SessionCache(root), SessionCache(root)]  # one per xdist worker: nothing shared but the folder
    threads = [threading.Thread(target=cache.copy_into, args=(tmp_path / f"copy{i}", ("flight", 3), build))
               for i, cache in enumerate(workers)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(builds) == 1
    assert [(tmp_path / f"copy{i}" / "frame.txt").read_text() for i in range(2)] == ["whole", "whole"]
    assert sorted(p.name for p in root.iterdir() if not p.name.endswith(".lock")) == [workers[0].built[("flight", 3)].name]


def test_a_build_that_fails_leaves_no_folder_and_the_next_caller_builds_again(tmp_path):
    cache = SessionCache(tmp_path)

    def broken(folder: Path) -> None:
        (folder / "half.txt").write_text("half")
        raise RuntimeError("the simulator failed")

    with pytest.raises(RuntimeError, match="the simulator failed"):
        cache.copy_into(tmp_path / "copy", "key", broken)
    assert [p.name for p in tmp_path.iterdir() if not p.name.endswith(".lock")] == []
    cache.copy_into(tmp_path / "copy", "key", lambda folder: (folder / "whole.txt").write_text("whole"))
    assert sorted(p.name for p in (tmp_path / "copy").iterdir()) == ["whole.txt"]
