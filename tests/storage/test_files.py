"""Safe files: atomic writes leave the old file or the new one; appended logs survive a torn last line."""

from __future__ import annotations

import json

import pytest

from agsf_torch.storage.files import (
    append_line,
    atomic_open,
    json_text,
    read_json,
    read_json_lines,
    repair_json_lines,
    write_json,
    write_text,
)


def test_an_interrupted_atomic_write_leaves_the_old_file_and_no_temporary(tmp_path):
    path = write_text(tmp_path / "summary.json", "old")
    with pytest.raises(KeyboardInterrupt):
        with atomic_open(path, "w") as fh:
            fh.write("new, half written")
            raise KeyboardInterrupt
    assert path.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["summary.json"]
    write_json(path, {"a": 1})
    assert json.loads(path.read_text()) == {"a": 1}
    with pytest.raises(ValueError, match="mode must be 'wb' or 'w'"):
        with atomic_open(path, "a"):
            pass


def test_read_json_names_a_truncated_file(tmp_path):
    path = tmp_path / "experiment.json"
    path.write_text('{"kind": "run", "dig')
    with pytest.raises(ValueError, match=r"experiment marker .*experiment.json is corrupt"):
        read_json(path, "experiment marker")


def test_a_torn_last_line_is_skipped_with_a_warning_naming_the_file_and_repaired(tmp_path):
    path = tmp_path / "results.jsonl"
    append_line(path, json.dumps({"digest": "a"}))
    append_line(path, json.dumps({"digest": "b"}))
    with open(path, "a") as fh:
        fh.write('{"digest": "c", "par')  # killed between the two writes of a row
    with pytest.warns(RuntimeWarning, match=r"results.jsonl: skipped a torn last line"):
        assert read_json_lines(path) == [{"digest": "a"}, {"digest": "b"}]
    with pytest.warns(RuntimeWarning, match="removed a torn last line"):
        assert repair_json_lines(path) == [{"digest": "a"}, {"digest": "b"}]
    append_line(path, json.dumps({"digest": "c"}))
    assert path.read_text().splitlines() == ['{"digest": "a"}', '{"digest": "b"}', '{"digest": "c"}']


@pytest.mark.parametrize("tail", ["\n\n", "   ", ""])
def test_blank_lines_are_not_records(tmp_path, tail):
    path = tmp_path / "results.jsonl"
    path.write_text('{"digest": "a"}\n' + tail)
    assert read_json_lines(path) == [{"digest": "a"}]


def test_a_complete_last_record_without_its_newline_is_kept_and_terminated(tmp_path):
    path = tmp_path / "results.jsonl"
    path.write_text('{"digest": "a"}\n{"digest": "b"}')
    assert repair_json_lines(path) == [{"digest": "a"}, {"digest": "b"}]
    append_line(path, '{"digest": "c"}')
    assert [json.loads(x)["digest"] for x in path.read_text().splitlines()] == ["a", "b", "c"]


def test_a_corrupt_line_before_the_last_is_an_error_naming_file_and_line(tmp_path):
    path = tmp_path / "results.jsonl"
    path.write_text('{"digest": "a"}\n{"dig\n{"digest": "c"}\n')
    with pytest.raises(ValueError, match=r"results.jsonl: line 2 is not valid JSON"):
        read_json_lines(path)


def test_append_line_refuses_a_newline(tmp_path):
    with pytest.raises(ValueError, match="must not contain a newline"):
        append_line(tmp_path / "x.jsonl", "a\nb")
    assert not (tmp_path / "x.jsonl").exists()


def test_every_json_file_is_strict_json_with_null_for_undefined_numbers(tmp_path):
    """NaN and ±inf (also nested, and as NumPy floats) are written as null, which any JSON parser reads;
    Python's default would write the bare NaN that strict parsers refuse."""
    import numpy as np

    obj = {"a": float("nan"), "b": [1.0, float("inf"), (-float("inf"), 2)], "c": np.float64("nan"), "d": "NaN"}
    path = write_json(tmp_path / "x.json", obj)

    def refuse(token):
        raise ValueError(f"non-standard JSON constant {token}")

    back = json.loads(path.read_text(), parse_constant=refuse)
    assert back == {"a": None, "b": [1.0, None, [None, 2]], "c": None, "d": "NaN"}
    assert json.loads(json_text({"x": [float("nan")]}), parse_constant=refuse) == {"x": [None]}
