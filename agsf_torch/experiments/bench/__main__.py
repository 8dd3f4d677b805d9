"""``python -m agsf_torch.experiments.bench``: ``agsf bench`` with a choice of rows.

``--only KEY ...`` runs the named groups of rows alone (:data:`~.run.SECTIONS`, each the key it is stored under in
``bench.json``), for example the mixture management's rows::

    python -m agsf_torch.experiments.bench --only managed qp qp_filter memory_managed --out runs/bench-managed

Writes ``bench.json`` and ``bench.md`` under ``--out`` and prints the table, as ``agsf bench`` does.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ...allocator import set_mmap_threshold
from ...storage.files import write_text
from ..cli.commands import _threads
from .report import format_table
from .run import SECTIONS, check_reference, run_bench


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m agsf_torch.experiments.bench", description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="runs/bench", help="output folder (default: runs/bench)")
    parser.add_argument("--only", nargs="+", choices=SECTIONS, metavar="KEY", help=f"run these groups: {SECTIONS}")
    parser.add_argument("--quick", action="store_true", help="smaller samples (a smoke run, not the reference numbers)")
    parser.add_argument("--no-compile", action="store_true", help="run the kernels eagerly")
    parser.add_argument("--main-job-reference", default=None, metavar="DIR", help="as agsf bench's")
    parser.add_argument("--threads", type=int, default=None, help="torch threads")
    args = parser.parse_args(argv)
    set_mmap_threshold()  # as the agsf command sets the allocator up
    _threads(args)  # and torch's threads
    reference = check_reference(args.main_job_reference)
    report = run_bench(
        Path(args.out), compile=not args.no_compile, quick=args.quick, main_job_reference=reference, only=args.only
    )
    table = format_table(report)
    write_text(Path(args.out) / "bench.md", table + "\n")
    print(table)
    print(f"report: {args.out}/bench.json, {args.out}/bench.md")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
