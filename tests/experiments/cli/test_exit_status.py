"""The ``agsf`` command's exit status tells a refusal (2: nothing was written) from a failure after work was written
(3, the I/O status), whatever the file error: a permission denied halfway through a run is not a refused input."""

from __future__ import annotations

import errno
import io
from contextlib import redirect_stderr, redirect_stdout

import pytest

from agsf_torch.experiments.cli import main as cli


def _agsf(argv: list[str]) -> tuple[int, str]:
    """``(exit code, stderr)`` of ``agsf argv``."""
    err = io.StringIO()
    with redirect_stdout(io.StringIO()), redirect_stderr(err):
        code = cli.main(argv)
    return code, err.getvalue()


def _denied(path) -> OSError:
    return PermissionError(errno.EACCES, "Permission denied", str(path))


@pytest.mark.parametrize("code", [errno.EACCES, errno.EPERM, errno.ENOENT])
def test_a_file_error_after_work_was_written_exits_3_naming_the_file(tmp_path, monkeypatch, code):
    """``simulate`` has written its ``experiment.json`` when its recording cannot be written."""
    from agsf_torch.attitude import recordings

    def fail(self, path):
        raise OSError(code, "cannot write", str(path))

    monkeypatch.setattr(recordings.Recording, "save", fail)
    out = tmp_path / "s"
    status, err = _agsf(["simulate", "--runs", "2", "--steps", "3", "--quiet", "--out", str(out)])
    assert status == cli.EXIT_IO_FAILURE == 3
    assert err.count("\n") == 1 and err.startswith(f"agsf: I/O failure ({out / 'recording.npz'}): cannot write")
    assert (out / "experiment.json").is_file()


def test_a_permission_denied_before_anything_is_written_is_a_refusal(tmp_path, monkeypatch):
    """The output folder cannot be claimed: nothing was written, so the command is refused (2) and leaves no folder."""
    from agsf_torch.experiments.run import outputs

    monkeypatch.setattr(outputs, "write_json", lambda path, obj, **kwargs: (_ for _ in ()).throw(_denied(path)))
    out = tmp_path / "s"
    status, err = _agsf(["simulate", "--runs", "2", "--steps", "3", "--quiet", "--out", str(out)])
    assert status == 2 and err.startswith("agsf: error: ") and "experiment.json" in err
    assert not out.exists()


def test_a_permission_denied_reading_an_input_file_is_a_refusal(tmp_path):
    """A configuration file that is not readable (here: a folder) is refused before anything is written."""
    (tmp_path / "conf.toml").mkdir()
    status, err = _agsf(["run", str(tmp_path / "conf.toml"), "--quiet", "--out", str(tmp_path / "r")])
    assert status == 2 and err.startswith("agsf: error: ")
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("jobs", ["1", "3"])
def test_a_case_denied_its_folder_after_the_run_began_exits_3(tmp_path, monkeypatch, jobs):
    """``agsf reproduce`` rerun over a folder whose case folder it may not write: the run had begun (its
    ``experiment.json`` rewritten, the other cases run), so the status is the I/O failure's, in this process or in
    a case's forked one."""
    from agsf_torch.experiments.run.worker_pool import fork_available
    from agsf_torch.experiments.studies import reproduce

    if jobs != "1" and not fork_available():
        pytest.skip("cases side by side need fork (Linux)")

    def denied(cfg, out, **kwargs):
        raise _denied(out / "summary.json")

    monkeypatch.setattr(reproduce, "run_experiment", denied)
    monkeypatch.setattr(reproduce, "make_filters", lambda cfg: None)
    out = tmp_path / "rep"
    argv = [
        "reproduce",
        "--case",
        "all",
        "--jobs",
        jobs,
        "--runs",
        "2",
        "--duration",
        "1",
        "--quiet",
        "--out",
        str(out),
    ]
    status, err = _agsf(argv + ["--set", "compile=false", "--set", "compile_fused=false"])
    assert status == 3 and err.startswith(f"agsf: I/O failure ({out / 'case1' / 'summary.json'}): Permission denied")
