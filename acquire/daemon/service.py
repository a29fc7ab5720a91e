"""``acquire daemon``: the service on the cell PC.

Start-up (``Daemon.run``):

1. open the Zenoh session (``acquire.live.bus.Bus``) — by default the cell's *router*, listening on
   loopback only; remote listeners need mTLS or access control (``acquire.daemon.config``); its
   Unix-socket listeners (``unixsock-stream/…``) go to ``zenoh.socket_group``, mode 0660
   (``acquire.daemon.local_sockets``);
   with ``live.enabled``, start the Foxglove live view (``acquire.live.foxglove_server.LiveServer``), which then
   serves every run's log channels as they are written;
2. bring up the cell's devices (``DeviceHost``): the configured commander and sensors, or with
   ``fake`` the simulated cell ``acquire daemon`` started and handed over (a ``CellSource``),
   with a commander exchanging real-time packets with its controller; announce each with a liveliness token
   ``remaster/<cell>/device/<name>`` (and the daemon itself as ``remaster/<cell>/daemon``);
3. serve the control queries (``acquire.daemon.control``) — on Zenoh and, with ``control_socket``, on
   the operators' Unix socket (``acquire.daemon.control_socket``) — and tell systemd ``READY=1``.

Then, every ``tick`` (half the systemd watchdog interval, or ``status_interval_s``), a health
check (``HealthMonitor``): the commander's measured state is fresh and its late real-time
answers are not growing, and a running run's log is being written. While healthy the daemon
sends ``WATCHDOG=1``; while not, it stops pinging (systemd then restarts it) and says why in
``STATUS=``.

A run (``start`` query) gets the devices: the daemon closes its own connections (the run opens
the plan's drivers at the same ports, through the cell's description: ``cell_for_plan``), watches the run's commander instead, and takes the
devices back once the run ends.

SIGTERM/SIGINT: ``STOPPING=1``; a running run is paused (it finishes the configuration it is
measuring) or aborted (``shutdown.on_sigterm``), then aborted after ``shutdown.timeout_s`` at the
latest — the robot decelerates and the run's log is closed; then devices, queryables and the
session are closed. Exit status 0 after a clean stop, 1 when start-up failed.
"""

from __future__ import annotations

import gc
import logging
import os
import signal
import threading
import time
import tracemalloc
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from acquire.daemon.control import Authorizer, BadRequest, Conflict, ControlServer, Identity
from acquire.daemon.archive import CellRuns
from acquire.daemon.config import DaemonConfig
from acquire.daemon.devices import CellSource, DeviceHost, cell_for_plan  # noqa: F401 (DeviceHost: acquire.daemon.service's API)
from acquire.daemon.runs import RunTextLog, announce_run_end, list_runs, plan_path, run_log
from acquire.daemon.sdnotify import SdNotifier
from drivers.errors import DeviceTimeoutError, DriverError

log = logging.getLogger(__name__)

#: Run states in which the run holds the devices.
ACTIVE_STATES = ("starting", "running", "paused", "suspended", "stopping")


@dataclass(frozen=True)
class Health:
    """The outcome of one health check."""

    ok: bool
    reason: str


class HealthMonitor:
    """Decides whether the real-time exchange and the recorder are healthy.

    Real-time exchange (the commander that currently drives the robot, the daemon's or the
    run's): ``joint_state()`` must not raise and must be at most ``max_state_age_s`` old (in the
    commander's clock) whenever the exchange is expected to stream; when the driver reports
    ``link_stats()`` and its controller stops on late answers (RSI), its ``late_answers`` may grow
    by at most ``max_late_answers_per_check`` between two checks. (An FRI controller grades the
    connection itself and drops the session, which the run waits out.) Recorder: the log of a running run must exist and have been written
    within ``recorder_max_silence_s`` (file modification time, wall clock).
    """

    def __init__(self, health_cfg, *, wall_clock: Callable[[], float] = time.time) -> None:
        self.cfg = health_cfg
        self.wall_clock = wall_clock
        self._late: dict[int, int] = {}

    def check(self, commander, *, expect_stream: bool, run_status: dict | None) -> Health:
        problems = []
        if commander is not None:
            problems += self._check_commander(commander, expect_stream)
        elif expect_stream:
            problems.append("no commander")
        if run_status is not None and run_status.get("state") == "running":
            problems += self._check_recorder(run_status.get("log"))
        return Health(not problems, "; ".join(problems) or "ok")

    def forget(self, commander) -> None:
        """Drop the late-answer baseline of a commander that went away."""
        self._late.pop(id(commander), None)

    def _check_commander(self, cmd, expect_stream: bool) -> list[str]:
        out = []
        name = getattr(cmd, "name", "commander")
        stats = getattr(cmd, "link_stats", None)
        if callable(stats) and getattr(cmd, "controller_stops_on_late_answers", True):
            try:
                late = int(stats().late_answers)
            except (AttributeError, ValueError, TypeError, DriverError) as exc:
                out.append(f"{name}: link stats unavailable ({exc})")
            else:
                before = self._late.get(id(cmd))
                self._late[id(cmd)] = late
                if before is not None and late - before > self.cfg.max_late_answers_per_check:
                    out.append(f"{name}: {late - before} late real-time answers since the last check "
                               f"(allowed {self.cfg.max_late_answers_per_check})")
        if expect_stream:
            try:
                state = cmd.joint_state()
            except (DeviceTimeoutError, DriverError) as exc:
                out.append(f"{name}: {exc}")
            else:
                clock = getattr(cmd, "clock", time.monotonic)
                age = clock() - state.host_time
                if age > self.cfg.max_state_age_s:
                    out.append(f"{name}: measured state is {age:.3f} s old (allowed {self.cfg.max_state_age_s} s)")
        return out

    def _check_recorder(self, log_path: str | None) -> list[str]:
        if not log_path:
            return []
        p = Path(log_path)
        try:
            st = p.stat()
        except OSError as exc:
            return [f"run log {p}: {exc.strerror or exc}"]
        silence = self.wall_clock() - st.st_mtime
        if silence > self.cfg.recorder_max_silence_s:
            return [f"run log {p.name} not written for {silence:.0f} s (allowed {self.cfg.recorder_max_silence_s:g} s)"]
        return []


def stop_run_on_shutdown(ctl, sd, notifier, say: Callable[[str], None]) -> None:
    """A stopping daemon's run: pause it (finish the current configuration) or abort it, as the
    ``shutdown`` section ``sd`` says, then abort and wait for its log within ``sd.timeout_s``;
    ``notifier`` extends systemd's stop timeout, ``say`` sets the status line."""
    st = ctl.status()
    if st["state"] in ("finished", "aborted", "failed"):
        return
    notifier.extend_timeout(sd.timeout_s + 10)
    deadline = time.monotonic() + sd.timeout_s
    if sd.on_sigterm == "pause" and st["state"] in ("starting", "running", "suspended"):
        say(f"stopping: finishing configuration {st.get('current')} of run {st['run_id']}")
        log.info("stopping: pausing run %s after its current configuration", st["run_id"])
        ctl.pause()
        while time.monotonic() < deadline and ctl.status()["state"] not in ("paused",) + ("finished", "aborted", "failed"):
            time.sleep(0.05)
    say(f"stopping: aborting run {st['run_id']}")
    ctl.abort("daemon stopping (SIGTERM)")
    try:
        ctl.wait(max(1.0, deadline - time.monotonic()))
    except TimeoutError:
        log.error("run %s did not stop within %g s", st["run_id"], sd.timeout_s)
    else:
        st = ctl.status()
        log.info("run %s %s; log %s closed", st["run_id"], st["state"], st.get("log"))


def open_control_socket(section, control: ControlServer, authorizer: Authorizer):
    """The operators' Unix control socket (``acquire.daemon.control_socket``) serving ``control``'s
    operations, or None when the configuration has no ``control_socket`` section."""
    if section is None:
        return None
    from acquire.daemon.control_socket import ControlSocketServer

    return ControlSocketServer(section.path, section.group, section.allow, control.perform, throttle=authorizer.throttle)


class Daemon:
    """The service (see the module docstring). ``run()`` blocks until ``request_stop()``.

    controller_factory: builds a run controller, ``(lp, **kwargs) -> RunController``
    (``acquire.run.RunController`` by default). cell: the cell when it describes itself (a
    ``CellSource``, e.g. the simulated cell ``acquire daemon`` starts for ``fake``); None: the
    configured devices, and each plan's own device URLs.
    """

    def __init__(
        self,
        cfg: DaemonConfig,
        *,
        notifier: SdNotifier | None = None,
        controller_factory: Callable[..., Any] | None = None,
        cell: CellSource | None = None,
    ) -> None:
        self.cfg = cfg
        self.cell = cell
        self.notifier = notifier or SdNotifier()
        self._factory = controller_factory
        self.health = HealthMonitor(cfg.health)
        self.devices = DeviceHost(cfg, cell)
        self.bus = None
        self.live = None  # acquire.live.foxglove_server.LiveServer when cfg.live.enabled
        self.control: ControlServer | None = None
        self.control_socket = None  # acquire.daemon.control_socket.ControlSocketServer with cfg.control_socket
        self.controller = None
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._state = "starting"
        self._healthy = Health(False, "starting")
        self._tokens: dict[str, Any] = {}
        self._device_names: list[str] = []
        self._t0 = time.monotonic()
        self.pings = 0
        self._last_status = ""
        self.runs_dir = cfg.state_dir / "runs"
        self.run_text_log = RunTextLog()
        self._released: str | None = None   # the ended run whose text log is closed (offered to the station)
        self.cell_runs = CellRuns(self.runs_dir, cfg.robot_serial or cfg.cell, cfg.archive_keep_days)

    # ------------------------------------------------------------------ lifecycle
    @property
    def tick_s(self) -> float:
        """Seconds between health checks: half the watchdog interval, at most status_interval_s."""
        wd = self.notifier.watchdog_s
        return min(self.cfg.status_interval_s, wd / 2) if wd else self.cfg.status_interval_s

    def request_stop(self, *_args) -> None:
        """Ask the main loop to stop (signal handler; thread-safe)."""
        self._stop.set()

    def install_signal_handlers(self) -> None:
        """SIGTERM and SIGINT stop the daemon cleanly (main thread only)."""
        signal.signal(signal.SIGTERM, self.request_stop)
        signal.signal(signal.SIGINT, self.request_stop)

    def run(self) -> int:
        """Start up, serve until stopped, shut down. Returns the process exit status."""
        try:
            try:
                self._startup()
            except (OSError, ValueError, RuntimeError, DriverError, TimeoutError) as exc:
                log.error("start-up failed: %s", exc)
                self.notifier.notify(STATUS=f"start-up failed: {exc}".replace("\n", " "), ERRNO=1)
                return 1
            while not self._stop.wait(self.tick_s):
                self._tick()
            return 0
        finally:
            self._shutdown()

    def _startup(self) -> None:
        from acquire.daemon.local_sockets import check_socket_folder, hand_to_group, resolve_group
        from acquire.live.bus import Bus

        cfg = self.cfg
        self.runs_dir.mkdir(parents=True, exist_ok=True)
        zc = cfg.zenoh
        overrides: dict[str, Any] = {}
        full = zc.zenoh_config()
        if "transport" in full:
            overrides["transport/link/tls"] = full["transport"]["link"]["tls"]
        if "access_control" in full:
            overrides["access_control"] = full["access_control"]
        remote = bool(zc.remote_endpoints)
        if remote and zc.multicast_scouting:
            overrides["scouting/multicast/enabled"] = True
        gid = None if zc.socket_group is None else resolve_group(zc.socket_group, "zenoh.socket_group")
        for path in zc.socket_paths:
            check_socket_folder(path)
        self.bus = Bus(
            cfg.cell,
            config={"mode": zc.mode, "listen": list(zc.listen), "connect": list(zc.connect), "zenoh": overrides},
            listen_loopback_only=not remote,
            site=cfg.site,
        )
        for path in zc.socket_paths:  # Zenoh made it with our umask: nobody else could connect yet
            hand_to_group(path, gid)
        log.info("Zenoh %s for cell %s listening on %s%s", zc.mode, cfg.cell, ", ".join(zc.listen),
                 " (mTLS)" if zc.tls and zc.tls.enable_mtls else "")
        if cfg.live.enabled:
            from acquire.live.foxglove_server import LiveServer
            from acquire.record.recorder import advertise_run_channels

            self.live = LiveServer(cfg.live.host, cfg.live.port, name=f"remaster {cfg.cell}")
            advertise_run_channels(self.live)  # (each sensor's channel comes with its first run)
        self._status("bringing up devices")
        self._bring_up_devices()
        self._tokens["daemon"] = self.bus.liveliness_token(self.bus.key("daemon"))
        authorizer = Authorizer(cfg.auth, lambda zid: link_subject(self.bus, zid))
        self.control = ControlServer(self.bus.session, cfg.cell, self, authorizer, site=cfg.site)
        self.control_socket = open_control_socket(cfg.control_socket, self.control, authorizer)
        with self._lock:
            self._state = "ready"
        self._healthy = self._check_health()
        self.notifier.ready(self._status_line())
        log.info("ready: devices %s up; control queries on %s/*", self._device_names,
                 self.bus.key("control"))
        if self._healthy.ok:
            self._ping()

    def _bring_up_devices(self) -> None:
        names = self.devices.open()
        for name in names:
            if name not in self._tokens:
                self._tokens[name] = self.bus.liveliness_token(self.bus.key("device", name))
        self._device_names = names
        log.info("devices up: %s", ", ".join(names))

    def _tick(self) -> None:
        with self._lock:
            ctl = self.controller
        self.run_text_log.open_beside(ctl)
        self._after_run()
        health = self._check_health()
        if health.ok != self._healthy.ok:
            if health.ok:
                log.info("healthy again")
            else:
                log.warning("unhealthy, watchdog pings stopped: %s", health.reason)
        self._healthy = health
        if health.ok:
            self._ping()
        line = self._status_line()
        if line != self._last_status:
            self.notifier.status(line)
            self._last_status = line

    def _ping(self) -> None:
        if self.notifier.watchdog():
            self.pings += 1

    def _check_health(self) -> Health:
        with self._lock:
            ctl = self.controller
        if ctl is not None:
            st = ctl.status()
            cmd = getattr(ctl, "commander", None)
            streaming = st["state"] in ("running", "paused", "suspended") and cmd is not None
            return self.health.check(cmd, expect_stream=streaming, run_status=st)
        if not self._device_names:
            return Health(False, "the devices are not up")
        return self.health.check(self.devices.commander, expect_stream=self.devices.expect_stream, run_status=None)

    def _after_run(self) -> None:
        """When the current run has ended: close its text log and offer it to the station, take the
        devices back, then forget the run (until then ``status`` still shows the ended run and
        ``start`` is refused)."""
        with self._lock:
            ctl = self.controller
        if ctl is None or ctl.status()["state"] not in ("finished", "aborted", "failed"):
            return
        st = ctl.status()
        log.info("run %s ended: %s%s", st["run_id"], st["state"], f" ({st['reason']})" if st.get("reason") else "")
        self._release(ctl)
        announce_run_end(self.bus, st)
        self.health.forget(getattr(ctl, "commander", None))
        _collect_garbage()
        if not self._stop.is_set():
            try:
                self._bring_up_devices()
            except (OSError, ValueError, RuntimeError, DriverError, TimeoutError) as exc:
                log.error("devices did not come back after the run: %s", exc)
                self._device_names = []
                for name in list(self._tokens):
                    if name != "daemon":
                        self._tokens.pop(name).undeclare()
        with self._lock:
            self.controller = None

    def _release(self, ctl) -> None:
        """An ended run's files are complete: close its text log; from now on it is offered to the station."""
        self.run_text_log.open_beside(ctl)  # a run that ended between two ticks still gets its text log
        self.run_text_log.close()
        with self._lock:
            self._released = ctl.run_id

    def _status(self, text: str) -> None:
        self.notifier.status(text)
        self._last_status = text

    def _status_line(self) -> str:
        with self._lock:
            ctl = self.controller
            state = self._state
        parts = [state]
        if ctl is not None:
            st = ctl.status()
            parts.append(f"run {st['run_id']} {st['state']} {st['done']}/{st['total']}")
        else:
            parts.append("idle")
        parts.append(f"devices {len(self._device_names)}")
        parts.append("healthy" if self._healthy.ok else f"UNHEALTHY: {self._healthy.reason}")
        return "; ".join(parts)

    def _shutdown(self) -> None:
        with self._lock:
            self._state = "stopping"
            ctl = self.controller
        self.notifier.stopping("stopping")
        log.info("stopping")
        if ctl is not None:
            stop_run_on_shutdown(ctl, self.cfg.shutdown, self.notifier, self._status)
            self.run_text_log.open_beside(ctl)
        self.run_text_log.close()
        if self.control_socket is not None:
            self.control_socket.close()
            self.control_socket = None
        if self.control is not None:
            self.control.close()
            self.control = None
        self.devices.close()
        for tok in self._tokens.values():
            tok.undeclare()
        self._tokens.clear()
        if self.live is not None:
            self.live.close()
            self.live = None
        if self.bus is not None:
            self.bus.close()
            self.bus = None
        log.info("stopped")
        self.notifier.status("stopped")
        self.notifier.close()

    # ------------------------------------------------------------------ control backend
    def status(self, *, include_plan: bool) -> dict:
        with self._lock:
            ctl = self.controller
            state = self._state
        run = None
        if ctl is not None:
            run = dict(ctl.status())
            if include_plan:
                run["plan"] = str(ctl.lp.path)
        return {
            "cell": self.cfg.cell,
            "daemon": state,
            "healthy": self._healthy.ok,
            "health": self._healthy.reason,
            "devices": list(self._device_names),
            "fake": self.cfg.fake_cell is not None,
            "uptime_s": round(time.monotonic() - self._t0, 3),
            "watchdog_pings": self.pings,
            "memory": _memory(),
            "run": run,
        }

    def runs(self) -> dict:
        with self._lock:
            current = self.controller.run_id if self.controller is not None else None
        return {"runs": list_runs(self.runs_dir, current)}

    def plan(self, run_id: str | None) -> dict:
        with self._lock:
            ctl = self.controller
        if run_id is None or (ctl is not None and run_id == ctl.run_id):
            if ctl is None:
                raise Conflict("no run is active; give run_id")
            return {"run_id": ctl.run_id, "plan_text": ctl.lp.text}
        from acquire.record.recorder import read_run

        path = run_log(self.runs_dir, run_id)
        return {"run_id": run_id, "plan_text": read_run(path).plan_text}

    def start(self, request: dict, identity: Identity) -> dict:
        from acquire.plan.schema import load_plan
        from calib.io.yamlfile import ConfigError

        with self._lock:
            if self._state != "ready":
                raise Conflict(f"the daemon is {self._state}; not starting a run")
            if self.controller is not None:
                st = self.controller.status()
                if st["state"] in ("finished", "aborted", "failed"):
                    raise Conflict(f"run {st['run_id']} has just ended ({st['state']}); the devices are being "
                                   "taken back — try again in a few seconds")
                raise Conflict(f"run {st['run_id']} is {st['state']}; abort it or wait for it to end")
            path = plan_path(self.cfg, request)
            try:
                lp = load_plan(path)
            except ConfigError as exc:
                sep = "\n" if "\n" in str(exc) else " "  # one problem, one line
                raise BadRequest(f"plan not valid:{sep}{exc}") from exc
            plan_cell = getattr(lp.plan.cell, "id", lp.plan.cell)
            if plan_cell != self.cfg.cell:
                raise BadRequest(f"the plan is for cell {plan_cell!r}; this daemon serves {self.cfg.cell!r}")
            resume = request.get("resume")
            if resume is not None and not isinstance(resume, str):
                raise BadRequest(f"resume must be a run id string, given {resume!r}")
            resume_path = run_log(self.runs_dir, resume) if resume else None
            try:
                cell = cell_for_plan(self.cell, lp)
            except ValueError as exc:
                raise BadRequest(f"the plan cannot run in this cell: {exc}") from exc
            factory = self._factory
            if factory is None:
                from acquire.run import RunController as factory
            self.run_text_log.begin()
            # Hand the devices over: the run opens the plan's drivers at the same ports.
            self.health.forget(self.devices.commander)
            self.devices.close()
            try:
                extra = {"live": self.live} if self.live is not None else {}
                ctl = factory(lp, cell=cell, resume=resume_path, bus=self.bus,
                              out_dir=self.runs_dir, **extra)
                run_id = ctl.start()
            except (OSError, ValueError, RuntimeError, DriverError) as exc:
                self.run_text_log.close()
                log.error("run did not start: %s", exc)
                self._bring_up_devices()
                from acquire.run import RunError

                if isinstance(exc, RunError):  # e.g. the runs folder is not writable: say so, no traceback
                    raise Conflict(f"run not started: {exc}") from exc
                raise
            self.controller = ctl
        log.info("run %s started by %s from %s%s", run_id, identity.describe(), path,
                 f" (resuming {resume})" if resume else "")
        with self._lock:
            ctl = self.controller
        self.run_text_log.open_beside(ctl)
        return {"run_id": run_id, "plan": str(path), "state": ctl.status()["state"]}

    def _active(self, verb: str):
        with self._lock:
            ctl = self.controller
        if ctl is None or ctl.status()["state"] not in ACTIVE_STATES:
            raise Conflict(f"no active run to {verb}")
        return ctl

    def pause(self) -> dict:
        ctl = self._active("pause")
        ctl.pause()
        return {"run_id": ctl.run_id, "state": ctl.status()["state"]}

    def resume(self) -> dict:
        ctl = self._active("resume")
        ctl.resume()
        return {"run_id": ctl.run_id, "state": ctl.status()["state"]}

    def abort(self, reason: str) -> dict:
        ctl = self._active("abort")
        ctl.abort(reason)
        return {"run_id": ctl.run_id, "state": ctl.status()["state"]}

    def confirm(self) -> dict:
        ctl = self._active("confirm")
        waiting = ctl.confirm()
        return {"run_id": ctl.run_id, "state": ctl.status()["state"], "confirmed": waiting}

    # The plant's station (acquire.daemon.archive): finished runs, their bytes, confirmation.
    def _active_run_id(self) -> str | None:
        """The run whose files may still grow, never offered to the station: the daemon's run until
        its text log is closed (``_release``; an ended run's log takes lines until then)."""
        with self._lock:
            ctl, released = self.controller, self._released
        return ctl.run_id if ctl is not None and ctl.run_id != released else None

    def archive_list(self) -> dict:
        return self.cell_runs.pending(self._active_run_id())

    def archive_chunk(self, request: dict) -> dict:
        return self.cell_runs.chunk(request, self._active_run_id())

    def archive_confirm(self, request: dict, identity: Identity) -> dict:
        return self.cell_runs.confirm(request, identity.describe(), self._active_run_id())


def link_subject(bus, zid: str) -> str | None:
    """The TLS certificate name of the link to Zenoh peer ``zid`` (hex) on ``bus``, or None (no bus
    yet, no such link, or a link without a certificate)."""
    if bus is None:
        return None
    for link in bus.session.info.links():
        if str(link.zid) == zid:
            return link.auth_identifier or None
    return None


def init_zenoh_log() -> None:
    """Zenoh's own log (Rust ``tracing``) on stderr when ``RUST_LOG`` is set — e.g. its
    access-control decisions with ``zenoh::net::routing::interceptor::access_control=trace``;
    colour-free unless stderr is a terminal."""
    if not os.environ.get("RUST_LOG"):
        return
    import sys

    import zenoh

    if not sys.stderr.isatty():
        os.environ.setdefault("NO_COLOR", "1")
    zenoh.try_init_log_from_env()


def run_daemon(cfg: DaemonConfig, cell: CellSource | None = None) -> int:
    """Run the daemon in this process until SIGTERM/SIGINT; returns the exit status. ``cell``:
    see ``Daemon``."""
    init_zenoh_log()
    d = Daemon(cfg, cell=cell)
    d.install_signal_handlers()
    log.info("acquire daemon pid %d, cell %s, state %s", os.getpid(), cfg.cell, cfg.state_dir)
    return d.run()


def _collect_garbage() -> None:
    """A full garbage collection between runs, so a run's cyclic garbage is returned before the
    next run starts. It runs while no device is open: its pause (tens of ms) cannot make the
    robot's cyclic exchange late, as it would from a status query during a run."""
    t0 = time.perf_counter()
    found = gc.collect()
    log.debug("garbage collection between runs: %d objects in %.0f ms", found, (time.perf_counter() - t0) * 1e3)


def _memory() -> dict:
    """The daemon's memory for health checks and soak tests: resident set size (kB, from
    /proc/self/status) and, only when Python was started with tracemalloc tracing
    (``PYTHONTRACEMALLOC=1``), the traced Python heap in kB — the figure that separates a leak
    of Python objects from native allocator noise. No garbage collection here: a full
    collection holds the GIL long enough to make the robot's cyclic exchange late."""
    rss_kb = None
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    rss_kb = int(line.split()[1])
                    break
    except OSError:  # not Linux
        pass
    heap_kb = None
    if tracemalloc.is_tracing():
        heap_kb = round(tracemalloc.get_traced_memory()[0] / 1024, 1)
    return {"rss_kb": rss_kb, "python_heap_kb": heap_kb}
