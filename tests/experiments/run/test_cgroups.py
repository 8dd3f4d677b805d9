"""Control-group memory limits (agsf_torch.experiments.run.cgroups) on fake /proc and cgroup trees, and their use by the memory
budget."""

from __future__ import annotations

from pathlib import Path

import pytest

from agsf_torch.experiments.run import resources
from agsf_torch.experiments.run.cgroups import memory_headroom
from tests.helpers import assert_within


def fake_system(tmp_path: Path, memberships: list[str], mounts: list[tuple[str, str, str, str]], files: dict) -> Path:
    """A ``/proc`` whose ``self/cgroup`` lists ``memberships`` and whose ``self/mountinfo`` mounts each ``(root,
    folder under tmp_path, fstype, super options)``; ``files`` maps paths under ``tmp_path`` to their contents."""
    proc = tmp_path / "proc"
    (proc / "self").mkdir(parents=True)
    (proc / "self" / "cgroup").write_text("\n".join(memberships) + "\n")
    lines = [
        f"{30 + i} 23 0:{28 + i} {root} {tmp_path / point} rw,relatime - {fstype} cgroup {options}"
        for i, (root, point, fstype, options) in enumerate(mounts)
    ]
    (proc / "self" / "mountinfo").write_text("\n".join(lines) + "\n")
    for path, text in files.items():
        (tmp_path / path).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / path).write_text(text)
    return proc


V2_MOUNT = [("/", "cg", "cgroup2", "rw,nsdelegate")]


def limit(folder: str, limit: int, used: int = 0) -> dict[str, str]:
    """The files of a v2 group at ``folder`` (under tmp_path) that limits its memory to ``limit`` bytes, ``used`` in
    use: its headroom is ``limit - used``."""
    return {f"{folder}/memory.max": f"{limit}\n", f"{folder}/memory.current": f"{used}\n"}


def test_v2_limit_of_the_process_group(tmp_path):
    proc = fake_system(tmp_path, ["0::/job/task"], V2_MOUNT, limit("cg/job/task", 150000, 50000))
    assert memory_headroom(proc) == 100000


def test_v2_unlimited_and_malformed_limits_are_no_limit(tmp_path):
    files = {**limit("cg/job", 0), "cg/job/memory.max": "max\n", **limit("cg", 0), "cg/memory.max": "garbage\n"}
    proc = fake_system(tmp_path, ["0::/job"], V2_MOUNT, files)
    assert memory_headroom(proc) is None


def test_the_tightest_enclosing_group_wins(tmp_path):
    files = {**limit("cg/a/b", 400000), **limit("cg/a", 200000), **limit("cg", 800000)}
    proc = fake_system(tmp_path, ["0::/a/b"], V2_MOUNT, files)
    assert memory_headroom(proc) == 200000


def test_a_namespaced_container_reads_its_own_mount(tmp_path):
    """The host's path of the group (``/docker/abc``) does not exist under the container's mount, which is the
    container's own group."""
    proc = fake_system(tmp_path, ["0::/docker/abc"], V2_MOUNT, limit("cg", 50000))
    assert memory_headroom(proc) == 50000


def test_no_cgroup_file_system(tmp_path):
    proc = tmp_path / "proc"
    proc.mkdir()
    assert memory_headroom(proc) is None
    other = fake_system(tmp_path / "x", ["0::/"], [("/", "tmpfs", "tmpfs", "rw")], {})
    assert memory_headroom(other) is None


def test_memory_headroom_v1_and_v2_the_tightest_wins(tmp_path):
    mounts = [*V2_MOUNT, ("/", "memory", "cgroup", "rw,memory")]
    files = {
        "cg/svc/memory.max": "1000000\n",
        "cg/svc/memory.current": "400000\n",
        "memory/svc/memory.limit_in_bytes": "800000\n",
        "memory/svc/memory.usage_in_bytes": "500000\n",
        "memory/memory.limit_in_bytes": "9223372036854771712\n",  # v1's "no limit"
        "memory/memory.usage_in_bytes": "10\n",
    }
    proc = fake_system(tmp_path, ["5:memory:/svc", "0::/svc"], mounts, files)
    assert memory_headroom(proc) == 300000
    (tmp_path / "memory/svc/memory.usage_in_bytes").write_text("900000\n")  # over its limit: no room, not negative
    assert memory_headroom(proc) == 0
    (tmp_path / "memory/svc/memory.limit_in_bytes").write_text("9223372036854771712\n")
    assert memory_headroom(proc) == 600000
    (tmp_path / "cg/svc/memory.max").write_text("max\n")
    assert memory_headroom(proc) is None


def test_available_memory_is_capped_by_the_groups_headroom(monkeypatch):
    unlimited = resources.available_memory()
    monkeypatch.setattr(resources, "memory_headroom", lambda: 1000)
    capped = resources.available_memory()
    assert capped < unlimited
    # the process's own memory added: its resident set, read twice a moment apart (statm, then status)
    resident = resources.resident_memory()
    assert_within(capped - 1000, resident, 0.05 * resident, "resident memory added to the headroom")


def test_this_machine_reads_without_error():
    """Whatever this machine's groups say, the reader returns a number or None."""
    value = memory_headroom()
    assert value is None or value >= 0


def test_escaped_mount_points_are_decoded(tmp_path):
    """The kernel writes a space in a mount point as ``\\040``."""
    proc = fake_system(tmp_path, ["0::/"], [], limit("my cg", 50000))
    (proc / "self" / "mountinfo").write_text(f"30 23 0:28 / {tmp_path}/my\\040cg rw - cgroup2 cgroup rw\n")
    assert memory_headroom(proc) == 50000


def test_of_the_mounts_that_show_the_group_the_shallowest_is_read(tmp_path):
    """Every mount of a hierarchy shows the same groups: the whole tree's shows the enclosing ``machine.slice`` and its
    limit, a bind of the service's group alone does not, whatever the order of the mounts."""
    mounts = [("/machine.slice/svc", "svc-only", "cgroup2", "rw"), ("/", "whole", "cgroup2", "rw")]
    files = {**limit("whole/machine.slice", 100000), **limit("whole/machine.slice/svc", 0), **limit("svc-only", 0)}
    files["whole/machine.slice/svc/memory.max"] = files["svc-only/memory.max"] = "max\n"
    proc = fake_system(tmp_path, ["0::/machine.slice/svc"], mounts, files)
    assert memory_headroom(proc) == 100000


def test_a_group_shown_by_a_deeper_mount_only_is_read_there(tmp_path):
    mounts = [("/", "whole", "cgroup2", "rw"), ("/machine.slice/svc", "svc-only", "cgroup2", "rw")]
    (tmp_path / "whole").mkdir()  # the whole tree's mount does not show the group's folder
    proc = fake_system(tmp_path, ["0::/machine.slice/svc"], mounts, limit("svc-only", 50000))
    assert memory_headroom(proc) == 50000


def test_a_siblings_mount_is_not_read(tmp_path):
    """A mount rooted at another group beside this process's (``/../other``) sets none of its limits."""
    proc = fake_system(tmp_path, ["0::/"], [("/../other", "cg", "cgroup2", "rw")], limit("cg", 50000))
    assert memory_headroom(proc) is None


def test_a_mount_point_not_in_utf8_is_read(tmp_path):
    """Paths are bytes to the kernel; one that is not UTF-8 elsewhere in the table does not stop the reader."""
    proc = fake_system(tmp_path, ["0::/"], V2_MOUNT, limit("cg", 200000))
    with open(proc / "self" / "mountinfo", "ab") as fh:
        fh.write(b"41 23 0:40 / /media/Caf\xe9 rw - vfat /dev/sdb1 rw\n")
    assert memory_headroom(proc) == 200000


def test_a_mount_rooted_outside_a_nested_namespace_is_read_as_an_enclosing_group(tmp_path):
    """``/..``: the mount shows a group above this namespace's; its limit applies to this process too."""
    proc = fake_system(tmp_path, ["0::/"], [("/../..", "cg", "cgroup2", "rw")], limit("cg", 100000))
    assert memory_headroom(proc) == 100000


@pytest.mark.parametrize(
    ("mounts", "membership", "limit_file", "usage_file", "stat"),
    [
        (V2_MOUNT, "0::/svc", "cg/svc/memory.max", "cg/svc/memory.current", "inactive_file 700000\n"),
        (
            [("/", "memory", "cgroup", "rw,memory")],
            "5:memory:/svc",
            "memory/svc/memory.limit_in_bytes",
            "memory/svc/memory.usage_in_bytes",
            "inactive_file 1\ntotal_inactive_file 700000\n",  # v1: the hierarchy's, as its usage
        ),
    ],
)
def test_the_page_cache_a_group_can_drop_is_not_counted_as_used(
    tmp_path, mounts, membership, limit_file, usage_file, stat
):
    """A group that has written more files than its limit sits at its limit in page cache without being short of
    memory: its working set is the usage less ``inactive_file``."""
    folder = str(Path(limit_file).parent)
    files = {limit_file: "1000000\n", usage_file: "990000\n", f"{folder}/memory.stat": f"anon 290000\n{stat}"}
    proc = fake_system(tmp_path, [membership], mounts, files)
    assert memory_headroom(proc) == 1000000 - (990000 - 700000)
    (tmp_path / folder / "memory.stat").write_text("anon 990000\n")  # nothing to drop
    assert memory_headroom(proc) == 10000
