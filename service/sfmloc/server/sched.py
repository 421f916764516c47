"""The scheduler time slice of a stream worker (Linux EEVDF, kernel 6.12+: ``sched_setattr``'s
``sched_runtime`` is a SCHED_OTHER task's slice, 0.1-100 ms).

Why: a worker is CPU-bound for a whole frame (~14 ms of CPU on the synthetic room, ~12 ms on
redkitchen). The kernel's default slice here is 1.4 ms (0.7 ms x (1 + log2 cores)), so when
several workers share a core (servers co-located on a machine, or one machine's workers beside
other CPU-bound tenants) each frame is cut into ~10 pieces, and every switch lands on another
process's working set (its map's index and descriptors, the frame's pyramids): the caches are
refilled every slice. With slices as long as a frame, a worker mostly finishes a frame before
another takes the core. Alone on a core nothing changes (no one to switch to); short wake-ups
(the server's Zenoh and pump threads keep the default slice) still preempt a long-slice worker
at once (EEVDF: a shorter slice has the earlier deadline).

Best effort: another OS, an older kernel or a refused call leave the kernel's default, and
``set_slice`` says so (False).
"""

from __future__ import annotations

import ctypes
import os
import platform
import struct

# sched_setattr / sched_getattr syscall numbers (no libc wrapper before glibc 2.41).
_SYSCALLS = {"x86_64": (314, 315), "aarch64": (274, 275), "arm64": (274, 275)}
# struct sched_attr (include/uapi/linux/sched/types.h), SCHED_ATTR_SIZE_VER1: size, policy,
# flags, nice, priority, runtime, deadline, period, util_min, util_max.
_ATTR = struct.Struct("IIqiIQQQII")
SCHED_OTHER = 0


def _calls() -> tuple[int, int] | None:
    if not hasattr(os, "sched_getaffinity"):  # not Linux
        return None
    return _SYSCALLS.get(platform.machine())


def get_slice_ns(tid: int = 0) -> int | None:
    """The slice (``sched_runtime``, ns) of thread ``tid`` (0: the calling thread), or None
    where it cannot be read."""
    calls = _calls()
    if calls is None:
        return None
    libc = ctypes.CDLL(None, use_errno=True)
    buf = ctypes.create_string_buffer(_ATTR.size)
    if libc.syscall(calls[1], int(tid), buf, _ATTR.size, 0) != 0:
        return None
    fields = _ATTR.unpack(buf.raw)
    return int(fields[5]) if fields[1] == SCHED_OTHER else None


def set_slice(tid: int, ms: float) -> bool:
    """Give thread ``tid`` (0: the calling thread; a process's pid is its main thread) a
    ``ms`` slice, keeping its nice value and policy (SCHED_OTHER only: another policy is left
    alone). True when the kernel took it."""
    calls = _calls()
    if calls is None or ms <= 0:
        return False
    libc = ctypes.CDLL(None, use_errno=True)
    buf = ctypes.create_string_buffer(_ATTR.size)
    if libc.syscall(calls[1], int(tid), buf, _ATTR.size, 0) != 0:
        return False
    _, policy, _, nice, *_ = _ATTR.unpack(buf.raw)
    if policy != SCHED_OTHER:
        return False
    attr = _ATTR.pack(_ATTR.size, SCHED_OTHER, 0, nice, 0, int(ms * 1e6), 0, 0, 0, 0)
    out = ctypes.create_string_buffer(attr, _ATTR.size)
    if libc.syscall(calls[0], int(tid), out, 0) != 0:
        return False
    got = get_slice_ns(tid)
    return got is not None and abs(got - int(ms * 1e6)) < 1000
