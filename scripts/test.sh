#!/usr/bin/env bash
# Set up .venv (pinned), check the tree with ruff (lint and format) and run the test suite.
# `--slow` runs only the slow tests.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$here"
bash scripts/setup_env.sh
if [ "${1:-}" = "--slow" ]; then
    shift
    exec .venv/bin/python -m pytest -m slow -n 2 "$@"
fi
.venv/bin/ruff check --quiet . || { echo "ruff check failed: .venv/bin/ruff check --fix . mends most" >&2; exit 1; }
.venv/bin/ruff format --check --quiet . || { echo "ruff format --check failed: .venv/bin/ruff format . reformats" >&2; exit 1; }
exec .venv/bin/python -m pytest -n 2 "$@"
