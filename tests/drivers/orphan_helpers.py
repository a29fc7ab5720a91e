"""Helpers for the parent-death tests: a commander owned by a child process we can kill -9."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


class CommanderProcess:
    """``python -c script`` with the repository (and ``tests/drivers/<pkg>``) importable; the
    script talks in lines on stdout and waits for lines on stdin."""

    def __init__(self, script: str, helpers_dir: Path) -> None:
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(helpers_dir), env.get("PYTHONPATH", "")])
        self.proc = subprocess.Popen(
            [sys.executable, "-c", script], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env,
        )

    def expect(self, prefix: str) -> str:
        """The next stdout line, which must start with ``prefix``; returns the rest."""
        line = self.proc.stdout.readline()
        assert line.startswith(prefix), f"expected {prefix!r} from the commander process, got {line!r}"
        return line[len(prefix):].strip()

    def say(self, line: str) -> None:
        self.proc.stdin.write(line + "\n")
        self.proc.stdin.flush()

    def kill9(self) -> None:
        self.proc.kill()  # SIGKILL: no handler, no atexit, no finally
        self.proc.wait(5.0)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(5.0)
        for f in (self.proc.stdin, self.proc.stdout):
            f.close()


def process_ended(pid: int, timeout: float) -> bool:
    """True once ``pid`` no longer runs (gone, or a zombie nobody reaped yet) within ``timeout``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            status = Path(f"/proc/{pid}/status").read_text()
        except (FileNotFoundError, ProcessLookupError):
            return True
        if "\nState:\tZ" in status or "\nState:\tX" in status:
            return True
        time.sleep(0.02)
    return False
