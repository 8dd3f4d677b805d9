#!/usr/bin/env bash
# Set up .venv (pinned) and build the documentation site into docs/_build/html (Sphinx: the MyST pages of docs/
# and the API reference from the docstrings); every warning is an error.  -E reads every page afresh, so a warning
# of an unchanged page is not hidden by the environment a failed build saved.  Then open docs/_build/html/index.html.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$here"
bash scripts/setup_env.sh
.venv/bin/python -m sphinx -E -W --keep-going -b html docs docs/_build/html "$@"
echo "documentation: $here/docs/_build/html/index.html"
