"""agsf_torch.allocator: the C allocator's mmap threshold, fixed so that a step's buffers come from the heap."""

import ctypes
import subprocess
import sys

import pytest

from agsf_torch import allocator
from agsf_torch.allocator import MAX_MMAP_THRESHOLD, set_mmap_threshold


def _glibc() -> bool:
    try:
        ctypes.CDLL(None).gnu_get_libc_version
    except (OSError, AttributeError):
        return False
    return sys.platform.startswith("linux")


glibc_only = pytest.mark.skipif(not _glibc(), reason="mallopt's mmap threshold is glibc's")

# a 4 MiB tensor alive while glibc's count of mapped blocks (mallinfo2().hblks) is read, before and after
_MAPPED_BLOCKS = """
import ctypes, sys, torch
from agsf_torch.allocator import set_mmap_threshold

class MallInfo2(ctypes.Structure):
    _fields_ = [(name, ctypes.c_size_t) for name in
                ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]

libc = ctypes.CDLL(None)
libc.mallinfo2.restype = MallInfo2

def mapped_while_alive():
    before = libc.mallinfo2().hblks
    t = torch.empty(512 * 1024, dtype=torch.float64)
    return libc.mallinfo2().hblks - before

default = mapped_while_alive()
print(default, set_mmap_threshold(), mapped_while_alive())
"""


@glibc_only
def test_after_the_call_a_few_mb_buffer_comes_from_the_heap_not_a_fresh_map():
    if not hasattr(ctypes.CDLL(None), "mallinfo2"):
        pytest.skip("mallinfo2 needs glibc 2.33")
    env = {k: v for k, v in __import__("os").environ.items() if k != "MALLOC_MMAP_THRESHOLD_"}
    out = subprocess.run([sys.executable, "-c", _MAPPED_BLOCKS], capture_output=True, text=True, check=True, env=env)
    assert out.stdout.split() == ["1", "True", "0"]


def test_the_users_own_environment_setting_is_kept(monkeypatch):
    monkeypatch.setenv("MALLOC_MMAP_THRESHOLD_", "1048576")
    assert set_mmap_threshold() is False


def test_a_platform_without_glibc_has_nothing_to_set(monkeypatch):
    monkeypatch.delenv("MALLOC_MMAP_THRESHOLD_", raising=False)
    monkeypatch.setattr(allocator.sys, "platform", "darwin")
    assert set_mmap_threshold() is False


@pytest.mark.parametrize("bad", [0, -1, MAX_MMAP_THRESHOLD + 1, 1.5, True, "32M", None])
def test_a_threshold_out_of_range_is_refused_naming_it(bad):
    with pytest.raises(ValueError, match=r"nbytes must be an integer from 1 to 33554432 \(32 MiB\), got"):
        set_mmap_threshold(bad)


def test_every_agsf_command_sets_it_before_it_runs(monkeypatch, capsys, tmp_path):
    from agsf_torch.experiments.cli import main as cli

    calls = []
    monkeypatch.setattr(cli, "set_mmap_threshold", lambda: calls.append(True))
    # refused input: the setting came first, harmlessly, and nothing was created
    assert cli.main(["reproduce", "--set", "no_such_key=1", "--out", str(tmp_path / "out")]) == 2
    assert calls == [True]
    assert "agsf: error:" in capsys.readouterr().err and not (tmp_path / "out").exists()
