#!/usr/bin/env bash
# Set up .venv (pinned) and run the main job: the paper's three cases (star frames
# at 1, 0.5 and 0.2 Hz), 100 Monte Carlo runs each, EKF / GSF / adaptive GSF with the
# paper's and with the Galerkin weight update on identical truth and measurements
# (5.6–6 s on 2 idle cores of an AMD EPYC VM, the three cases side by side; several times longer when the cores
# are shared; a few minutes the first time on a machine, which compiles the filters' kernels once).  Progress bars on stderr; at the end,
# the tables and where the outputs are (folder, results.md, figures, the TensorBoard command).
set -euo pipefail
if [ "${1:-}" = "-h" ] || [ "${1:-}" = "--help" ]; then
    echo "usage: bash scripts/main.sh [OUT]   (set up .venv, then agsf reproduce --case all --out OUT;"
    echo "       OUT defaults to runs/reproduce, or runs/reproduce-<date> if that already holds a result)"
    exit 0
fi
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$here"
bash scripts/setup_env.sh
out="${1:-runs/reproduce}"
if [ -e "$out/experiment.json" ]; then
    out="$out-$(date +%Y%m%d-%H%M%S)"   # never overwrite an earlier result
fi
echo "reproducing the paper's three cases into $out (about 6-10 s on 2 idle cores; a few minutes the first time, compiling)..." >&2
start=$SECONDS
.venv/bin/agsf reproduce --case all --out "$out"
echo "main job done in $((SECONDS - start)) s; outputs in $(cd "$out" && pwd)/"
