"""``agsf reproduce`` with its cases side by side in forked worker processes (``jobs``): the same tables and files as
one after another, refusals before anything is created, a failing case raised once the others are complete, a case
whose process dies named with its exit code."""

from __future__ import annotations

import pytest
import torch

from agsf_torch.experiments.run.resources import TooLarge
from agsf_torch.experiments.run.worker_pool import TaskDied, fork_available
from agsf_torch.experiments.studies import reproduce as reproduce_module
from agsf_torch.experiments.studies.reproduce import check_jobs, default_jobs, reproduce
from tests.experiments.cli.test_cli_failures import _assert_refused
from tests.helpers import EAGER, TINY_CLI, event_records, file_digests

needs_fork = pytest.mark.skipif(not fork_available(), reason="cases side by side need fork (Linux)")
SMALL = ["runs=3", "duration=2.0", "components=2", *EAGER]


@needs_fork
@pytest.mark.parametrize("jobs", [2, 3])
def test_cases_side_by_side_write_what_one_after_another_writes_and_the_threads_are_restored(tmp_path, jobs):
    threads = torch.get_num_threads()
    tables = {
        label: reproduce([1, 2, 3], tmp_path / label, SMALL, progress=False, **kw)
        for label, kw in (("sequential", {"jobs": 1}), ("forked", {"jobs": jobs}))
    }
    assert torch.get_num_threads() == threads
    assert tables["forked"] == tables["sequential"]
    forked, sequential = file_digests(tmp_path / "forked"), file_digests(tmp_path / "sequential")
    assert {f"case{k}/{name}" for k in (1, 2, 3) for name in ("runs.npz", "axes.png", "fpke.png")} <= set(forked)
    assert forked == sequential  # byte for byte: the same numbers, figures and summaries
    assert event_records(tmp_path / "forked") == event_records(tmp_path / "sequential")


@needs_fork
def test_a_failing_case_is_raised_once_the_other_cases_are_written(tmp_path, monkeypatch):
    run = reproduce_module.run_experiment

    def failing_case2(cfg, out, **kw):  # inherited by the forked processes
        if out.name == "case2":
            raise ValueError("case 2's recording is unreadable")
        return run(cfg, out, **kw)

    monkeypatch.setattr(reproduce_module, "run_experiment", failing_case2)
    with pytest.raises(ValueError, match="^case 2's recording is unreadable$"):
        reproduce([1, 2, 3], tmp_path / "out", SMALL, progress=False, jobs=3)
    for case in ("case1", "case3"):  # complete, whatever case 2 did, their HParams sessions included
        assert {"runs.npz", "summary.json", "axes.png", "rms.png", "weights.png", "fpke.png"} <= {
            p.name for p in (tmp_path / "out" / case).iterdir()
        }
        assert list((tmp_path / "out" / case / "tensorboard").glob("events.out.tfevents.*"))
    assert not (tmp_path / "out" / "results.md").exists()


@needs_fork
def test_a_case_whose_process_dies_is_named_with_its_exit_code_once_the_others_are_written(tmp_path, monkeypatch):
    import os

    run = reproduce_module.run_experiment

    def dying_case2(cfg, out, **kw):  # inherited by the forked processes
        if out.name == "case2":
            os._exit(9)
        return run(cfg, out, **kw)

    monkeypatch.setattr(reproduce_module, "run_experiment", dying_case2)
    with pytest.raises(TaskDied, match=r"^case2 ended without a reply \(exit code 9\)$"):
        reproduce([1, 2], tmp_path / "out", SMALL, progress=False, jobs=2)
    assert not (tmp_path / "out" / "results.md").exists()
    assert not list((tmp_path / "out").rglob(".*.tmp"))


@pytest.mark.parametrize(
    ("jobs", "threads", "match"),
    [
        (0, None, "jobs must be a positive integer, got 0"),
        (1.5, None, "jobs must be a positive integer"),
        (True, None, "jobs must be a positive integer"),
        (2, 2, r"cases side by side run one torch thread each, got threads=2"),
        (1, 0, "threads must be a positive integer or None, got 0"),
    ],
)
def test_bad_job_counts_are_refused_before_anything_is_created(tmp_path, monkeypatch, jobs, threads, match):
    monkeypatch.setattr(reproduce_module, "fork_available", lambda: True)
    kw = {"threads": threads}
    with pytest.raises(ValueError, match=match):
        reproduce([1, 2], tmp_path / "out", list(EAGER), progress=False, jobs=jobs, **kw)
    assert not (tmp_path / "out").exists()


def test_without_fork_cases_run_one_after_another_by_default_and_side_by_side_is_refused(tmp_path, monkeypatch):
    monkeypatch.setattr(reproduce_module, "fork_available", lambda: False)
    assert default_jobs(3) == 1
    with pytest.raises(ValueError, match="which need Linux and the main thread"):
        reproduce([1, 2], tmp_path / "out", list(EAGER), progress=False, jobs=2)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(("cpus", "cases", "expected"), [(1, 3, 1), (2, 3, 3), (8, 3, 3), (2, 1, 1)])
def test_by_default_every_case_runs_at_once_on_two_cpus_or_more(monkeypatch, cpus, cases, expected):
    monkeypatch.setattr(reproduce_module, "fork_available", lambda: True)
    import joblib

    monkeypatch.setattr(joblib, "cpu_count", lambda only_physical_cores=False: cpus)
    assert default_jobs(cases) == expected
    assert check_jobs(None, cases) == expected


def test_jobs_are_capped_by_the_cases():
    if fork_available():
        assert check_jobs(7, 3) == 3
    assert check_jobs(5, 1) == 1  # one case: nothing side by side


def test_cases_side_by_side_that_do_not_fit_in_memory_are_refused_naming_jobs_1(tmp_path, monkeypatch):
    from agsf_torch.experiments.run import resources

    monkeypatch.setattr(reproduce_module, "fork_available", lambda: True)
    monkeypatch.setattr(resources, "available_memory", lambda: 700 * 2**20)  # one case fits, three do not
    with pytest.raises(TooLarge, match=r"3 configurations side by side need an estimated .* \(--jobs 1\)"):
        reproduce([1, 2, 3], tmp_path / "out", list(EAGER), progress=False, jobs=3)
    assert not (tmp_path / "out").exists()


def test_the_cli_refuses_bad_jobs_and_the_writers_flag_that_jobs_replaced_in_one_line_exit_2(tmp_path):
    out = tmp_path / "out"
    _assert_refused(["reproduce", "--out", str(out), "--jobs", "0", *TINY_CLI], tmp_path, "--jobs")
    _assert_refused(["reproduce", "--out", str(out), "--jobs", "2", "--writers", "1", *TINY_CLI], tmp_path, "--writers")
    _assert_refused(["sweep", "case1", "--grid", "reg=1", "--writers", "1", "--out", str(out)], tmp_path, "--writers")


def test_a_cases_process_that_dies_is_a_one_line_failure_exit_3(tmp_path, monkeypatch):
    """A case's process killed (out of memory, say) is the machine's failure, not a traceback."""
    from tests.experiments.cli.test_cli_failures import _agsf

    def died(*a, **kw):
        raise TaskDied("case2 ended without a reply (exit code -9)")

    monkeypatch.setattr(reproduce_module, "reproduce", died)
    code, err = _agsf(["reproduce", "--out", str(tmp_path / "out"), *TINY_CLI])
    assert code == 3 and err == "agsf: failure: case2 ended without a reply (exit code -9)\n"
