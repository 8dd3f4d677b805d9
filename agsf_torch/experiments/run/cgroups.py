"""The memory a Linux control group still allows this process.

A container or a batch scheduler (Docker ``--memory``, Kubernetes, Slurm, systemd) limits a process's memory below
what the machine reports free (``MemAvailable``); the memory checks of :mod:`agsf_torch.experiments.run.resources` read the
group's limit as well (:func:`memory_headroom`).  Kept by hand because no library reads it (psutil's available memory
and ``/proc/meminfo`` are the machine's; joblib reads the CPU quota only, ``joblib.cpu_count``).

Both cgroup versions are read.  This process's group comes from ``/proc/self/cgroup`` and the hierarchies' mounts
from ``/proc/self/mountinfo`` (the mount whose root holds the group; its fields' octal escapes decoded); a limit set
on an enclosing group applies too, so every group from this process's up to the top of its mount is read and the
tightest limit wins.  Where the group does not resolve under the mount — a container whose cgroup namespace hides
the host's path, or a nested namespace whose mount root lies outside it (``/..``) — the mount's own group is read:
it encloses this process's, so its limits apply, though a tighter one below it cannot be seen from here.

Memory in use is the group's *working set*, as container runtimes count it: its usage less the page cache it
can drop at once (``inactive_file`` of ``memory.stat``): a group that has written more files than its limit
holds them in cache, close to the limit, without being short of memory.
"""

from __future__ import annotations

import re
from pathlib import Path

__all__ = ["memory_headroom"]

#: The files :func:`memory_headroom` reads, ``(limit, usage)``: v1, v2.
_V1_MEMORY = ("memory.limit_in_bytes", "memory.usage_in_bytes")
_V2_MEMORY = ("memory.max", "memory.current")
#: A v1 memory limit at or above this is "no limit" (the kernel reports ``PAGE_COUNTER_MAX`` pages, ~2⁶³ bytes).
_V1_UNLIMITED = 2**60


def _groups(controller: str, proc: Path) -> list[Path]:
    """The folders of this process's cgroup and of its enclosing groups up to the top of the mount, innermost
    first, in the hierarchy holding ``controller`` (v1) or in the unified one (v2, ``controller = ""``)."""
    try:  # paths are bytes to the kernel: one not in UTF-8 is kept as surrogates (os.fsencode gives it back)
        memberships = (proc / "self" / "cgroup").read_text(errors="surrogateescape").splitlines()
        mounts = (proc / "self" / "mountinfo").read_text(errors="surrogateescape").splitlines()
    except OSError:
        return []
    path = None
    for line in memberships:
        parts = line.split(":", 2)
        if len(parts) == 3 and (controller in parts[1].split(",") if controller else parts[0] == "0"):
            path = parts[2]
    if path is None:
        return []
    candidates = []  # (root, mount point) of the hierarchy's mounts
    for line in mounts:
        fields = line.split()
        if " - " not in line or len(fields) < 5:
            continue
        fstype, _, options = line.split(" - ", 1)[1].partition(" ")
        options = options.split()[-1].split(",") if options.split() else []
        if fstype == "cgroup2" if not controller else (fstype == "cgroup" and controller in options):
            candidates.append((_unescape(fields[3]), Path(_unescape(fields[4]))))
    # the mounts whose root encloses the group, shallowest first: each shows the same hierarchy, so the shallowest
    # under which the group's folder exists shows every enclosing group
    holding = sorted(
        ((root, point) for root, point in candidates if Path(path).is_relative_to(root)),
        key=lambda mount: len(Path(mount[0]).parts),
    )
    found = next(((r, p) for r, p in holding if (p / Path(path).relative_to(r)).is_dir()), None)
    if found is not None:
        point = found[1]
        start = point / Path(path).relative_to(found[0])
    elif holding:  # the group's path hidden (a cgroup namespace): the mount's own group encloses it
        point = start = holding[0][1]
    else:  # a mount rooted above a nested namespace (only "..": an enclosing group); a sibling's is not read
        above = [p for r, p in candidates if Path(r).is_absolute() and set(Path(r).parts[1:]) == {".."}]
        if not above:
            return []
        point = start = above[0]
    return [start, *[p for p in start.parents if p.is_relative_to(point)]]


def _unescape(field: str) -> str:
    """A ``mountinfo`` path field with the kernel's octal escapes (``\\040`` a space, ``\\011`` a tab, ``\\012`` a
    newline, ``\\134`` a backslash) decoded."""
    return re.sub(r"\\([0-7]{3})", lambda m: chr(int(m.group(1), 8)), field)


def _read(folder: Path, name: str) -> list[str] | None:
    """The words of a cgroup file, or None where it is absent or unreadable."""
    try:
        return (folder / name).read_text(errors="replace").split()
    except OSError:
        return None


def memory_headroom(proc: Path = Path("/proc")) -> int | None:
    """Bytes this process's control groups still allow (limit − working set, at least 0; the working set is the
    usage less the droppable page cache, module docstring), the tightest over the enclosing groups of both cgroup
    versions; ``None`` where no group sets a memory limit.

    Args:
        proc: the ``/proc`` to read (tests pass a fake tree).
    """
    room = []
    for controller, (limit_file, usage_file), cache in (
        ("", _V2_MEMORY, ("inactive_file",)),
        ("memory", _V1_MEMORY, ("total_inactive_file", "inactive_file")),  # v1: the hierarchy's, as its usage
    ):
        for folder in _groups(controller, proc):
            limit, usage = _read(folder, limit_file), _read(folder, usage_file)
            if limit and usage and limit[0].isdigit() and usage[0].isdigit() and int(limit[0]) < _V1_UNLIMITED:
                working = max(int(usage[0]) - _stat(folder, cache), 0)
                room.append(max(int(limit[0]) - working, 0))
    return min(room) if room else None


def _stat(folder: Path, keys: tuple[str, ...]) -> int:
    """The first of ``keys`` found in the group's ``memory.stat`` (bytes), else 0."""
    words = _read(folder, "memory.stat") or []
    values = dict(zip(words[::2], words[1::2]))
    for key in keys:
        if values.get(key, "").isdigit():
            return int(values[key])
    return 0
