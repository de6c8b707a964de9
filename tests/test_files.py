"""Tests of rlpipe.pipelines.artifacts.files on real files in tmp_path."""

from __future__ import annotations

import json
import stat

import pytest

from rlpipe.pipelines.artifacts.files import (
    FileWriteError,
    atomic_path,
    remove_temporaries,
    write_bytes_atomic,
    write_json_atomic,
    write_text_atomic,
)


def mode(path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_atomic_path_moves_the_finished_file_into_place_readable(tmp_path):
    target = tmp_path / "video.mp4"
    with atomic_path(target, suffix=".mp4") as tmp:
        assert tmp.parent == tmp_path
        assert tmp.name.startswith(".video.mp4.") and tmp.suffix == ".mp4"  # a writer picks its format by it
        assert not target.exists()
        tmp.write_bytes(b"frames")
    assert target.read_bytes() == b"frames"
    assert mode(target) == 0o644  # mkstemp makes 0600; run files are readable like the rest
    assert [p.name for p in tmp_path.iterdir()] == ["video.mp4"]


def test_atomic_path_failure_keeps_the_old_file_and_leaves_no_temp(tmp_path):
    target = tmp_path / "summary.json"
    target.write_text("old\n")
    with pytest.raises(RuntimeError, match="writer died"), atomic_path(target) as tmp:
        tmp.write_text("half of the new")
        raise RuntimeError("writer died")
    assert target.read_text() == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["summary.json"]


def test_a_reader_of_the_old_file_keeps_reading_the_old_file(tmp_path):
    target = write_text_atomic(tmp_path / "policy.json", "old contents\n")
    with target.open() as reader:
        write_text_atomic(target, "new\n")
        assert reader.read() == "old contents\n"  # replaced, not rewritten in place
    assert target.read_text() == "new\n"


def test_write_helpers(tmp_path):
    assert write_bytes_atomic(tmp_path / "a.bin", b"\x00\x01").read_bytes() == b"\x00\x01"
    assert write_text_atomic(tmp_path / "a.md", "★ full\n").read_text(encoding="utf-8") == "★ full\n"
    path = write_json_atomic(tmp_path / "a.json", {"x": [1, 2], "y": float("nan"), "z": [float("-inf")]})
    text = path.read_text()
    assert text == json.dumps({"x": [1, 2], "y": None, "z": [None]}, indent=2) + "\n"  # strict JSON: no bare NaN
    assert mode(path) == 0o644
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin", "a.json", "a.md"]


def test_remove_temporaries_clears_what_a_killed_write_left(tmp_path):
    (tmp_path / "policy.pt2").write_bytes(b"the export")
    (tmp_path / ".policy.pt2.ab_cd123.pt2").write_bytes(b"half an export")
    (tmp_path / ".metrics.csv.x1y2z3w4").write_text("half a table")
    (tmp_path / ".hidden-by-the-user").write_text("not ours")
    removed = remove_temporaries(tmp_path, ["policy.pt2"])
    assert [p.name for p in removed] == [".policy.pt2.ab_cd123.pt2"]
    remove_temporaries(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == [".hidden-by-the-user", "policy.pt2"]


def test_a_refused_write_is_one_file_write_error_and_leaves_the_old_file(tmp_path):
    target = write_text_atomic(tmp_path / "summary.json", "old\n")
    with pytest.raises(FileWriteError, match="cannot write .*summary.json: No space left on device"):
        with atomic_path(target) as tmp, tmp.open("wb") as fh, open("/dev/full", "wb") as full:
            fh.write(b"new")
            full.write(b"x" * 100_000)  # a full disk, as the system reports it
            full.flush()
    assert target.read_text() == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["summary.json"]
