"""Spare cores for the long, linear stages of a long recording (parsing a CSV, the pass over every set).

Both stages cut their work into independent pieces; with more than one usable core the pieces run
side by side and their results are combined in their own order, so the outcome is the same to the
last bit as one piece after another. ``MAGCAL_WORKERS`` (an integer, 1: never in parallel) overrides
the count of usable cores; nothing here starts anything for a short job.
"""

from __future__ import annotations

import mmap
import os
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

import numpy as np

T = TypeVar("T")
R = TypeVar("R")

MAX_WORKERS: int = 4
"""At most this many pieces run at once (the stages are bound by memory, not arithmetic)."""


def workers() -> int:
    """Pieces that may run at once: ``MAGCAL_WORKERS`` when set, else the usable cores (at most
    :data:`MAX_WORKERS`)."""
    given = os.environ.get("MAGCAL_WORKERS", "").strip()
    if given:
        try:
            return max(1, int(given))
        except ValueError:
            return 1
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    return max(1, min(cores, MAX_WORKERS))


def map_in_threads(fn: Callable[[T], R], items: Iterable[T]) -> list[R]:
    """``[fn(x) for x in items]``, in threads when there are several items and cores (for work that
    releases the GIL: large numpy operations)."""
    items = list(items)
    count = min(workers(), len(items))
    if count < 2:
        return [fn(x) for x in items]
    with ThreadPoolExecutor(count) as pool:
        return list(pool.map(fn, items))


def _single_threaded() -> bool:
    """True when this process runs one thread (Linux; then a fork copies no lock another thread holds)."""
    try:
        return len(os.listdir("/proc/self/task")) == 1
    except OSError:
        return False


def can_fork() -> bool:
    """Whether :func:`fill_in_child` may run its work in a child process here."""
    return hasattr(os, "fork") and workers() > 1 and _single_threaded()


def fill_in_child(nbytes: int, fill: Callable[[memoryview], bool]) -> ForkedFill | None:
    """Start ``fill(buffer)`` in a forked child, writing its result into ``nbytes`` of memory shared
    with this process; ``fill`` returns False when its input is not what it expected. Returns a handle
    to :meth:`ForkedFill.result` once this process has done its own share, or None when no child can
    be forked here (the caller then does the work itself)."""
    if not can_fork():
        return None
    buf = mmap.mmap(-1, max(nbytes, 1))  # anonymous and shared: the child's writes are seen here
    try:
        pid = os.fork()
    except OSError:
        buf.close()
        return None
    if pid == 0:  # the child: do the work, report by the exit status, never return into the caller
        code = 2
        try:
            code = 0 if fill(memoryview(buf)) else 1
        except BaseException:
            code = 2
        finally:
            os._exit(code)
    return ForkedFill(pid, buf)


class ForkedFill:
    """A child started by :func:`fill_in_child`."""

    def __init__(self, pid: int, buf: mmap.mmap) -> None:
        self.pid = pid
        self.buf = buf
        self.reaped = False

    def result(self) -> mmap.mmap | None:
        """Wait for the child: the shared memory it filled, or None when its input was not as expected
        or it failed (the caller then does that share itself)."""
        _, status = os.waitpid(self.pid, 0)
        self.reaped = True
        if os.waitstatus_to_exitcode(status) == 0:
            return self.buf
        self.buf.close()
        return None

    def cancel(self) -> None:
        """Stop and reap the child (this process failed, or was interrupted, before it had the result)."""
        if not self.reaped:  # (a reaped child's number may be another process's by now)
            try:
                os.kill(self.pid, 9)
                os.waitpid(self.pid, 0)
            except OSError:
                pass
            self.reaped = True
        if not self.buf.closed:
            self.buf.close()


def as_array(buf: mmap.mmap | memoryview, dtype: type, shape: tuple[int, ...], offset: int = 0) -> np.ndarray:
    """A numpy view of ``shape`` into ``buf`` at byte ``offset``."""
    count = int(np.prod(shape))
    return np.frombuffer(buf, dtype=dtype, count=count, offset=offset).reshape(shape)
