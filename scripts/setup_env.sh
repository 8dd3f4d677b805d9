#!/usr/bin/env bash
# Create (or reuse) the project's virtual environment in .venv and install the
# package with its dev, ray and docs extras, every version pinned by constraints.txt.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$here"
python="${PYTHON:-python3}"
if [ ! -x .venv/bin/python ]; then
    "$python" -m venv .venv
fi
stamp=.venv/.agsf-installed
extras="dev,ray,docs"
want="$( (cat constraints.txt pyproject.toml; echo "extras=$extras") | sha256sum | cut -d' ' -f1)"
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
    echo "installing agsf-torch[$extras] and its pinned dependencies into .venv (the first time: a few minutes)..." >&2
    .venv/bin/python -m pip install --quiet --upgrade pip
    # not --quiet: pip's download and install progress is the only sign of life for minutes
    .venv/bin/python -m pip install -c constraints.txt -e ".[$extras]"
    echo "$want" > "$stamp"
fi
# the package's bytecode, written once here: where PYTHONDONTWRITEBYTECODE is set (this project's CI machines set
# it) every process would otherwise compile the sources again at import (~0.1 s of every agsf command's start)
.venv/bin/python -m compileall -q agsf_torch envs >/dev/null
