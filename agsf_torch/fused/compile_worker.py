"""A worker process of :func:`agsf_torch.fused.lanes.compiling_in_parallel`: compiles one kernel into the cache.

``python -m agsf_torch.fused.compile_worker JOB`` reads ``JOB`` (a pickle of the kernel, its export sample,
its shared tensors, the cache path, the variant and the caller's thread count), compiles the kernel ahead of time into that path
(written atomically) and prints the seconds it took.
"""

from __future__ import annotations

import pickle
import sys
import time
from pathlib import Path

from ..torch_internals import torch_internal_deprecations_hidden
from .lanes import compile_ahead_of_time


def main(job: str) -> None:
    kernel, inputs, shared, path, serial, threads = pickle.loads(Path(job).read_bytes())
    t0 = time.perf_counter()
    if not Path(path).is_file():
        with torch_internal_deprecations_hidden():
            compile_ahead_of_time(kernel, inputs, shared, Path(path), serial, threads)
    print(f"{time.perf_counter() - t0:.1f}")


if __name__ == "__main__":
    main(sys.argv[1])
