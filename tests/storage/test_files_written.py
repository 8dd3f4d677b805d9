"""files_written counts what this process put into place: whole files and appended lines, never a failed write."""

from __future__ import annotations

import pytest

from agsf_torch.storage.files import append_line, atomic_open, files_written, write_json, write_text


def test_whole_files_and_lines_are_counted_and_a_failed_write_is_not(tmp_path):
    start = files_written()
    write_text(tmp_path / "a.txt", "a")
    write_json(tmp_path / "b.json", {"b": 1})
    append_line(tmp_path / "c.jsonl", "{}")
    assert files_written() == start + 3
    with pytest.raises(RuntimeError), atomic_open(tmp_path / "d.bin") as fh:
        fh.write(b"half")
        raise RuntimeError("interrupted")
    with pytest.raises(ValueError):
        append_line(tmp_path / "c.jsonl", "two\nlines")
    assert files_written() == start + 3 and not (tmp_path / "d.bin").exists()
