"""``scripts/main.sh`` runs the reproduction with its progress shown and ends by naming its outputs
(run here against stand-ins for the environment setup and the ``agsf`` command)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

MAIN = Path(__file__).resolve().parents[2] / "scripts" / "main.sh"


def _checkout(tmp_path: Path) -> Path:
    """A copy of main.sh in a folder whose setup is a no-op and whose ``agsf`` records its arguments."""
    root = tmp_path / "checkout"
    (root / "scripts").mkdir(parents=True)
    shutil.copy(MAIN, root / "scripts" / "main.sh")
    (root / "scripts" / "setup_env.sh").write_text("#!/usr/bin/env bash\n")
    agsf = root / ".venv" / "bin" / "agsf"
    agsf.parent.mkdir(parents=True)
    agsf.write_text(
        "#!/usr/bin/env bash\n"
        'echo "$@" > "$(dirname "$0")/args"\n'
        'while [ $# -gt 0 ]; do if [ "$1" = --out ]; then mkdir -p "$2"; fi; shift; done\n'
        'echo "TensorBoard: tensorboard-command"\n'
    )
    agsf.chmod(0o755)
    return root


def test_main_shows_progress_and_ends_with_the_output_folder(tmp_path):
    root = _checkout(tmp_path)
    done = subprocess.run(["bash", str(root / "scripts" / "main.sh")], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    args = (root / ".venv" / "bin" / "args").read_text().split()
    assert args[:3] == ["reproduce", "--case", "all"] and "--quiet" not in args
    assert args[args.index("--out") + 1] == "runs/reproduce"
    assert "reproducing the paper's three cases into runs/reproduce" in done.stderr
    lines = done.stdout.splitlines()
    assert lines[0] == "TensorBoard: tensorboard-command"  # the command's own report comes through
    assert lines[-1].startswith("main job done in ") and lines[-1].endswith(
        f"outputs in {root / 'runs' / 'reproduce'}/"
    )


def test_main_never_overwrites_an_earlier_result(tmp_path):
    root = _checkout(tmp_path)
    (root / "runs" / "reproduce").mkdir(parents=True)
    (root / "runs" / "reproduce" / "experiment.json").write_text("{}")
    done = subprocess.run(["bash", str(root / "scripts" / "main.sh")], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    out = (root / ".venv" / "bin" / "args").read_text().split("--out ")[1].split()[0]
    assert out.startswith("runs/reproduce-") and out != "runs/reproduce"
    assert done.stdout.splitlines()[-1].endswith(f"outputs in {root / out}/")
