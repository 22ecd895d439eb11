"""udh_cli.files: outputs replaced only when udh wrote them; side files bounded and regular before they are read."""

from __future__ import annotations

import json
import os

import pytest

from udh_cli.errors import UdhError
from udh_cli.files import (MANIFEST_NAME, check_replaceable, read_side_file, read_side_text, write_file_set, write_output,
                           written_by_udh)

from conftest import run_main


def test_a_file_udh_wrote_is_replaced_and_recorded_with_its_size_and_digest(tmp_path):
    target = tmp_path / "results.md"
    write_output(target, b"first run\n")
    assert written_by_udh(target)
    write_output(target, b"second run, longer\n")  # no --overwrite needed: the manifest proves it is ours
    assert target.read_bytes() == b"second run, longer\n"
    entry = json.loads((tmp_path / MANIFEST_NAME).read_text())["files"]["results.md"]
    assert entry["size"] == len(b"second run, longer\n") and len(entry["sha256"]) == 64


@pytest.mark.parametrize("edit", [b"edited by hand\n", b"first run!\n"], ids=["other-size", "same-size"])
def test_a_file_changed_since_udh_wrote_it_needs_overwrite(tmp_path, edit):
    target = tmp_path / "results.md"
    write_output(target, b"first run\n")
    target.write_bytes(edit)
    with pytest.raises(UdhError, match="udh did not write it .* add --overwrite"):
        write_output(target, b"second run\n")
    assert target.read_bytes() == edit  # nothing lost
    write_output(target, b"second run\n", overwrite=True)
    assert target.read_bytes() == b"second run\n" and written_by_udh(target)


def test_a_users_file_is_refused_and_a_foreign_manifest_proves_nothing(tmp_path):
    target = tmp_path / "config.json"
    target.write_text('{"mine": 1}')
    (tmp_path / MANIFEST_NAME).write_text(json.dumps({"files": {"config.json": {"size": 11}}}))  # not our format
    with pytest.raises(UdhError, match=r"config.json: exists and udh did not write it"):
        check_replaceable(target)
    assert check_replaceable(tmp_path / "new.json") == tmp_path / "new.json"


def test_the_manifest_forgets_removed_files(tmp_path):
    write_output(tmp_path / "a.txt", b"a")
    write_output(tmp_path / "b.txt", b"b")
    (tmp_path / "a.txt").unlink()
    write_output(tmp_path / "b.txt", b"bb")
    assert sorted(json.loads((tmp_path / MANIFEST_NAME).read_text())["files"]) == ["b.txt"]


def test_side_files_are_read_when_regular_and_small(tmp_path):
    path = tmp_path / "gcp.txt"
    path.write_bytes(b"\xef\xbb\xbfEPSG:32611\n1 2 3\n")
    assert read_side_text(path, "--gcp") == "EPSG:32611\n1 2 3\n"  # the byte-order mark is not part of the text
    with pytest.raises(UdhError, match="--gcp .*: 1.0 MiB, more than the 1000 bytes"):
        path.write_bytes(b"x" * 2**20)
        read_side_file(path, "--gcp", limit=1000)
    with pytest.raises(UdhError, match="--camera .*: no such file"):
        read_side_file(tmp_path / "missing.json", "--camera")
    with pytest.raises(UdhError, match="--camera .*: is a folder"):
        read_side_file(tmp_path, "--camera")
    path.write_bytes(b"\xff\xfe not utf-8")
    with pytest.raises(UdhError, match="not UTF-8 text"):
        read_side_text(path, "--gcp")


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs here")
def test_a_fifo_without_a_writer_and_a_device_are_refused_at_once(tmp_path):
    fifo = tmp_path / "cameras.json"
    os.mkfifo(fifo)
    with pytest.raises(UdhError, match="--camera .*: not a regular file"):
        read_side_file(fifo, "--camera")  # would block for ever if it waited for a writer
    if os.path.exists("/dev/zero"):
        with pytest.raises(UdhError, match="--gt /dev/zero: not a regular file"):
            read_side_file("/dev/zero", "--gt")


def test_a_second_bench_into_the_same_folder_replaces_its_own_results(tmp_path, pool, monkeypatch, capfd):
    out = tmp_path / "b"
    args = ["bench", "synthetic", "--images", str(pool), "--n", "2", "--rho", "8", "-m", "identity", "--mode", "patch", "--no-plots",
            "--out", str(out), "--save-pairs", str(tmp_path / "p.npz")]
    for seed in ("0", "1"):
        code, _, err = run_main(monkeypatch, capfd, *args, "--seed", seed)
        assert code == 0, err
    assert json.loads((out / "results.json").read_text())["config"]["seed"] == 1
    (out / "results.md").write_text("my notes\n")
    code, _, err = run_main(monkeypatch, capfd, *args)
    assert code == 1 and "results.md: exists and udh did not write it" in err and (out / "results.md").read_text() == "my notes\n"
    code, _, err = run_main(monkeypatch, capfd, *args, "--overwrite")
    assert code == 0, err
    assert written_by_udh(out / "results.md") and written_by_udh(tmp_path / "p.npz")


def test_a_gcp_file_with_a_byte_order_mark_reads_its_crs(tmp_path):
    pytest.importorskip("pyproj")
    from udh_cli.mosaic.georef.gcp import read_gcp_file

    path = tmp_path / "gcp_list.txt"
    path.write_bytes("EPSG:32611\n500000 4100000 10 5 5 a.jpg g1\n500100 4100000 10 9 5 b.jpg g2\n".encode("utf-8-sig"))
    gcps = read_gcp_file(path)
    assert gcps.epsg == 32611 and [o.x for o in gcps.observations] == [500000.0, 500100.0]


def test_a_set_is_written_all_or_none(tmp_path, monkeypatch):
    from udh_cli import files

    write_file_set(tmp_path, {"results.md": b"first\n", "results.json": b"{}\n"})
    real_fsync, calls = os.fsync, []

    def full_disk_on_the_second(fd):
        calls.append(fd)
        if len(calls) == 2:
            raise OSError(28, "No space left on device")
        real_fsync(fd)

    monkeypatch.setattr(files.os, "fsync", full_disk_on_the_second)
    with pytest.raises(UdhError, match="No space left on device.*nothing was replaced"):
        write_file_set(tmp_path, {"results.md": b"second\n", "results.json": b'{"second": 1}\n'})
    assert (tmp_path / "results.md").read_bytes() == b"first\n" and (tmp_path / "results.json").read_bytes() == b"{}\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == [MANIFEST_NAME, "results.json", "results.md"]  # no temporary left


def test_a_set_interrupted_while_staging_leaves_the_earlier_set_and_no_temporary(tmp_path, monkeypatch):
    from udh_cli import files

    write_file_set(tmp_path, {"results.md": b"first\n", "results.json": b"{}\n"})
    created, calls = files.create_new, []

    def interrupted_on_the_second(path):
        calls.append(path)
        descriptor = created(path)
        if len(calls) == 2:  # just created, as Ctrl-C or SIGTERM would find it
            os.close(descriptor)
            raise KeyboardInterrupt
        return descriptor

    monkeypatch.setattr(files, "create_new", interrupted_on_the_second)
    with pytest.raises(KeyboardInterrupt):
        write_file_set(tmp_path, {"results.md": b"second\n", "results.json": b'{"second": 1}\n'})
    assert (tmp_path / "results.md").read_bytes() == b"first\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == [MANIFEST_NAME, "results.json", "results.md"]
