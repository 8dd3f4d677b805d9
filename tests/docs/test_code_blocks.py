"""Every Python block of the user guide (``docs/guide/*.md``) and of the README runs.

The blocks of one file run in order in one namespace (``mktestdocs.check_md_file(..., memory=True)``), so a
page reads as one session.  A block that cannot run in a test is written as ``bash`` or ``text``: every fenced
block must name one of the languages below, so that no block is skipped silently (mktestdocs runs only blocks
opened by exactly three backticks and ``python``).
"""

from __future__ import annotations

import re
from pathlib import Path

import mktestdocs
import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]
FILES = sorted((ROOT / "docs" / "guide").glob("*.md")) + [ROOT / "README.md"]
#: Languages a fenced block may have: ``python`` runs, the others are shown only.
LANGUAGES = {"python", "bash", "text", "toml"}
_FENCE = re.compile(r"^(\s*)(`{3,}|~{3,})(.*)$")


def fenced_blocks(text: str) -> list[str]:
    """The info string (language) of every fenced block, in order (CommonMark fences: ``` or ~~~)."""
    infos, fence = [], None
    for line in text.splitlines():
        m = _FENCE.match(line)
        if not m:
            continue
        mark, info = m.group(2), m.group(3).strip()
        if fence is None:
            fence = mark
            infos.append(info)
        elif mark[0] == fence[0] and len(mark) >= len(fence) and not info:
            fence = None
    assert fence is None, "a fenced block is not closed"
    return infos


def test_the_guide_and_the_readme_are_covered():
    names = {p.name for p in FILES}
    assert {"README.md", "filters.md", "environment.md"} <= names
    assert all(p.is_file() for p in FILES)


@pytest.mark.parametrize("path", FILES, ids=[str(p.relative_to(ROOT)) for p in FILES])
def test_python_blocks_run(path: Path, monkeypatch: pytest.MonkeyPatch, tmp_path: Path):
    text = path.read_text(encoding="utf-8")
    infos = fenced_blocks(text)
    unknown = [info for info in infos if info not in LANGUAGES and not info.startswith("{")]
    assert not unknown, (
        f"{path.name}: fenced blocks must be one of {sorted(LANGUAGES)} (or a MyST directive): {unknown}"
    )
    python = sum(info == "python" for info in infos)
    assert len(mktestdocs.grab_code_blocks(text, lang="python")) == python, f"{path.name}: a python block is not run"
    if path.name == "README.md":
        assert python >= 1, "the README's library example"
    monkeypatch.chdir(tmp_path)  # anything a block writes relative to the working directory stays in tmp_path
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # small batches: one thread is fastest, and no oversubscription beside xdist workers
    try:
        mktestdocs.check_md_file(path, memory=True)
    finally:
        torch.set_num_threads(threads)
