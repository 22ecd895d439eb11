"""Fuzzing what outlives a run: workers and temporary folders after a SIGKILL, and a cluster that never answers.

Each case starts the real thing (a pool of workers, ``udh mosaic --follow``) in a child process, kills it with
SIGKILL, and checks that every process it started ends on its own and that the next run removes its leftovers.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mosaic_flights import SMALL, make_flight
from udh_cli.processes import remove_dead_runs_folders, run_temp_folder

pytestmark = pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads the process table in /proc")
ENV = dict(os.environ, OMP_NUM_THREADS="1", COLUMNS="200", PYTHONPATH=os.pathsep.join([str(Path(__file__).parents[1]), os.environ.get("PYTHONPATH", "")]))
WAIT_S = 60  # a generous bound for a process to start or to end; the test never measures it


def _state(pid: int) -> str | None:
    """The process's state letter from /proc (``Z`` for a zombie), None when it is gone."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return None


def _running(pid: int) -> bool:
    return _state(pid) not in (None, "Z", "X")


def _descendants(pid: int) -> set[int]:
    """Every live process below ``pid`` in the process tree."""
    parents = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                parents[int(entry.name)] = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
    found, frontier = set(), {pid}
    while frontier:
        frontier = {child for child, parent in parents.items() if parent in frontier and child not in found}
        found |= frontier
    return {child for child in found if _running(child)}


def _wait_for(condition, what: str) -> None:
    deadline = time.monotonic() + WAIT_S
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.05)


def _kill_and_check_all_end(process: subprocess.Popen, children: set[int]) -> None:
    """SIGKILL ``process``; every one of ``children`` must end without being told."""
    process.kill()
    process.wait(timeout=WAIT_S)
    try:
        _wait_for(lambda: not any(_running(child) for child in children), f"still running after the parent's SIGKILL: {children}")
    finally:
        for child in children:  # never leave one behind, even when the test fails
            if _running(child):
                os.kill(child, signal.SIGKILL)


POOL_SCRIPT = """
import json, os, time
from multiprocessing import resource_tracker
from udh_cli.mosaic.pairs.workers import EstimatorSpec, PoolRunner
runner = PoolRunner(EstimatorSpec((("sift", {}),)), 2)
busy = [runner.pool.submit(time.sleep, 600) for _ in range(2)]
while len(runner.pool._processes) < 2:
    time.sleep(0.05)
print(json.dumps({"workers": list(runner.pool._processes), "tracker": resource_tracker._resource_tracker._pid}), flush=True)
time.sleep(600)
"""


def test_a_killed_runs_pool_workers_and_resource_tracker_end_with_it():
    process = subprocess.Popen([sys.executable, "-c", POOL_SCRIPT], stdout=subprocess.PIPE, text=True, env=ENV)
    try:
        started = json.loads(process.stdout.readline())
    except ValueError:
        process.kill()
        raise
    children = {*started["workers"], started["tracker"]}
    assert all(_running(child) for child in children) and children <= _descendants(process.pid)
    _kill_and_check_all_end(process, children)


def test_a_killed_live_runs_refresh_process_ends_and_the_next_run_removes_its_folder(tmp_path):
    frames, out = tmp_path / "frames", tmp_path / "out"
    make_flight(frames, SMALL, seed=3)
    out.mkdir()
    args = [sys.executable, "-m", "udh_cli", "mosaic", str(frames), "-o", str(out / "m.png"), "-m", "sift", "--follow",
            "--refresh-every", "2", "--idle-timeout", "600", "--quiet"]
    process = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=ENV)
    try:  # the refresh process and the resource tracker are up, and the staging folder is there
        _wait_for(lambda: len(_descendants(process.pid)) >= 2 and any(out.glob(".udh-follow-*")) or process.poll() is not None,
                  "the live run never started its refresh process")
    except AssertionError:
        process.kill()
        raise
    assert process.poll() is None, process.stderr.read()
    _kill_and_check_all_end(process, _descendants(process.pid))
    left = list(out.glob(".udh-follow-*"))
    assert len(left) == 1
    alive = run_temp_folder(out, ".udh-follow-")  # this test's own: a live run's folder, which must stay
    try:
        (frames / "DONE").write_text("")
        rerun = subprocess.run(args, capture_output=True, text=True, env=ENV, timeout=300)
        assert rerun.returncode == 0, rerun.stderr
        assert not left[0].exists() and alive.is_dir()
        assert sorted(p.name for p in out.glob(".udh-follow-*")) == [alive.name]
    finally:
        alive.rmdir()


def test_only_folders_of_dead_processes_on_this_host_are_removed(tmp_path):
    mine = run_temp_folder(tmp_path, ".udh-x-")
    dead_pid = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True).stdout.strip()
    host = mine.name.split("-")[3]
    dead = tmp_path / f".udh-x-{dead_pid}-{host}-abc"
    other_host = tmp_path / f".udh-x-{dead_pid}-{'0' * 8 if host != '0' * 8 else '1' * 8}-abc"
    users = tmp_path / f".udh-x-{dead_pid}-mine"
    for folder in (dead, other_host, users):
        folder.mkdir()
    (dead / "link.jpg").symlink_to(tmp_path / "nowhere.jpg")
    assert remove_dead_runs_folders(tmp_path, ".udh-x-") == [dead]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([mine.name, other_host.name, users.name])


class _Server:
    """A local TCP server on a thread that accepts every connection and then does ``behaviour(connection)``."""

    def __init__(self, behaviour):
        import socket
        import threading

        self.socket = socket.create_server(("127.0.0.1", 0))
        self.stop = threading.Event()
        self.behaviour = behaviour
        self.thread = threading.Thread(target=self.serve, daemon=True)
        self.thread.start()
        self.address = f"tcp://127.0.0.1:{self.socket.getsockname()[1]}"

    def serve(self) -> None:
        self.socket.settimeout(0.1)
        while not self.stop.is_set():
            try:
                connection, _ = self.socket.accept()
            except OSError:
                continue
            with connection:
                self.behaviour(connection, self.stop)

    def close(self) -> None:
        self.stop.set()
        self.thread.join()
        self.socket.close()


def _silent(connection, stop) -> None:
    stop.wait()


def _http(connection, stop) -> None:
    connection.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n")
    stop.wait()


def _dripping(connection, stop) -> None:
    while not stop.wait(0.05):
        try:
            connection.sendall(b"\x00")
        except OSError:
            return


@pytest.mark.parametrize("behaviour", [_silent, _http, _dripping], ids=["silent", "http", "dripping"])
def test_a_scheduler_that_never_answers_is_a_one_line_error_within_the_timeout(behaviour):
    pytest.importorskip("distributed")
    from udh_cli.errors import UdhError
    from udh_cli.mosaic.pairs.workers import DaskRunner, EstimatorSpec

    server = _Server(behaviour)
    try:
        with pytest.raises(UdhError, match="cannot reach the Dask scheduler") as refused:
            DaskRunner(EstimatorSpec((("sift", {}),)), server.address, timeout_s=1.0)
    finally:
        server.close()
    assert "\n" not in str(refused.value) and server.address in str(refused.value)


def test_a_staged_folder_left_by_a_killed_run_is_removed_by_the_next_one(tmp_path):
    from udh_cli.files import staged_folder

    dead_pid = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True).stdout.strip()
    live = run_temp_folder(tmp_path, ".flight.", ".staged")  # this process's: a run still writing
    host = live.name.split("-")[1]
    dead = tmp_path / f".flight.{dead_pid}-{host}-abcd.staged"
    dead.mkdir()
    (dead / "frame_000.jpg").write_bytes(b"half a flight")
    with staged_folder(tmp_path / "flight") as staging:
        (staging / "frame_000.jpg").write_bytes(b"a whole flight")
    assert not dead.exists() and live.is_dir()
    assert (tmp_path / "flight" / "frame_000.jpg").read_bytes() == b"a whole flight"
    live.rmdir()


def test_the_handshake_connects_with_the_tls_settings_of_dasks_config_as_client_does(monkeypatch):
    pytest.importorskip("distributed")
    import dask
    import distributed.comm
    from distributed.security import Security

    from udh_cli.mosaic.pairs.workers import _handshake

    seen: list[dict] = []

    class Comm:
        async def close(self):
            pass

    async def connect(address, timeout=None, **connection_args):
        seen.append({"address": address, **connection_args})
        return Comm()

    monkeypatch.setattr(distributed.comm, "connect", connect)
    with dask.config.set({"distributed.comm.require-encryption": True}):
        _handshake("tls://scheduler.example:8786", 1.0)
        expected = Security().get_connection_args("client")  # what Client passes, from the same config
    assert seen == [{"address": "tls://scheduler.example:8786", **expected}] and expected["require_encryption"] is True


def test_a_folder_of_another_container_sharing_the_host_name_is_kept_though_its_pid_is_dead_here(tmp_path, monkeypatch):
    from udh_cli import processes
    from udh_cli.files import staged_folder

    if not processes._pid_namespace():
        pytest.skip("no pid namespace to tell containers apart here")
    dead_pid = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True).stdout.strip()
    with monkeypatch.context() as other_container:  # same host name and boot, its own pid namespace (Docker --network host)
        other_container.setattr(processes.os, "readlink", lambda path: "pid:[4026599999]")
        theirs = processes._host_tag()
    with monkeypatch.context() as after_a_reboot:
        after_a_reboot.setattr(processes, "_boot_id", lambda: "another boot")
        rebooted = processes._host_tag()
    ours = processes._host_tag()
    assert len({theirs, rebooted, ours}) == 3
    other = tmp_path / f".flight.{dead_pid}-{theirs}-abcd.staged"  # a live run's there: its pid means nothing here
    dead = tmp_path / f".flight.{dead_pid}-{ours}-abcd.staged"
    other.mkdir()
    dead.mkdir()
    with staged_folder(tmp_path / "flight") as staging:
        (staging / "frame_000.jpg").write_bytes(b"a whole flight")
    assert other.is_dir() and not dead.exists()
