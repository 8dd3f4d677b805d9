"""A run checkpointed and resumed is bit-identical to an uninterrupted one."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

import envs
from agsf_torch import GaussianMixture
from agsf_torch.filters import (
    AdaptiveGaussianSumFilter,
    ExtendedKalmanFilter,
    GaussianSumFilter,
    MixtureManagement,
    PenaltyWeightUpdate,
)
from agsf_torch.models import AttitudeModel, StarVectorMeasurement
from agsf_torch.storage.checkpoint import FORMAT, load_checkpoint, save_checkpoint
from tests.helpers import F64


def _setup(management=None):
    env = envs.StarTrackerAttitudeVectorEnv(num_envs=3, max_steps=50, star_period=0.5)
    model = AttitudeModel(estimate_bias=True)
    filters = {
        "gsf": GaussianSumFilter(model, management=management),
        "agsf": AdaptiveGaussianSumFilter(model, weight_update=PenaltyWeightUpdate(cadence=2), management=management),
    }
    return env, filters


def _start(env):
    obs, info = env.reset(seed=9)
    mean = torch.cat((info["truth_mrp"] + 1e-3, torch.zeros(3, 3, dtype=F64)), -1)
    P0 = torch.diag(torch.tensor([1e-6] * 3 + [1e-12] * 3, dtype=F64)).expand(3, 6, 6)
    return GaussianMixture.from_gaussian(mean, P0, 3)


def _steps(env, filters, mixtures, n):
    for _ in range(n):
        obs, _, _, _, _ = env.step(torch.zeros(3, 3, dtype=F64))
        for name, f in filters.items():
            m = f.predict(mixtures[name], obs["gyro"], 0.1)
            if obs["star_mask"].any():
                y, meas = StarVectorMeasurement.from_observation(obs, 1e-5)
                m = f.update(m, y, meas)
            mixtures[name] = m
    return mixtures


@pytest.mark.parametrize("management", [None, MixtureManagement(capacity=6)], ids=["fixed", "managed"])
def test_resume_is_bit_identical(tmp_path, management):
    env, filters = _setup(management)
    mix0 = _start(env)
    straight = _steps(env, filters, {"gsf": mix0, "agsf": mix0}, 20)

    env, filters = _setup(management)
    mix0 = _start(env)
    half = _steps(env, filters, {"gsf": mix0, "agsf": mix0}, 9)
    path = save_checkpoint(tmp_path / "run.pt", half, filters, {"env": env.state_dict()})
    del env, filters, half

    env, filters = _setup(management)
    mixtures, extra = load_checkpoint(path, filters)
    env.load_state_dict(extra["env"])
    resumed = _steps(env, filters, mixtures, 11)
    for name in straight:
        for field in ("log_weights", "means", "covs"):
            assert torch.equal(getattr(resumed[name], field), getattr(straight[name], field)), (name, field)


def test_bad_checkpoints(tmp_path):
    env, filters = _setup()
    mix = _start(env)
    with pytest.raises(ValueError, match="same filters"):
        save_checkpoint(tmp_path / "x.pt", {"gsf": mix}, filters)
    torch.save({"format": "other"}, tmp_path / "y.pt")
    with pytest.raises(ValueError, match=f"not an {FORMAT} file"):
        load_checkpoint(tmp_path / "y.pt", filters)
    path = save_checkpoint(tmp_path / "z.pt", {"gsf": mix, "agsf": mix}, filters)
    with pytest.raises(ValueError, match="holds filters"):
        load_checkpoint(path, {"gsf": filters["gsf"]})


@pytest.mark.parametrize(
    ("value", "named"),
    [
        (np.zeros(3), r"extra\['rng'\] is a numpy.ndarray"),
        (np.float64(1.5), r"extra\['rng'\] is a numpy.float64"),
        ({"inner": [1, np.int64(7)]}, r"extra\['rng'\]\['inner'\]\[1\] is a numpy.int64"),
        (Path("/tmp/x"), r"extra\['rng'\] is a pathlib.*Path.*str\(path\)"),
        ({3: 1.0}, r"extra\['rng'\]: checkpoint keys must be strings"),
    ],
)
def test_extra_state_that_could_not_be_read_back_is_refused_at_save(tmp_path, value, named):
    """A value torch.load(weights_only=True) cannot read back is refused, naming its key, and the last good
    checkpoint stays as it was; plain values, tensors and nested lists/dicts of them round-trip."""
    env, filters = _setup()
    mix = _start(env)
    mixtures = {"gsf": mix, "agsf": mix}
    path = save_checkpoint(tmp_path / "c.pt", mixtures, filters, extra={"rng": [1, 2.5, "a", None, torch.ones(2)]})
    good = path.read_bytes()
    with pytest.raises(ValueError, match=named):
        save_checkpoint(path, mixtures, filters, extra={"rng": value})
    assert path.read_bytes() == good and sorted(p.name for p in tmp_path.iterdir()) == ["c.pt"]
    _, extra = load_checkpoint(path, filters)
    assert extra["rng"][:4] == [1, 2.5, "a", None] and torch.equal(extra["rng"][4], torch.ones(2))


@pytest.mark.parametrize("build", ["other_state_dim", "mixture_into_ekf"])
def test_a_mixture_that_does_not_fit_its_filter_is_refused_at_load(tmp_path, build):
    """A 6-state mixture for 3-state filters, or a 5-component one for an EKF, is refused when the
    file is read, naming the file and the mismatch, with every filter unchanged."""
    env, filters = _setup()
    mix = _start(env)
    path = save_checkpoint(tmp_path / "six.pt", {"gsf": mix, "agsf": mix}, filters)
    if build == "other_state_dim":
        three = AttitudeModel(estimate_bias=False)
        targets = {"gsf": GaussianSumFilter(three), "agsf": AdaptiveGaussianSumFilter(three)}
        match = r"six\.pt: filter 'gsf': mixture state dimension 6 != model state_dim 3"
    else:
        targets = {"gsf": ExtendedKalmanFilter(filters["gsf"].model), "agsf": filters["agsf"]}
        match = r"six\.pt: filter 'gsf': ExtendedKalmanFilter needs a one-component mixture, got 3 components"
    before = {k: f.state_dict() for k, f in targets.items()}
    with pytest.raises(ValueError, match=match):
        load_checkpoint(path, targets)
    assert {k: f.state_dict() for k, f in targets.items()} == before


def test_malformed_or_mismatched_checkpoints_are_named_and_change_nothing(tmp_path):
    env, filters = _setup()
    mix = _start(env)
    path = save_checkpoint(tmp_path / "ok.pt", {"gsf": mix, "agsf": mix}, filters)
    state = torch.load(path, weights_only=True)
    del state["filters"]["agsf"]["filter"]
    torch.save(state, tmp_path / "bad.pt")
    with pytest.raises(ValueError, match=r"bad\.pt: malformed checkpoint"):
        load_checkpoint(tmp_path / "bad.pt", filters)
    # a Galerkin filter under the name of the penalty one: refused, and the GSF put back as it was
    galerkin = {
        "gsf": GaussianSumFilter(filters["gsf"].model),
        "agsf": AdaptiveGaussianSumFilter(filters["agsf"].model, weight_update="galerkin"),
    }
    before = {k: f.state_dict() for k, f in galerkin.items()}
    with pytest.raises(ValueError, match="filter 'agsf'.*penalty"):
        load_checkpoint(path, galerkin)
    assert {k: f.state_dict() for k, f in galerkin.items()} == before
    nan = torch.load(path, weights_only=True)
    nan["filters"]["gsf"]["mixture"]["means"][0, 0, 0] = float("nan")
    torch.save(nan, tmp_path / "nan.pt")
    with pytest.raises(ValueError, match="nan.pt: filter 'gsf': means must be finite"):
        load_checkpoint(tmp_path / "nan.pt", filters)


def _set(*keys, value):
    def mutate(state):
        d = state
        for k in keys[:-1]:
            d = d[k]
        d[keys[-1]] = value

    return mutate


@pytest.mark.parametrize(
    "mutate, match",
    [
        (
            _set("filters", "gsf", "mixture", "means", value=torch.zeros(3, 3, 6, dtype=torch.int64)),
            r"filter 'gsf': mixture 'means' must be a floating-point tensor, got a torch.int64 tensor",
        ),
        (
            _set("filters", "gsf", "mixture", "covs", value=torch.eye(6, dtype=torch.int64).expand(3, 3, 6, 6).clone()),
            r"filter 'gsf': mixture 'covs' must be a floating-point tensor",
        ),
        (
            _set(
                "filters", "agsf", "mixture", "covs", value=torch.eye(6, dtype=torch.float32).expand(3, 3, 6, 6).clone()
            ),
            r"filter 'agsf': mixture 'covs' is torch.float32 but 'means' is torch.float64",
        ),
        (
            _set("filters", "gsf", "mixture", "means", value="abc"),
            r"filter 'gsf': mixture 'means' must be a floating-point tensor, got str",
        ),
        (
            _set("filters", "gsf", "mixture", "means", value=[[[0.0] * 6] * 3] * 3),
            r"mixture 'means' must be a floating-point tensor, got list",
        ),
        (_set("filters", "gsf", "mixture", value="m"), r"filter 'gsf': mixture must be a dict"),
        (
            _set("filters", "agsf", "mixture", "covs", value=torch.full((3, 3, 6, 6), float("nan"), dtype=F64)),
            r"filter 'agsf': covs has non-finite entries",
        ),
        (
            _set("filters", "agsf", "mixture", "covs", value=-torch.eye(6, dtype=F64).expand(3, 3, 6, 6).clone()),
            r"filter 'agsf': covs is not positive definite at batch index \(0, 0\)",
        ),
        (
            _set(
                "filters",
                "agsf",
                "filter",
                "weight_update",
                "ref_log_weights",
                value=torch.zeros(3, 3, dtype=torch.int64),
            ),
            r"filter 'agsf': weight-update state 'ref_log_weights' must be None or a floating-point tensor",
        ),
        (
            _set("filters", "agsf", "filter", "weight_update", "ref_log_weights", value=torch.zeros(7, dtype=F64)),
            r"filter 'agsf': weight-update state 'ref_log_weights' has shape \(7,\), the mixture's weights \(3, 3\)",
        ),
        (_set("filters", value=None), r"checkpoint holds filters NoneType"),
    ],
)
def test_malformed_content_is_refused_naming_file_and_filter_and_changes_nothing(tmp_path, mutate, match):
    env, filters = _setup()
    mix = _start(env)
    path = save_checkpoint(tmp_path / "ok.pt", {"gsf": mix, "agsf": mix}, filters)
    state = torch.load(path, weights_only=True)
    mutate(state)
    torch.save(state, tmp_path / "broken.pt")
    filters["agsf"].weight_update.load_state_dict(
        {"kind": "penalty", "step": 5, "elapsed": 0.25, "ref_log_weights": None}
    )
    before = {k: f.state_dict() for k, f in filters.items()}
    with pytest.raises(ValueError, match=r"broken\.pt: .*" + match):
        load_checkpoint(tmp_path / "broken.pt", filters)
    assert {k: f.state_dict() for k, f in filters.items()} == before


def test_a_filter_refusing_its_state_with_any_error_puts_every_filter_back(tmp_path):
    """The adaptive filter is restored first; the next one fails with a RuntimeError: the counter goes back."""

    class Fussy(GaussianSumFilter):
        def load_state_dict(self, state):
            raise RuntimeError("cannot restore")

    env, filters = _setup()
    mix = _start(env)
    model = filters["agsf"].model
    path = save_checkpoint(
        tmp_path / "run.pt", {"agsf": mix, "odd": mix}, {"agsf": filters["agsf"], "odd": GaussianSumFilter(model)}
    )
    agsf = AdaptiveGaussianSumFilter(model, weight_update=PenaltyWeightUpdate(cadence=2))
    agsf.weight_update.load_state_dict({"kind": "penalty", "step": 5, "elapsed": 0.25, "ref_log_weights": None})
    with pytest.raises(ValueError, match=r"run\.pt: filter 'odd': cannot restore"):
        load_checkpoint(path, {"agsf": agsf, "odd": Fussy(model)})
    assert agsf.state_dict()["weight_update"]["step"] == 5


def test_unreadable_files_are_named(tmp_path):
    env, filters = _setup()
    mix = _start(env)
    path = save_checkpoint(tmp_path / "ok.pt", {"gsf": mix, "agsf": mix}, filters)
    (tmp_path / "junk.pt").write_bytes(b"not a torch file at all")
    data = path.read_bytes()
    (tmp_path / "cut.pt").write_bytes(data[: len(data) // 2])
    for name in ("junk.pt", "cut.pt"):
        with pytest.raises(ValueError, match=rf"{name} is not a readable torch checkpoint"):
            load_checkpoint(tmp_path / name, filters)
    (tmp_path / "folder.pt").mkdir()
    with pytest.raises(IsADirectoryError, match=r"folder\.pt is a directory"):
        load_checkpoint(tmp_path / "folder.pt", filters)
    with pytest.raises(FileNotFoundError, match=r"missing\.pt does not exist"):
        load_checkpoint(tmp_path / "missing.pt", filters)
