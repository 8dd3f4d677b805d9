"""The command line's failure paths, as a property: every refused command exits 2 with one
line naming the problem, creates and changes nothing, and the corrected command then succeeds.

Each failure kind draws its bad input with hypothesis (values out of range, corrupt or
misshapen files, unusable output folders); the corrected command of each kind is run
once, after its refusals, in the same folder.
"""

from __future__ import annotations

import hashlib
import io
import tempfile
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from agsf_torch.attitude.learning import PARAMETERS
from agsf_torch.attitude.recordings import Recording
from agsf_torch.experiments.cli import main as cli
from agsf_torch.experiments.config.loader import MAX_SEED
from tests.helpers import TINY_CLI

TINY = TINY_CLI


def _tree(root: Path) -> dict[str, str]:
    """Every path under ``root`` with a digest of its bytes (folders: ``"dir"``)."""
    return {
        str(p.relative_to(root)): ("dir" if p.is_dir() else hashlib.sha256(p.read_bytes()).hexdigest())
        for p in sorted(root.rglob("*"))
    }


def _agsf(argv: list[str]) -> tuple[int, str]:
    err = io.StringIO()
    with redirect_stderr(err), redirect_stdout(io.StringIO()):
        try:
            code = cli.main(argv)
        except SystemExit as exc:  # argparse
            code = exc.code
    return code, err.getvalue()


def _assert_refused(argv: list[str], root: Path, names: str) -> None:
    before = _tree(root)
    code, err = _agsf(argv)
    assert code == 2, (argv, err)
    assert err.endswith("\n") and "\n" not in err[:-1], f"not one line: {err!r}"
    assert err.startswith("agsf") and ": error: " in err, err
    assert names.lower() in err.lower(), (names, err)
    assert _tree(root) == before, f"{argv} changed {root}"


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    """A valid recording for the TINY configuration (2 runs, 0.3 s, truth included)."""
    out = tmp_path_factory.mktemp("rec") / "sim"
    assert _agsf(["simulate", "--runs", "2", "--steps", "3", "--star-period", "0.1", "--out", str(out)])[0] == 0
    return out / "recording.npz"


def _bad_override():
    """``(overrides, text the message must contain)`` that the configuration refuses
    (several overrides separated by NUL)."""
    return st.one_of(
        st.integers(max_value=-1).map(lambda v: (f"seed={v}", "'seed'")),
        st.integers(min_value=MAX_SEED + 1).map(lambda v: (f"seed={v}", "'seed'")),
        st.integers(max_value=0).map(lambda v: (f"runs={v}", "'runs'")),
        st.floats(max_value=0.0, allow_nan=False).map(lambda v: (f"duration={v!r}", "'duration'")),
        st.integers(65, 10**6).map(lambda v: (f'components={v}\0filters=["AGSF"]', "'components'")),
        st.integers(117_956, 10**12).map(lambda v: (f"max_stars={v}", "max_stars")),
        st.floats(1e3, 1e300).map(lambda v: (f"omega0={v!r}", "rate")),
        st.floats(1.0, 1e300).map(lambda v: (f"gate_probability={v!r}", "'gate_probability'")),
        st.sampled_from(["true", '"1.0"']).map(lambda v: (f"sigma_s={v}", "'sigma_s'")),
        st.from_regex(r"\Azz[a-z_]{1,8}\Z").map(lambda k: (f"{k}=1", k)),
    )


def _bad_recording_file(path: Path, good: Path, data) -> str:
    """Write a broken recording at ``path``; returns what the message must contain."""
    raw = good.read_bytes()
    kind = data.draw(
        st.sampled_from(
            ["missing", "directory", "text", "empty", "truncated", "flipped", "complex", "non-unit", "runs", "no-truth"]
        )
    )
    if kind == "missing":
        return path.name
    if kind == "directory":
        path.mkdir()
    elif kind == "text":
        path.write_text(data.draw(st.text(min_size=1)))
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "truncated":
        path.write_bytes(raw[: data.draw(st.integers(1, len(raw) - 1))])
    elif kind == "flipped":
        at = data.draw(st.integers(0, len(raw) - 1))
        path.write_bytes(raw[:at] + bytes([raw[at] ^ 0xFF]) + raw[at + 1 :])
        try:
            same = Recording.load(path).content_digest() == Recording.load(good).content_digest()
        except ValueError:
            same = False
        assume(not same)  # a flip in bytes the archive does not check leaves the data intact
    else:
        rec = Recording.load(good)
        arrays = {
            k: getattr(rec, k)
            for k in ("time", "gyro", "star_body", "star_inertial", "star_mask", "truth_mrp", "truth_bias")
        }
        if kind == "complex":
            arrays["gyro"] = arrays["gyro"].astype(np.complex128)
        elif kind == "no-truth":  # a recording of flight data: nothing to score the filters against
            del arrays["truth_mrp"], arrays["truth_bias"]
        elif kind == "non-unit":
            arrays["star_mask"] = np.ones_like(arrays["star_mask"])
            arrays["star_body"] = np.full_like(arrays["star_body"], data.draw(st.floats(0.0, 0.5)))
        else:  # three trajectories for a two-run configuration
            arrays = {k: (v if k == "time" else np.concatenate([v, v[:1]])) for k, v in arrays.items()}
        np.savez(path, **arrays)
    return str(path.name)


KINDS = ["override", "memory", "recording", "simulate", "learn", "sweep", "config", "output"]


@pytest.mark.parametrize("kind", KINDS)
def test_a_refused_command_exits_2_in_one_line_creates_nothing_and_the_corrected_one_runs(kind, recording, tmp_path):
    root = tmp_path / "work"
    root.mkdir()

    @settings(max_examples=12, deadline=None, suppress_health_check=list(HealthCheck), database=None)
    @given(data=st.data())
    def refused(data):
        with tempfile.TemporaryDirectory(dir=root) as d:
            d = Path(d)
            out = str(d / "out")
            if kind == "override":
                overrides, names = data.draw(_bad_override())
                sets = [a for o in overrides.split("\0") for a in ("--set", o)]
                _assert_refused(["run", "case1", *TINY, *sets, "--out", out], d, names)
            elif kind == "memory":
                runs = data.draw(st.integers(10**7, 10**12))
                _assert_refused(["run", "case1", *TINY, "--set", f"runs={runs}", "--out", out], d, "memory")
            elif kind == "recording":
                bad = d / "bad.npz"
                names = _bad_recording_file(bad, recording, data)
                _assert_refused(["run", "case1", *TINY, "--recording", str(bad), "--out", out], d, names)
            elif kind == "simulate":
                arg = data.draw(st.sampled_from(["--star-period", "--seed", "--runs", "--steps"]))
                value = {
                    "--star-period": st.floats(0.01, 10.0)
                    .filter(lambda v: abs(v / 0.1 - round(v / 0.1)) > 1e-6)
                    .map(repr),
                    "--seed": st.one_of(st.integers(max_value=-1), st.integers(min_value=MAX_SEED + 1)).map(str),
                    "--runs": st.integers(max_value=0).map(str),
                    "--steps": st.one_of(st.integers(max_value=0).map(str), st.just("ten")),
                }[arg]
                names = "star_period" if arg == "--star-period" else arg
                _assert_refused(
                    ["simulate", "--runs", "2", "--steps", "3", arg, data.draw(value), "--out", out], d, names
                )
            elif kind == "learn":
                name = data.draw(st.from_regex(r"\A[a-z_]{1,12}\Z").filter(lambda s: s not in PARAMETERS))
                _assert_refused(
                    ["learn", "case1", *TINY, "--learn", name, "--recording", str(recording), "--out", out],
                    d,
                    "--learn",
                )
            elif kind == "sweep":
                v = data.draw(st.integers(1, 9))
                grid, names = data.draw(
                    st.sampled_from(
                        [
                            (f"reg={v},{v}.0", "twice"),
                            (f"zz_key={v}", "zz_key"),
                            (f"reg=-{v}", "'reg'"),
                            (f"spread={v}", "'spread'"),
                        ]
                    )
                )
                _assert_refused(["sweep", "case1", *TINY, "--grid", grid, "--out", out], d, names)
            elif kind == "config":
                path = d / "mine.toml"
                case = data.draw(st.sampled_from(["missing", "directory", "binary", "toml", "unknown key"]))
                if case == "directory":
                    path.mkdir()
                elif case == "binary":
                    path.write_bytes(b"\xff" + data.draw(st.binary()))
                elif case == "toml":
                    path.write_text("runs = [" + data.draw(st.text(alphabet="0123456789, ")))
                elif case == "unknown key":
                    path.write_text('preset = "case1"\nzz_speed = 1\n')
                names = {"missing": "does not exist", "directory": "not a file", "binary": "utf-8", "toml": "toml"}.get(
                    case, "zz_speed"
                )
                _assert_refused(["run", str(path), *TINY, "--out", out], d, names)
            else:  # output folders that cannot hold the experiment
                target = d / "taken"
                case = data.draw(st.sampled_from(["file", "corrupt marker", "other experiment", "foreign folder"]))
                if case == "file":
                    target.write_text("not a folder")
                    names = "is a file"
                else:
                    target.mkdir()
                    marker = {
                        "corrupt marker": '{"kind": "run", "dig',
                        "other experiment": '{"kind": "run", "digest": "0"}',
                    }
                    if case in marker:
                        (target / "experiment.json").write_text(marker[case])
                    else:
                        (target / "notes.txt").write_text("mine")
                    names = {"corrupt marker": "corrupt", "other experiment": "different experiment"}.get(
                        case, "not an agsf"
                    )
                _assert_refused(["run", "case1", *TINY, "--out", str(target)], d, names)

    refused()
    out = str(root / "corrected")
    corrected = {
        "simulate": ["simulate", "--runs", "2", "--steps", "3", "--star-period", "0.2", "--out", out],
        "learn": [
            "learn",
            "case1",
            *TINY,
            "--learn",
            "sigma_v",
            "--max-iter",
            "1",
            "--recording",
            str(recording),
            "--out",
            out,
        ],
        "recording": ["run", "case1", *TINY, "--recording", str(recording), "--out", out],
        "sweep": ["sweep", "case1", *TINY, "--grid", "reg=0.5,1", "--out", out],
    }.get(kind, ["run", "case1", *TINY, "--out", out])
    code, err = _agsf(corrected)
    assert code == 0, err
    assert (Path(out) / "experiment.json").exists()


@pytest.mark.parametrize("frames", [0, 1])
def test_learn_refuses_a_recording_with_too_few_star_frames(tmp_path, recording, frames):
    """No star frame (or one) leaves the noise parameters unconstrained: refused before --out exists,
    saying why (it exited 0 with NaN intervals and a "mis-modelled" verdict)."""
    rec = Recording.load(recording)
    arrays = {
        k: getattr(rec, k)
        for k in ("time", "gyro", "star_body", "star_inertial", "star_mask", "truth_mrp", "truth_bias")
    }
    assert bool(arrays["star_mask"].any(-1)[:, 1:].all())  # the fixture has a star frame at every sample after t = 0
    arrays["star_mask"] = arrays["star_mask"].copy()
    arrays["star_mask"][:, 1 + frames :] = False
    path = tmp_path / "no_stars.npz"
    np.savez(path, **arrays)
    out = tmp_path / "out"
    argv = ["learn", "case1", *TINY, "--learn", "sigma_v", "--recording", str(path), "--out", str(out)]
    _assert_refused(argv, tmp_path, f"{frames} star frame(s)")
    assert not out.exists()


def _rewrite(recording: Path, path: Path, **changes) -> Path:
    rec = Recording.load(recording)
    keys = ("time", "gyro", "star_body", "star_inertial", "star_mask", "truth_mrp", "truth_bias")
    np.savez(path, **{k: changes.get(k, getattr(rec, k)) for k in keys})
    return path


def test_a_recording_without_the_truth_or_an_initial_estimate_is_refused_naming_it(recording, tmp_path):
    """Flight data without an initial estimate gives the filters nowhere to start: ``agsf run --recording``
    refuses it in one line naming the file, before the output folder exists."""
    rec = Recording.load(recording)
    keys = ("time", "gyro", "star_body", "star_inertial", "star_mask")
    bad = tmp_path / "flight.npz"
    np.savez(bad, **{k: getattr(rec, k) for k in keys})
    argv = ["run", "case1", *TINY, "--recording", str(bad), "--out", str(tmp_path / "out")]
    _assert_refused(
        argv, tmp_path, "flight.npz has neither the truth (truth_mrp and truth_bias) nor an initial estimate"
    )


@pytest.mark.parametrize("stamps", ["epoch_float64", "float32"])
def test_evenly_sampled_recordings_are_judged_at_the_precision_of_their_timestamps(tmp_path, recording, stamps):
    """Unix-epoch seconds (float64: spacings jitter by ~1e-7 s from rounding alone) and float32 timestamps are
    evenly sampled; they were refused as "needs uniformly spaced samples"."""
    t = Recording.load(recording).time
    time = (1.7e9 + t) if stamps == "epoch_float64" else (1000.0 + t).astype(np.float32)
    path = _rewrite(recording, tmp_path / "stamped.npz", time=time)
    code, err = _agsf(["run", "case1", *TINY, "--recording", str(path), "--out", str(tmp_path / "out")])
    assert code == 0, err


@pytest.mark.parametrize("command", ["run", "learn", "diagnose"])
@pytest.mark.parametrize("defect", ["uneven", "gyro_x1e6", "other_dt"])
def test_run_learn_and_diagnose_check_a_recording_alike(tmp_path, recording, command, defect):
    """One set of checks for every command that reads a recording: samples evenly spaced, at the configuration's
    dt, gyro rates that are rotations (×1e6 ran to completion with NEES 3e112); learn accepted a dt that run
    refused."""
    rec = Recording.load(recording)
    if defect == "uneven":
        time = rec.time.copy()
        time[2] += 0.01
        path = _rewrite(recording, tmp_path / "r.npz", time=time)
        names = f"recording {path}: the samples are not uniformly spaced"
    elif defect == "gyro_x1e6":
        path, names = _rewrite(recording, tmp_path / "r.npz", gyro=rec.gyro * 1e6), "rad per sample"
    else:
        path, names = _rewrite(recording, tmp_path / "r.npz", time=rec.time * 2), "sampled every 0.2 s"
    argv = [command, "case1", *TINY, "--recording", str(path), "--out", str(tmp_path / "out")]
    if command == "learn":
        argv += ["--learn", "sigma_v", "--max-iter", "1"]
    _assert_refused(argv, tmp_path, names)


def test_one_writer_per_output_folder(tmp_path):
    """While another process writes --out (its lock held), a second command on it is refused, one line, exit
    2, nothing changed; once released, the same command runs (two runs both succeeded and could leave two
    event files)."""
    from filelock import FileLock

    out = tmp_path / "out"
    assert _agsf(["run", "case1", *TINY, "--out", str(out)])[0] == 0
    other = FileLock(str(out / ".agsf.lock"))  # another process's claim (a separate open file)
    other.acquire(timeout=0)
    try:
        _assert_refused(["run", "case1", *TINY, "--out", str(out)], tmp_path, "another agsf command is writing")
    finally:
        other.release()
    assert _agsf(["run", "case1", *TINY, "--out", str(out)])[0] == 0


def test_a_rerun_of_learn_replaces_its_events(tmp_path, recording):
    """learn's loss curve after a rerun reads 1, 2, … once (it read 1, 2, 1, 2, 3: appended event files)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out = tmp_path / "learn"
    argv = ["learn", "case1", *TINY, "--learn", "sigma_v", "--max-iter", "2", "--recording", str(recording)]
    for _ in range(2):
        assert _agsf([*argv, "--out", str(out)])[0] == 0
    events = sorted((out / "tensorboard").glob("events.out.tfevents.*"))
    assert len(events) == 1
    acc = EventAccumulator(str(out / "tensorboard"))
    acc.Reload()
    steps = [e.step for e in acc.Scalars("learn/nll")]
    assert steps == sorted(set(steps)) and steps[0] == 1


def test_a_warning_is_one_line_naming_the_file(tmp_path, recording):
    """A recording's star vectors off unit norm within the tolerance are normalised with a warning: on the
    command line one line ``agsf: warning: recording FILE: …`` (it was Python's ``<string>:11: UserWarning: …``,
    with a location inside the package), also with ``--quiet``, and the command runs."""
    rec = Recording.load(recording)
    star_body = np.where(rec.star_mask[..., None], rec.star_body * (1 + 5e-4), rec.star_body)
    path = _rewrite(recording, tmp_path / "off.npz", star_body=star_body)
    code, err = _agsf(["run", "case1", *TINY, "--recording", str(path), "--out", str(tmp_path / "out")])
    assert code == 0, err
    assert err.startswith(
        f"agsf: warning: recording {path}: column 'star_body' has star vectors off unit norm by up to "
    )
    assert err.endswith("; normalised\n") and err.count("\n") == 1 and "UserWarning" not in err


@pytest.mark.parametrize(
    ("argv", "names"),
    [
        (["soak", "--runs", "2", "--duration", "10", "--warmup", "5"], "multiple of report_every=60"),
        (["soak", "--runs", "2", "--duration", "10", "--report-every", "5", "--warmup", "5.5"], "multiple"),
        (["soak", "--runs", "2", "--duration", "10", "--report-every", "5", "--warmup", "10"], "no report to judge"),
        (
            ["soak", "--runs", "2", "--duration", "10", "--set", "duration=70"],
            "--set duration=… conflicts with --duration",
        ),
        (["soak", "--runs", "2", "--duration", "10", "--set", "runs=3"], "--set runs=… conflicts with --runs"),
        (["reproduce", "--case", "1", "--runs", "2", "--set", "runs=3"], "--set runs=… conflicts with --runs"),
        (["sweep", "case1", "--grid", "reg=1,2", "--set", "reg=3"], "--set reg=… conflicts with --grid reg"),
        (["soak", "--filter", "EKF", "--set", 'filters=["GSF"]'], "--set filters=… conflicts with --filter"),
        (["soak", "--no-compile", "--set", "compile=true"], "--set compile=… conflicts with --no-compile"),
    ],
)
def test_a_value_given_twice_or_a_soak_schedule_without_a_verdict_is_refused_before_any_work(argv, names, tmp_path):
    """A soak whose warm-up falls inside a report row (the verdict would count the rest of that row, the prior's
    stretch included) or leaves no row to judge, and a key set both by ``--set`` and by the command's own option,
    are refused in one line before anything runs or is created (they had simulated the whole run, or dropped a value)."""
    root = tmp_path / "work"
    root.mkdir()
    _assert_refused([*argv, "--out", str(root / "out"), "--quiet"], root, names)


def test_soak_progress_rows_go_to_stderr(tmp_path, capsys):
    """stdout carries the verdict alone (``agsf soak … | jq``); the report rows are progress, on stderr."""
    import json

    code = cli.main(
        ["soak", "--runs", "2", "--duration", "2", "--report-every", "1", "--warmup", "1"]
        + ["--set", "components=2", "--out", str(tmp_path / "s")]
    )
    out, err = capsys.readouterr()
    assert code in (0, 1) and json.loads(out)["warmup_s"] == 1.0
    assert err.count("t = ") == 2 and "RSS" in err


def test_a_recording_with_half_the_truth_is_refused_naming_the_missing_column(recording, tmp_path):
    """``truth_mrp`` without ``truth_bias`` had been replayed as flight data, its truth ignored without a word."""
    rec = Recording.load(recording)
    keys = ("time", "gyro", "star_body", "star_inertial", "star_mask", "truth_mrp")
    half = tmp_path / "half.npz"
    np.savez(half, initial_mrp=rec.truth_mrp[:, 0], **{k: getattr(rec, k) for k in keys})
    argv = ["run", "case1", *TINY, "--recording", str(half), "--out", str(tmp_path / "out")]
    _assert_refused(argv, tmp_path, "half.npz has truth_mrp but not truth_bias")
