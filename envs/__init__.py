"""Gymnasium environments for spacecraft attitude estimation: truth dynamics, gyro,
star camera and a Hipparcos star catalogue, all in batched float64 torch.

Importing this package registers ``agsf/StarTrackerAttitude-v0``::

    import envs  # registers the id
    env = gymnasium.make("agsf/StarTrackerAttitude-v0", star_period=2.0)
    venv = gymnasium.make_vec("agsf/StarTrackerAttitude-v0", num_envs=1024,
                              vectorization_mode="vector_entry_point")

Gymnasium ≥ 1.0 does not load the ``gymnasium.envs`` entry-point group by itself, so
without ``import envs`` use the module-qualified id
``gymnasium.make("envs:agsf/StarTrackerAttitude-v0")``, which imports this package
first.  Keyword arguments are :class:`StarTrackerConfig` fields (or ``config=``).

This package depends on :mod:`agsf_torch.rotations` only (never on the filters).

Modules:

* :mod:`envs.config` — :class:`StarTrackerConfig`, the validated settings.
* :mod:`envs.simulator` — :class:`StarTrackerSimulator`, the batched state and the
  one time-step implementation (used by stepping and by ``simulate``).
* :mod:`envs.star_tracker` — the gymnasium adapters :class:`StarTrackerAttitudeEnv`
  and :class:`StarTrackerAttitudeVectorEnv` (timeline and seeding documented there).
* :mod:`envs.dynamics`, :mod:`envs.gyro`, :mod:`envs.camera`, :mod:`envs.faults` —
  the physics: truth attitude, gyro model, star camera, injected sensor faults.
* :mod:`envs.catalog` — the Hipparcos catalogue (parsing, disk and in-process caches).
* :mod:`envs.random` — counter-based random numbers and the simulation's stream ids.
"""

from __future__ import annotations

import gymnasium

from .camera import StarCamera, StarObservation, random_attitude_quat, star_count_distribution
from .catalog import DEFAULT_MAX_MAGNITUDE, StarCatalog, cache_dir, load_hipparcos_table
from .config import StarTrackerConfig
from .dynamics import DEFAULT_OMEGA0, DEFAULT_RATE, AttitudeDynamics, propagate_quat
from .faults import FAULT_KINDS, SensorFault
from .gyro import DEFAULT_INITIAL_BIAS, DEFAULT_SIGMA_U, DEFAULT_SIGMA_V, DEG_PER_HOUR, Gyro
from .random import CounterKey, counter_normal, counter_uniform
from .simulator import StarTrackerSimulator
from .star_tracker import StarTrackerAttitudeEnv, StarTrackerAttitudeVectorEnv

__all__ = [
    "ENV_ID",
    "register_envs",
    "StarTrackerConfig",
    "StarTrackerSimulator",
    "StarTrackerAttitudeEnv",
    "StarTrackerAttitudeVectorEnv",
    "SensorFault",
    "FAULT_KINDS",
    "StarCatalog",
    "StarCamera",
    "StarObservation",
    "star_count_distribution",
    "random_attitude_quat",
    "cache_dir",
    "load_hipparcos_table",
    "Gyro",
    "AttitudeDynamics",
    "propagate_quat",
    "CounterKey",
    "counter_normal",
    "counter_uniform",
    "DEFAULT_MAX_MAGNITUDE",
    "DEFAULT_SIGMA_V",
    "DEFAULT_SIGMA_U",
    "DEFAULT_INITIAL_BIAS",
    "DEFAULT_OMEGA0",
    "DEFAULT_RATE",
    "DEG_PER_HOUR",
]

ENV_ID = "agsf/StarTrackerAttitude-v0"


def register_envs() -> None:
    """Register ``agsf/StarTrackerAttitude-v0`` with gymnasium (idempotent).

    ``entry_point`` is :class:`StarTrackerAttitudeEnv`, ``vector_entry_point``
    :class:`StarTrackerAttitudeVectorEnv`.  Keyword arguments of ``gymnasium.make``
    / ``make_vec`` are config fields (or ``config=StarTrackerConfig(...)``).
    """
    if ENV_ID in gymnasium.registry:
        return
    gymnasium.register(
        id=ENV_ID,
        entry_point="envs.star_tracker:StarTrackerAttitudeEnv",
        vector_entry_point="envs.star_tracker:StarTrackerAttitudeVectorEnv",
    )


register_envs()
