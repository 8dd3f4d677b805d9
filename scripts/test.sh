#!/usr/bin/env bash
# Set up .venv (pinned) and run the test suite.  `--slow` runs only the slow tests.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$here"
bash scripts/setup_env.sh
if [ "${1:-}" = "--slow" ]; then
    shift
    exec .venv/bin/python -m pytest -m slow -n 2 "$@"
fi
exec .venv/bin/python -m pytest -n 2 "$@"
