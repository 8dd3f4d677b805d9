"""``agsf bench``: what the filters cost, beside the peers a user would otherwise write.

* :mod:`.run` — the measurements and :func:`run_bench` (``only=``: some groups of rows alone; also
  ``python -m agsf_torch.experiments.bench --only KEY ...``);
* :mod:`.harness` — timing (median of repeats, interleaved side by side) and the shared problem;
* :mod:`.peers` — the filterpy loop and the NumPy batch doing the same numerical work;
* :mod:`.memory` — peak memory of one workload in a process of its own;
* :mod:`.managed` — the managed filters' steps beside the fused GSF's;
* :mod:`.weight_qp` — the weight QP against Clarabel, on random problems and on the filters' own;
* :mod:`.report` — the targets, met or not, and the Markdown table.
"""

from .report import format_table, targets
from .run import run_bench

__all__ = ["run_bench", "format_table", "targets"]
