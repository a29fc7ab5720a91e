"""The daemon's runs folder and plan requests: which runs it holds, where a run's log is, which
plan file a ``start`` request means (``plan`` inside ``plan_dirs``, or ``plan_text`` written to
``<state_dir>/plans``). Errors are ``acquire.daemon.control.BadRequest`` saying what is allowed."""

from __future__ import annotations

import logging
from datetime import datetime, timezone
from pathlib import Path

from acquire.daemon.control import BadRequest
from acquire.record.recorder import base_path

log = logging.getLogger("acquire.daemon.service")


def list_runs(runs_dir: Path, current: str | None) -> list[dict]:
    """One entry per run in ``runs_dir`` (its resume segments counted with it); ``current``:
    the id of the active run, if any."""
    out = []
    for p in sorted(runs_dir.glob("*/*.mcap")):
        if base_path(p) != p:
            continue  # a resume segment (RUN.resume1.mcap) belongs to the run of RUN.mcap
        segments = [p, *sorted(p.parent.glob(p.stem + ".resume*.mcap"))]
        st = p.stat()
        out.append({
            "run_id": p.parent.name,
            "file": p.name,
            "segments": len(segments),
            "bytes": sum(s.stat().st_size for s in segments),
            "modified": datetime.fromtimestamp(st.st_mtime, timezone.utc).isoformat(timespec="seconds"),
            "current": p.parent.name == current,
            "result": (p.parent / "result.json").exists() or any(p.parent.glob("*result.json")),
        })
    return out


def run_log(runs_dir: Path, run_id: str) -> Path:
    """The first log segment of run ``run_id`` in ``runs_dir``."""
    if "/" in run_id or run_id in ("", ".", ".."):
        raise BadRequest(f"run_id {run_id!r} is not a run id")
    path = runs_dir / run_id / f"{run_id}.mcap"
    if not path.is_file():
        known = sorted(p.name for p in runs_dir.iterdir() if p.is_dir())
        raise BadRequest(f"no run {run_id!r} in {runs_dir}; known: {known}")
    return path


def plan_path(cfg, request: dict) -> Path:
    """The plan file a ``start`` request means (``cfg``: the ``DaemonConfig``)."""
    plan, text = request.get("plan"), request.get("plan_text")
    if (plan is None) == (text is None):
        raise BadRequest("start needs exactly one of 'plan' (a path on the cell PC) or 'plan_text' (YAML)")
    if text is not None:
        if not cfg.allow_inline_plans:
            raise BadRequest("inline plans are disabled (allow_inline_plans: false); give 'plan'")
        if not isinstance(text, str):
            raise BadRequest(f"plan_text must be a string, given {type(text).__name__}")
        folder = cfg.state_dir / "plans"
        folder.mkdir(parents=True, exist_ok=True)
        stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S%f")
        path = folder / f"inline-{stamp}.yaml"
        path.write_text(text, encoding="utf-8")
        return path
    if not isinstance(plan, str) or not plan:
        raise BadRequest(f"plan must be a path string, given {plan!r}")
    dirs = [d.resolve() for d in cfg.plan_dirs]
    if not dirs:
        raise BadRequest("no plan_dirs configured: plans can only be sent inline ('plan_text')")
    p = Path(plan)
    p = (p if p.is_absolute() else dirs[0] / p).resolve()
    if not any(p.is_relative_to(d) for d in dirs):
        raise BadRequest(f"plan {plan!r} is not inside the allowed plan folders {[str(d) for d in dirs]}")
    if not p.is_file():
        raise BadRequest(f"plan {str(p)!r} does not exist")
    return p


class RunTextLog:
    """The current run's text log ``<run>.log`` beside its MCAP (``acquire.live.console.RunLogFile``,
    archived with the run): begun when a run starts, opened once the run knows its log path,
    closed when the run ends or fails to start."""

    def __init__(self) -> None:
        self._file = None

    def begin(self) -> None:
        """Collect the log lines of a run about to start (until ``open_beside`` finds its path)."""
        from acquire.live.console import RunLogFile

        self.close()
        self._file = RunLogFile(logging.INFO)

    def open_beside(self, ctl) -> None:
        """Open the file beside ``ctl``'s MCAP log once it has one (no-op before, or when open)."""
        logfile = self._file
        if ctl is None or logfile is None or logfile.path is not None:
            return
        path = ctl.status().get("log")
        if path:
            try:
                logfile.open(path)
            except OSError as exc:
                log.warning("no text log beside %s: %s", path, exc)
                self._file = None
                logfile.close()

    def close(self) -> None:
        """Close the file; a run that never made a folder has its held lines on stderr only where
        the daemon's own log did not show them (below INFO: the daemon logs INFO and above)."""
        logfile, self._file = self._file, None
        if logfile is not None:
            logfile.close(logging.INFO)


def announce_run_end(bus, status: dict) -> None:
    """A hint for the plant's station that this cell has a finished run to list now (the listing
    itself is authenticated); a lost hint costs the station one poll."""
    import zenoh

    from acquire.live.bus import BusError

    try:
        bus.publish(bus.key("archive", "ready"), {"run_id": status["run_id"], "state": status["state"]})
    except (BusError, zenoh.ZError) as exc:
        log.debug("archive/ready not announced: %s", exc)
