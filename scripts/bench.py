"""Thin entry point for the benchmark: ``python scripts/bench.py [--quick] [--out DIR]`` = ``agsf bench``."""

import sys

from agsf_torch.experiments.cli.main import main

if __name__ == "__main__":
    sys.exit(main(["bench", *sys.argv[1:]]))
