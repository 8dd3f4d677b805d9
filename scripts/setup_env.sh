#!/usr/bin/env bash
# Create (or reuse) the project's virtual environment in .venv and install the
# package with its dev and ray extras, every version pinned by constraints.txt.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$here"
python="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
    "$python" -m venv .venv
fi
stamp=.venv/.agsf-installed
extras="dev,ray"
want="$( (cat constraints.txt pyproject.toml; echo "extras=$extras") | sha256sum | cut -d' ' -f1)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
    .venv/bin/python -m pip install --quiet --upgrade pip
    .venv/bin/python -m pip install --quiet -c constraints.txt -e ".[$extras]"
    echo "$want" > "$stamp"
fi
