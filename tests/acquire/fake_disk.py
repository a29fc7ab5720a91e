"""Run ``acquire`` on a simulated small disk: ``python fake_disk.py BUDGET_BYTES run PLAN …``.

Stands in for a tiny tmpfs (not available to tests): the run log's system calls
(``acquire.record.logstorage``: write, posix_fallocate, unlink) share a budget of BUDGET_BYTES. A write
that does not fit is cut short at the budget, as the kernel does when a disk fills, and the next
one fails with ENOSPC; removing the reserve gives its bytes back. From the moment the disk was
first full, the run's text log fails too (its writes and flushes raise ENOSPC): another writer
takes the space the reserve freed.
"""

from __future__ import annotations

import errno
import os
import sys

import acquire.live.console as console
import acquire.record.logstorage as storage

state = {"left": 0, "sizes": {}, "full": False}
real_write, real_fallocate, real_unlink = storage._write, storage._fallocate, storage._unlink


def no_space():
    state["full"] = True
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def write(fd, data):
    n = len(data)
    if n <= state["left"]:
        state["left"] -= n
        return real_write(fd, data)
    if state["left"] == 0:
        no_space()
    k, state["left"] = state["left"], 0
    state["full"] = True
    return real_write(fd, bytes(data[:k]))


def fallocate(fd, offset, size):
    ino = os.fstat(fd).st_ino
    grow = max(0, size - state["sizes"].get(ino, 0))
    if grow > state["left"]:
        no_space()
    state["left"] -= grow
    state["sizes"][ino] = state["sizes"].get(ino, 0) + grow
    return real_fallocate(fd, offset, size)


def unlink(path):
    state["left"] += state["sizes"].pop(os.stat(path).st_ino, 0)
    return real_unlink(path)


class FullStream:
    """The text log's stream once the disk has been full."""

    def __init__(self, f):
        self.f = f

    def write(self, text):
        if state["full"]:
            no_space()
        return self.f.write(text)

    def flush(self):
        if state["full"]:
            no_space()
        self.f.flush()

    def close(self):
        self.f.close()


if __name__ == "__main__":  # not in the exchange processes, which import this file as __mp_main__
    state["left"] = int(sys.argv[1])
    sys.argv = ["acquire", *sys.argv[2:]]
    storage._write, storage._fallocate, storage._unlink = write, fallocate, unlink
    real_open = console.TextLogHandler._open
    console.TextLogHandler._open = lambda self: FullStream(real_open(self))

    from acquire.cli import main

    sys.exit(main())
