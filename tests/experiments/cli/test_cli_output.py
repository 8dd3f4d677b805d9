"""What the ``agsf`` command prints: help for every argument, a TensorBoard command that runs,
the sweep's results table, the valid keys of a bad ``--set``, and long steps announced on stderr."""

from __future__ import annotations

import argparse
import io
import logging
import os
import shlex
import sys
import warnings
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import pytest

from agsf_torch.experiments.cli import main as cli
from agsf_torch.experiments.sweep import results_table
from agsf_torch.storage.files import read_json_lines
from tests.helpers import TINY_CLI

TINY = TINY_CLI


def _agsf(argv: list[str]) -> tuple[int, str, str]:
    """``(exit code, stdout, stderr)`` of ``agsf argv``."""
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        try:
            code = cli.main(argv)
        except SystemExit as exc:  # argparse
            code = exc.code
    return code, out.getvalue(), err.getvalue()


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    raise AssertionError("agsf has no subcommands")


def test_every_argument_of_every_subcommand_has_help():
    subcommands = _subparsers(cli.build_parser())
    assert {"run", "reproduce", "sweep", "simulate", "soak", "learn", "diagnose", "adaptation", "bench"} <= set(
        subcommands
    )
    missing = [
        f"agsf {name} {action.option_strings[0] if action.option_strings else action.dest}"
        for name, sub in subcommands.items()
        for action in sub._actions
        if not isinstance(action, argparse._HelpAction) and not (action.help or "").strip()
    ]
    assert missing == []


def test_tensorboard_command_uses_the_executable_next_to_python(tmp_path, monkeypatch):
    bin_dir = tmp_path / "env dir" / "bin"
    bin_dir.mkdir(parents=True)
    (bin_dir / "python").write_text("")
    (bin_dir / "tensorboard").write_text("")
    monkeypatch.setattr(sys, "executable", str(bin_dir / "python"))
    command = cli.tensorboard_command("runs/x y")
    assert shlex.split(command) == [str(bin_dir / "tensorboard"), "--logdir", "runs/x y"]


def test_tensorboard_command_falls_back_to_the_module(tmp_path, monkeypatch):
    (tmp_path / "python").write_text("")
    monkeypatch.setattr(sys, "executable", str(tmp_path / "python"))
    assert shlex.split(cli.tensorboard_command("out")) == [
        str(tmp_path / "python"),
        "-m",
        "tensorboard.main",
        "--logdir",
        "out",
    ]


def test_tensorboard_command_of_this_environment_runs():
    program = shlex.split(cli.tensorboard_command("out"))[0]
    assert Path(program).is_file() and os.access(program, os.X_OK)


def test_run_prints_a_tensorboard_command_that_names_its_executable(tmp_path):
    out = tmp_path / "run"
    code, stdout, _ = _agsf(["run", "case1", *TINY, "--out", str(out)])
    assert code == 0
    assert f"TensorBoard: {cli.tensorboard_command(out)}" in stdout.splitlines()
    assert "tensorboard --logdir" not in stdout.replace(cli.tensorboard_command(out), "")


def test_sweep_prints_its_results_table_and_writes_results_md(tmp_path):
    out = tmp_path / "sweep"
    argv = [
        "sweep",
        "case1",
        *TINY,
        "--set",
        'filters=["EKF", "GSF"]',
        "--set",
        "duration=1.2",
        "--grid",
        "seed=3,5",
        "--out",
        str(out),
    ]
    code, stdout, _ = _agsf(argv)
    assert code == 0
    rows = read_json_lines(out / "results.jsonl")
    table = results_table(rows)
    assert (out / "results.md").read_text() == table + "\n"
    assert table in stdout
    assert f"TensorBoard (hparams): {cli.tensorboard_command(out)}" in stdout.splitlines()
    lines = table.split("\n\n")[0].splitlines()
    assert len(lines) == 2 + 2  # header, rule, one line per configuration
    assert "seed" in lines[0] and "GSF RMS (deg)" in lines[0] and "EKF NEES" in lines[0]
    assert sorted(line.split("|")[2].strip() for line in lines[2:]) == ["3", "5"]


def test_run_prints_every_filter_aligned_and_every_adaptive_difference_with_its_window(tmp_path):
    out = tmp_path / "run"
    filters = 'filters=["EKF", "GSF", "AGSF", "AGSF-galerkin"]'
    code, stdout, _ = _agsf(["run", "case1", *TINY, "--set", filters, "--set", "duration=1.2", "--out", str(out)])
    assert code == 0
    lines = stdout.splitlines()
    rows = [line for line in lines if "NEES" in line and line.startswith("  ")]
    assert [r.split()[0] for r in rows] == ["EKF", "GSF", "AGSF", "AGSF-galerkin"]
    assert len({r.index("NEES") for r in rows}) == 1  # the numbers in one column
    differences = [line for line in lines if "− GSF" in line]
    assert [d.split()[0] for d in differences] == ["AGSF", "AGSF-galerkin"]
    assert len({line.index(" deg,") for line in differences} | {r.index("NEES") - 7 for r in rows}) == 1
    assert "  (window — between frames: every step after the first star frame that is not itself a frame)" in lines


def test_run_without_a_star_frame_prints_a_dash_for_the_window_as_the_tables_do(tmp_path):
    code, stdout, _ = _agsf(["run", "case1", *TINY, "--set", "duration=0.5", "--out", str(tmp_path / "run")])
    rows = [line.split() for line in stdout.splitlines() if "NEES" in line and line.startswith("  ")]
    assert code == 0 and rows and all(r[1] == "—" for r in rows), rows


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (
            ["run", "case1", "--set", "runs", "8"],
            "argument --set: 'runs' is not KEY=VALUE: write the key, '=' and the value as one argument, e.g. --set runs=VALUE",
        ),
        (
            ["sweep", "case1", "--grid", "seed", "3,4"],
            "argument --grid: 'seed' is not KEY=VALUE: write the key, '=' and the value as one argument, e.g. --grid seed=V1,V2",
        ),
        (
            ["run", "case1", "--set", "filters=EKF"],
            """config key 'filters' must be a list (a TOML array), e.g. --set filters='["EKF"]', got 'EKF'""",
        ),
        (
            ["run", "case1", "--set", "rate_axes=1"],
            "config key 'rate_axes' must be a list (a TOML array), e.g. --set rate_axes='[1]', got 1",
        ),
    ],
)
def test_a_malformed_set_or_grid_shows_the_form_it_needs(tmp_path, argv, says):
    out = tmp_path / "out"
    code, stdout, stderr = _agsf([*argv, "--out", str(out)])
    assert code == 2 and stdout == ""
    assert len(stderr.splitlines()) == 1 and says in stderr
    assert not out.exists()


def test_an_unknown_set_key_lists_the_known_keys(tmp_path):
    code, _, stderr = _agsf(["run", "case1", "--set", "sigma_q=1", "--out", str(tmp_path / "x")])
    assert code == 2 and stderr.count("\n") == 1
    assert "unknown config key 'sigma_q'" in stderr
    known = stderr.split("known: ", 1)[1]
    assert {"runs", "duration", "sigma_s", "seed"} <= set(known.rstrip(")\n").split(", "))
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("quiet", [False, True])
def test_info_messages_reach_stderr_unless_quiet(quiet, tmp_path, monkeypatch):
    def fake_run(args):
        logging.getLogger("agsf_torch.fpke.matrices").info("compiling the kernel")
        return 0

    monkeypatch.setattr(cli, "run_command", fake_run)
    logger = logging.getLogger("agsf_torch")
    level, handlers = logger.level, list(logger.handlers)
    code, stdout, stderr = _agsf(["run", "case1", "--out", str(tmp_path)] + (["--quiet"] if quiet else []))
    assert code == 0 and stdout == ""
    assert stderr == ("" if quiet else "agsf: compiling the kernel\n")
    assert (logger.level, logger.handlers) == (level, handlers), "the command leaves logging as it found it"


def test_torch_internal_deprecation_is_hidden_and_nothing_else():
    message = "`torch._prims_common.check` is deprecated and will be removed in the future."
    with warnings.catch_warnings():
        warnings.resetwarnings()  # only the command's own filter below (not the test configuration's)
        warnings.simplefilter("default")
        with cli.messages(quiet=True), warnings.catch_warnings(record=True) as caught:
            warnings.warn_explicit(
                message, FutureWarning, "lowering.py", 1, module="torch._inductor.lowering", registry={}
            )
            warnings.warn_explicit(message, FutureWarning, "ours.py", 1, module="agsf_torch.ours", registry={})
            warnings.warn_explicit(
                "something else", FutureWarning, "lowering.py", 2, module="torch._inductor.lowering", registry={}
            )
    assert [(str(w.message), w.filename) for w in caught] == [(message, "ours.py"), ("something else", "lowering.py")]


def test_reproduce_names_its_outputs(tmp_path, monkeypatch):
    from agsf_torch.experiments.studies import reproduce

    monkeypatch.setattr(reproduce, "reproduce", lambda cases, out, overrides, progress, force, **_: "TABLE")
    out = tmp_path / "repro"
    code, stdout, _ = _agsf(["reproduce", "--case", "1", "--out", str(out)])
    assert code == 0
    assert stdout.splitlines()[0] == "TABLE"
    assert f"{out}/results.md" in stdout and "rms.png" in stdout and "runs.npz" in stdout
    assert stdout.splitlines()[-1] == f"TensorBoard: {cli.tensorboard_command(out)}"


def test_every_command_that_computes_takes_quiet_and_threads():
    """--quiet and --threads mean the same in every command that simulates or filters (simulate lacked both)."""
    subcommands = _subparsers(cli.build_parser())
    for name in ("simulate", "run", "reproduce", "sweep", "soak", "learn", "diagnose", "adaptation"):
        options = {s for action in subcommands[name]._actions for s in action.option_strings}
        assert {"--quiet", "--threads"} <= options, name


def test_simulate_shows_progress_unless_quiet_and_sets_the_threads(tmp_path, monkeypatch):
    import torch

    calls: list[int] = []
    monkeypatch.setattr(torch, "set_num_threads", calls.append)  # recorded, not applied to the test process
    code, _, err = _agsf(["simulate", "--runs", "2", "--steps", "3", "--threads", "1", "--out", str(tmp_path / "a")])
    assert code == 0 and "simulating" in err and calls == [1]
    code, _, err = _agsf(["simulate", "--runs", "2", "--steps", "3", "--quiet", "--out", str(tmp_path / "b")])
    assert code == 0 and err == ""


def test_without_threads_torch_is_capped_at_the_cpus_the_process_may_use(tmp_path, monkeypatch):
    """Torch's default counts the machine's cores; a CPU quota of 2 on a 16-thread default runs 2 threads."""
    import joblib
    import torch

    calls: list[int] = []
    monkeypatch.setattr(torch, "set_num_threads", calls.append)
    monkeypatch.setattr(torch, "get_num_threads", lambda: 16)
    monkeypatch.setattr(joblib, "cpu_count", lambda only_physical_cores=False: 2)
    code, _, _ = _agsf(["simulate", "--runs", "2", "--steps", "3", "--quiet", "--out", str(tmp_path / "a")])
    assert code == 0 and calls == [2]
    monkeypatch.setattr(joblib, "cpu_count", lambda only_physical_cores=False: 32)
    code, _, _ = _agsf(["simulate", "--runs", "2", "--steps", "3", "--quiet", "--out", str(tmp_path / "b")])
    assert code == 0 and calls == [2]  # more CPUs than threads: torch's default stands


def test_a_full_disk_is_an_io_failure_naming_the_file_with_its_own_exit_code(tmp_path, monkeypatch):
    """ENOSPC is the machine's failure, not refused input: exit 3 (not 2), one line naming the file."""
    import errno

    from agsf_torch.attitude import recordings

    def full(self, path):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(recordings.Recording, "save", full)
    code, _, err = _agsf(["simulate", "--runs", "2", "--steps", "3", "--quiet", "--out", str(tmp_path / "s")])
    assert code == cli.EXIT_IO_FAILURE == 3
    assert err.count("\n") == 1 and err.startswith("agsf: I/O failure (") and "recording.npz" in err
    assert "No space left on device" in err


def test_ctrl_c_prints_one_line_and_exits_130(tmp_path, monkeypatch):
    from agsf_torch.experiments.run import recorded

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(recorded, "record_environment", interrupted)
    code, _, err = _agsf(["simulate", "--runs", "2", "--steps", "3", "--quiet", "--out", str(tmp_path / "s")])
    assert code == 130 and err.strip().count("\n") == 0 and err.strip().startswith("agsf: interrupted")


def test_a_full_disk_while_claiming_the_output_folder_leaves_no_folder(tmp_path, monkeypatch):
    import errno

    from agsf_torch.experiments.run import outputs

    def full(path, obj, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(outputs, "write_json", full)
    out = tmp_path / "deep" / "s"
    code, _, err = _agsf(["simulate", "--runs", "2", "--steps", "3", "--quiet", "--out", str(out)])
    assert code == 3 and "experiment.json" in err
    assert not out.exists()


@pytest.mark.parametrize("argv", [["reproduce", "--case", "1"], ["run", "case1"], ["simulate", "--runs", "1"]])
@pytest.mark.parametrize("code", [0, 2, 3])
def test_the_agsf_command_exits_with_mains_code(tmp_path, monkeypatch, argv, code):
    """``entry`` (the console script) leaves through ``sys.exit`` with ``main``'s code after every command: the
    interpreter's normal exit, which flushes the standard streams."""
    monkeypatch.setattr(cli, "main", lambda args: code if args == [*argv, "--out", str(tmp_path)] else 5)
    monkeypatch.setattr(sys, "argv", ["agsf", *argv, "--out", str(tmp_path)])
    with pytest.raises(SystemExit) as info:
        cli.entry()
    assert info.value.code == code


def test_the_command_runs_as_a_module():
    """``python -m agsf_torch.experiments.cli`` is the ``agsf`` command (the package's ``__main__``)."""
    import subprocess

    done = subprocess.run(
        [sys.executable, "-m", "agsf_torch.experiments.cli", "--help"], capture_output=True, text=True, check=False
    )
    assert done.returncode == 0 and done.stdout.startswith("usage: agsf"), done.stderr
