"""Peak resident memory of one workload, run as its own process (``python -m agsf_torch.experiments.bench.memory``).

``gsf --batch B --chunk C``: a B × N = 5 6-state GSF sweep of 100 predict steps, in chunks of C trajectories.
``adaptive --update NAME --batch B``: one adaptive predict step (6-state, N = 5) with the weight update NAME.
``managed --filter NAME --batch B --capacity K [--compile]``: one predict + star update (5 stars) of the managed
filter NAME (6-state, the 5-component prior padded to K slots, management's defaults; ``--compile``: its kernels
compiled, as the timed rows run them).
The allocator is set up as the ``agsf`` command sets it (:func:`agsf_torch.allocator.set_mmap_threshold`) unless
``--default-allocator``.  Prints one JSON line: the workload and ``peak_rss_mib``, this process's own peak
(:func:`~agsf_torch.experiments.run.resources.peak_resident_memory`).
"""

from __future__ import annotations

import argparse
import json

import torch

from ...allocator import set_mmap_threshold
from ...filters.registry import make_filter
from ...models import AttitudeModel
from ..run.resources import peak_resident_memory
from .harness import MANAGED_FILTERS, WEIGHT_UPDATE_FILTERS, attitude_mixture


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m agsf_torch.experiments.bench.memory")
    parser.add_argument("workload", choices=("gsf", "adaptive", "managed"))
    parser.add_argument("--batch", type=int, required=True)
    parser.add_argument("--chunk", type=int, default=16384)
    parser.add_argument("--update", choices=tuple(WEIGHT_UPDATE_FILTERS), default="galerkin")
    parser.add_argument("--filter", choices=MANAGED_FILTERS, default="GSF-managed")
    parser.add_argument("--capacity", type=int, default=16)
    parser.add_argument("--compile", action="store_true", help="the managed filter's kernels compiled")
    parser.add_argument("--default-allocator", action="store_true", help="leave glibc's mmap threshold as it is")
    args = parser.parse_args(argv)
    if not args.default_allocator:
        set_mmap_threshold()
    gen = torch.Generator().manual_seed(4)
    model = AttitudeModel(estimate_bias=True)
    if args.workload == "gsf":
        filt = make_filter("GSF", model)
        for start in range(0, args.batch, args.chunk):
            size = min(args.chunk, args.batch - start)
            mix = attitude_mixture(size, 5, True, gen)
            u = torch.full((size, 3), 0.06, dtype=torch.float64)
            for _ in range(100):
                mix = filt.predict(mix, u, 0.1)
        what = f"GSF sweep B={args.batch} N=5 6-state, 100 steps, chunks of {args.chunk}"
        row = {"what": what, "batch": args.batch, "chunk": args.chunk}
    elif args.workload == "managed":
        from ...filters.management import pad_mixture
        from .fused import _star_problem

        filt = make_filter(args.filter, model, capacity=args.capacity, compile_fused=args.compile)
        mix = pad_mixture(attitude_mixture(args.batch, 5, True, gen), args.capacity)
        y, meas = _star_problem(args.batch)
        filt.update(filt.predict(mix, torch.full((args.batch, 3), 0.06, dtype=torch.float64), 0.1), y, meas)
        row = {
            "what": f"{args.filter} predict + star update B={args.batch} capacity {args.capacity} 6-state"
            + (" (compiled)" if args.compile else ""),
            "batch": args.batch,
            "filter": args.filter,
            "capacity": args.capacity,
            "compiled": args.compile,
        }
    else:
        filt = make_filter(WEIGHT_UPDATE_FILTERS[args.update], model)
        filt.predict(
            attitude_mixture(args.batch, 5, True, gen), torch.full((args.batch, 3), 0.06, dtype=torch.float64), 0.1
        )
        row = {
            "what": f"{args.update} adaptive predict B={args.batch} N=5 6-state",
            "batch": args.batch,
            "update": args.update,
        }
    print(json.dumps({**row, "peak_rss_mib": peak_resident_memory() / 2**20}))


if __name__ == "__main__":
    main()
