#!/usr/bin/env bash
# Set up .venv (pinned) and run the main job: a batched Monte Carlo of the paper's
# case 1 with the EKF, the classic GSF and the adaptive GSF (about 1 minute on 2 cores).
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$here"
bash scripts/setup_env.sh
out="${1:-runs/case1-quick}"
.venv/bin/agsf montecarlo --runs 100 --duration 30 --out "$out" --quiet
echo "results: $out/summary.json and $out/rms.png"
