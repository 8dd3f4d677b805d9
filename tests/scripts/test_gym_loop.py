"""``scripts/gym_loop.py`` shows its progress while it runs."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "gym_loop.py"


def test_gym_loop_shows_a_progress_bar_over_its_steps():
    done = subprocess.run(
        [sys.executable, str(SCRIPT), "--steps", "4", "--batch", "2"],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr
    assert "gym loop" in done.stderr and "4/4" in done.stderr  # tqdm's bar on stderr, to the last step
    assert done.stdout.startswith("mean reward")
