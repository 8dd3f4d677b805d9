"""``agsf sweep``: a resumable grid of configurations, each a batched Monte Carlo.

Every finished configuration is appended as one JSON line to ``results.jsonl``
(with the configuration's digest) as soon as it finishes; a rerun with the same
base and grid skips the digests already there, so an interrupted sweep loses
only the configuration that was running and the one whose files were being written
(locally, a configuration's figures, event files and ``runs.npz`` are written by a worker
process while the next one runs, and its row is appended once they are complete).

TensorBoard (``tensorboard --logdir out/tensorboard``) gets one HParams session per
configuration, named by its swept parameters (``reg=0.5,scaling=trace``,
:func:`agsf_torch.experiments.report.tensorboard.run_name`; a digest is appended only where two names would
collide), holding its parameters, its metrics and the sweep's complete grid as the
experiment configuration, and beneath it one run per filter with the configuration's
time series (tags per metric, simulated time as the step, see :mod:`agsf_torch.experiments.report.tensorboard`):
one chart overlays the filters, the run filter selects configurations::

    out/tensorboard/reg=0.5,scaling=trace/       events: the HParams session
    out/tensorboard/reg=0.5,scaling=trace/GSF/   events: the GSF's curves (rms_deg, nees, …)
    out/tensorboard/reg=1.0,scaling=trace/…      ...
    out/configs/<digest>/                        the configuration's experiment folder
                                                 (runs.npz, summary.json, figures)

The configuration's events are moved there from its folder when it is recorded,
just before its row is appended (a rerun replaces the run of a configuration
interrupted in between).

No filter runs twice on the same numbers: each filter's results depend on the simulation, the
prior and the options it reads (:meth:`~agsf_torch.experiments.config.loader.ExperimentConfig.filter_digest`),
so a sweep over ``reg`` runs the EKF, the GSF and the Galerkin filter once and copies their
arrays into the other configurations' folders (``summary.json``'s ``reused``, the row's
``reused`` and the table's "reused (not rerun)" column name the configuration they came
from).  The local backend does this; the Ray backend runs every configuration whole (its
tasks run at once and cannot wait for one another's filters).

Two backends run the pending configurations:

* ``"local"`` (default): one after another in this process.
* ``"ray"``: one Ray task per configuration (``num_cpus=cpus_per_task``), run
  in parallel on a local Ray instance or on an existing cluster.  Each task runs
  the configuration's Monte Carlo into a temporary folder *on its worker* and
  returns the folder's files; the driver (this process) is the only writer of
  ``out``: it unpacks each configuration's folder to ``out/configs/<digest>`` and
  appends its row in the order the tasks finish.  ``out`` therefore needs no
  shared filesystem.  A task whose worker or node dies is retried by Ray
  (``max_retries``); a configuration that still fails does not stop the others:
  the driver records every configuration that finishes, then raises
  :class:`SweepFailed` naming the failed ones, and a rerun runs only those.

Both backends give the same rows for the same seeds: a configuration's numbers
depend only on its fields (counter-based random streams seeded by ``seed``) and
not on the process or the number of torch threads that computes them (tested
bit for bit).  Only the order of the rows in ``results.jsonl`` may differ.
"""

from .ray_backend import RayUnavailable, SweepFailed
from .rows import results_table
from .run import BACKENDS, SweepBusy, parse_grid, run_sweep

__all__ = ["parse_grid", "run_sweep", "results_table", "SweepFailed", "SweepBusy", "RayUnavailable", "BACKENDS"]
