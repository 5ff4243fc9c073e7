"""Atomic writes: whole files only, the usual permissions, the process umask left alone."""

from __future__ import annotations

import os
import stat
import threading
from pathlib import Path

import pytest

from reachplan.imaging.files import atomic_write, atomic_write_bytes, atomic_write_json


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


@pytest.mark.skipif(os.name != "posix", reason="POSIX permissions")
def test_new_file_gets_0666_less_the_umask_and_the_umask_is_unchanged(tmp_path: Path) -> None:
    old = os.umask(0o027)
    try:
        atomic_write_bytes(tmp_path / "a" / "f.bin", b"x")  # the folder is created
        assert _mode(tmp_path / "a" / "f.bin") == 0o640
        assert os.umask(0o027) == 0o027  # nothing changed it behind our back
    finally:
        os.umask(old)


def test_replaces_whole_and_leaves_no_temporary_file(tmp_path: Path) -> None:
    path = tmp_path / "plan.json"
    path.write_text("old")
    atomic_write_json(path, {"a": 1})
    assert path.read_text(encoding="utf-8") == '{\n  "a": 1\n}\n'
    assert [p.name for p in tmp_path.iterdir()] == ["plan.json"]


def test_a_failing_writer_keeps_the_old_file(tmp_path: Path) -> None:
    path = tmp_path / "f.txt"
    path.write_text("old")

    def boom(f: object) -> None:
        raise RuntimeError("disk on fire")

    with pytest.raises(RuntimeError, match="disk on fire"):
        atomic_write(path, boom)
    assert path.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["f.txt"]


def test_threads_writing_side_by_side_each_get_their_file(tmp_path: Path) -> None:
    def work(i: int) -> None:
        for k in range(20):
            atomic_write_bytes(tmp_path / f"f{i}.bin", bytes([i]) * (k + 1))

    threads = [threading.Thread(target=work, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"f{i}.bin" for i in range(8)]
    assert all((tmp_path / f"f{i}.bin").read_bytes() == bytes([i]) * 20 for i in range(8))


def test_a_batch_replaces_every_file_whole_and_a_failure_mid_batch_leaves_no_temporary_file(tmp_path: Path) -> None:
    from reachplan.imaging.files import atomic_write_files

    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "a.dcm").write_bytes(b"old")
    atomic_write_files([(tmp_path / "s" / f"{n}.dcm", n.encode() * 1000) for n in "abc"])
    assert sorted(p.name for p in (tmp_path / "s").iterdir()) == ["a.dcm", "b.dcm", "c.dcm"]
    assert (tmp_path / "s" / "a.dcm").read_bytes() == b"a" * 1000

    def files() -> object:
        yield tmp_path / "s" / "a.dcm", b"new"
        raise RuntimeError("the encoder failed")

    with pytest.raises(RuntimeError, match="encoder failed"):
        atomic_write_files(files())  # type: ignore[arg-type]
    assert (tmp_path / "s" / "a.dcm").read_bytes() == b"a" * 1000  # nothing was renamed: the old file stays
    assert sorted(p.name for p in (tmp_path / "s").iterdir()) == ["a.dcm", "b.dcm", "c.dcm"]
