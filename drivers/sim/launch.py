"""Start every fake device of a simulated cell on loopback around one ``SimCell``.

``SimLaunch(cell).start()`` brings up, on 127.0.0.1 only:

- a fake Motive (NatNet over UDP) for every ``mocap`` sensor of the cell;
- a fake laser tracker for every ``tracker`` sensor, speaking the project's line protocol over
  TCP (a ``socket://`` URL), Leica's emScon TPI (an ``emscon://`` URL), or both
  (``tracker_protocols``; both front ends then drive the same simulated tracker); the cell
  already adds the sensor's noise, so the fake adds none;
- the robot controller named by the robot model: a fake Sunrise (FRI) for ``sunrise``, a fake
  KR C4 (RSI) for ``kss``. Both are UDP *senders*, as the real controllers are: they send to
  the commander's port on 127.0.0.1 (``fri_port`` / ``rsi_port``), and the commander answers.

What each fake speaks comes from the cell file (a mocap sensor's ``natnet:`` version and asset,
a tracker's ``protocols:``, ``controller.fri_version``) unless the constructor says otherwise.
Faults on demand: ``inject(fault, device, duration_s)`` (``drivers.sim.faults``) through the
fakes' own hooks; the cell file's ``faults:`` timeline fires by itself once started.

The controller keeps its own mastering (``drivers.sim.mastering``): per-axis zero corrections,
from the cell file's ``controller.mastering_deg``, changed by ``enter_mastering`` as an operator
changes them on the real one; the fake controller reports and commands axis angles through it.

Every fake reads from or writes to the same cell, so a commander that moves the fake
controller moves the markers the fake sensors see. ``addresses`` says where each one is;
``close()`` (or leaving the ``with`` block) stops them all. Controllers stop by themselves
after ``max_runtime_s``. A real controller never starves: the fake controller's cycle runs at
SCHED_FIFO ``controller_rt_priority`` where the host permits it (as the commander's exchange
does; one log line says which). Threads of a busy process still share its interpreter lock:
``drivers.sim.process.CellProcess`` runs a ``SimLaunch`` in a real-time process of its own, as
``acquire run --fake``, ``acquire daemon`` (``fake``) and ``acquire sim`` do.

The cell has the people and programs a real cell has: the fake Sunrise runs the robot
application we ship (``drivers/kuka_fri/controller/``: it starts its FRI overlay motion when
the client answers in time, again after a drop), and a simulated operator restarts the KR C4's
RSI program when the controller ended it (too many late answers, as the real one does). Nothing
outside the simulated cell does either.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

import numpy as np

from drivers.sim.cell import SimCell
from drivers.sim.mastering import MasteredScene, Mastering
from drivers.sim.scene import MarkerObservation

log = logging.getLogger(__name__)

#: The commanders' listening ports by default (drivers.kuka_fri / drivers.kuka_rsi).
FRI_CLIENT_PORT = 30200
RSI_CLIENT_PORT = 49152
#: How often the simulated operator looks at the KR C4 (wall s).
OPERATOR_POLL_S = 0.1
#: How long a KR C4 is watched for a commander's answers before a mastering is entered (wall s).
COMMANDING_WATCH_S = 0.25


@dataclass(frozen=True)
class DeviceAddress:
    """Where one fake device is. ``url`` is what a client is given (``natnet://host:command_port``,
    ``socket://host:port``, ``udp://host:port``); ``note`` says the rest in words."""

    name: str
    kind: str  # "natnet" | "tracker" | "emscon" | "fri" | "rsi"
    host: str
    port: int
    url: str
    note: str


class _SensorView:
    """A ``MarkerScene`` that answers every ``observe`` with one named sensor of the cell (the
    fake tracker always asks for ``"tracker"``). ``blocked`` hides every marker (a beam break:
    someone in the line of sight).

    cluster_radius_mm > 0: each marker ``m`` also brings a rigid-body cluster, three infrared
    markers ``m.1 m.2 m.3`` at 120° on a circle of that radius about it in its frame's xy plane
    (the flange's), each with its own draw of the sensor's noise, so that the fake Motive tracks a
    rigid body whose origin (their centroid with ``m``) is ``m`` and whose orientation is as noisy
    as a real one fitted to its markers."""

    def __init__(self, cell: SimCell, sensor: str, *, cluster_radius_mm: float = 0.0) -> None:
        self.cell = cell
        self.sensor = sensor
        self.blocked = False
        angles = np.radians([90.0, 210.0, 330.0])
        self._cluster = float(cluster_radius_mm) * np.stack([np.cos(angles), np.sin(angles), np.zeros(3)], 1)
        self._rng = np.random.default_rng(np.random.SeedSequence(cell.config.seed, spawn_key=(0xC1,)))
        self._rng_lock = threading.Lock()

    def _with_cluster(self, obs: list[MarkerObservation]) -> list[MarkerObservation]:
        out = []
        for o in obs:
            out.append(o)
            seen = o.visible and o.rotation is not None
            with self._rng_lock:
                noise = self._rng.standard_normal((len(self._cluster), 3))
            if seen:
                pts = o.position_mm + self._cluster @ np.asarray(o.rotation).T
                std = self.cell.noise_std_mm(self.sensor, float(np.linalg.norm(o.position_mm)))
                pts = pts + noise * std
            for k in range(len(self._cluster)):
                out.append(MarkerObservation(f"{o.name}.{k + 1}", pts[k] if seen else np.full(3, np.nan), bool(seen)))
        return out

    def observe(self, sensor: str) -> list[MarkerObservation]:
        obs = self.cell.observe(self.sensor)
        if self._cluster.any():
            obs = self._with_cluster(obs)
        if self.blocked:
            return [MarkerObservation(o.name, np.full(3, np.nan), False) for o in obs]
        return obs


def _natnet_version(v) -> tuple[int, int]:
    """(major, minor) of a NatNet version given as ``"4.1"``, ``(4, 1)`` or ``(4, 1, 0, 0)``."""
    from drivers.natnet.codec import version_tuple

    return tuple(version_tuple(v)[:2])


def _bone_name() -> str:
    from drivers.natnet.fake import BONE_NAME

    return BONE_NAME


#: SCHED_FIFO priority of a fake controller's cycle (below the commander exchange's 50, so on one
#: host the client still answers first; 0: normal priority).
CONTROLLER_RT_PRIORITY = 30

class SimLaunch:
    """The fakes of one cell. Parameters:

    fri_port / rsi_port: the commander's UDP port the fake controller sends to (127.0.0.1).
    mocap_rate_hz: NatNet frame rate (120–360). natnet_version: every fake Motive's version
    (None: each mocap sensor's ``natnet.version`` in the cell file, else 3.0). mocap_asset: what
    the tool is in Motive (``drivers.natnet.fake.ASSET_KINDS``; None: the cell file's, else a rigid body).
    max_runtime_s: wall seconds after which the fake controllers stop sending by themselves.
    controller: False starts no controller (sensors only).
    operator: run the simulated operator who restarts a KR C4 RSI program that stopped.
    fri_version: the fake Sunrise's FRI message layout (``drivers.kuka_fri.fake.FRI_VERSIONS``;
    None: the cell file's ``controller.fri_version``).
    fri_send_period_ms: the fake Sunrise's send period (simulated ms, FRI allows 1–100); None
    keeps the fake's default. A faster-than-real-time cell wants a longer simulated period so one
    cycle still lasts a few wall milliseconds.
    tracker_protocols: per tracker sensor name, the protocols its fake speaks: any of ``"line"``
    and ``"emscon"`` (default ``("line",)``). A sensor served by both has its emScon address
    under ``"<name>-emscon"``. None (or a sensor not named): the cell file's ``protocols``.
    fault_timeline: fire the cell file's ``faults:`` (wall s after ``start()``).
    controller_rt_priority: SCHED_FIFO priority of the fake controller's cycle where permitted
    (0: normal priority); below the commander exchange's default (50).
    """

    def __init__(
        self,
        cell: SimCell,
        *,
        fri_port: int = FRI_CLIENT_PORT,
        rsi_port: int = RSI_CLIENT_PORT,
        mocap_rate_hz: float = 120.0,
        natnet_version: tuple[int, int] | str | None = None,
        max_runtime_s: float = 3600.0,
        controller: bool = True,
        fri_send_period_ms: int | None = None,
        operator: bool = True,
        fri_version: str | None = None,
        tracker_protocols: dict[str, tuple[str, ...]] | None = None,
        mocap_asset: str | None = None,
        fault_timeline: bool = True,
        controller_rt_priority: int = CONTROLLER_RT_PRIORITY,
    ) -> None:
        if not (isinstance(controller_rt_priority, int) and 0 <= controller_rt_priority <= 99):
            raise ValueError(f"controller_rt_priority must be an integer in [0, 99], got {controller_rt_priority!r}")
        self.controller_rt_priority = controller_rt_priority
        for name, port in (("fri_port", fri_port), ("rsi_port", rsi_port)):
            if not (isinstance(port, int) and 1 <= port <= 65535):
                raise ValueError(f"{name} must be a UDP port 1..65535, got {port!r}")
        if not max_runtime_s > 0:
            raise ValueError(f"max_runtime_s must be positive, got {max_runtime_s}")
        self.cell = cell
        self.fri_port = fri_port
        self.rsi_port = rsi_port
        self.mocap_rate_hz = mocap_rate_hz
        self.natnet_version = None if natnet_version is None else _natnet_version(natnet_version)
        self.mocap_asset = mocap_asset
        self.max_runtime_s = float(max_runtime_s)
        self.want_controller = controller
        if fri_send_period_ms is not None and not (isinstance(fri_send_period_ms, int) and 1 <= fri_send_period_ms <= 100):
            raise ValueError(f"fri_send_period_ms must be 1..100 ms (FRI's range), got {fri_send_period_ms!r}")
        self.fri_send_period_ms = fri_send_period_ms
        self.want_operator = operator
        self.fri_version = fri_version if fri_version is not None else cell.config.controller.fri_version
        self.operator_restarts = 0
        self.tracker_protocols = {s.name: tuple(s.protocols) for s in cell.config.sensors if s.protocols}
        self.tracker_protocols.update({k: tuple(v) for k, v in (tracker_protocols or {}).items()})
        for name, protos in self.tracker_protocols.items():
            bad = [p for p in protos if p not in ("line", "emscon")] or ([] if protos else ["(none)"])
            if bad:
                raise ValueError(f"tracker_protocols[{name!r}]: {bad} not allowed; allowed: line, emscon")
        self.addresses: dict[str, DeviceAddress] = {}
        self.motives: dict[str, object] = {}
        self.trackers: dict[str, tuple[object, object]] = {}  # name → (FakeTracker, its first server)
        self.emscon: dict[str, tuple[object, object]] = {}  # name → (FakeEmscon, EmsconServer)
        self.controller: object | None = None
        self.socket_operator = None
        self.views: dict[str, _SensorView] = {}  # sensor name → what its fake sees (beam_break blocks it)
        self.want_fault_timeline = fault_timeline
        self.faults = None  # drivers.sim.faults.FaultInjector once started
        self.timeline = None  # drivers.sim.faults.FaultTimeline of the cell file's faults
        #: The controller's own mastering (``drivers.sim.mastering``): the fake controller sees the
        #: arm through it; ``enter_mastering`` changes it as an operator does.
        self.mastering = Mastering(cell.model.axis_names, cell.model.controller, cell.config.controller.mastering_deg)
        self.robot_view = MasteredScene(cell, self.mastering)
        self._controller_lock = threading.RLock()
        self._closers: list = []

    # --- lifecycle ----------------------------------------------------------------------
    def start(self) -> "SimLaunch":
        """Start every fake; on any failure the ones already started are stopped again."""
        if self._closers:
            raise RuntimeError("SimLaunch already started")
        try:
            for sensor in self.cell.config.sensors:
                if sensor.kind == "mocap":
                    self._start_motive(sensor.name)
                else:
                    self._start_tracker(sensor.name)
            if self.want_controller:
                self._start_controller()
                if self.want_operator:
                    self._start_operator()
                    if self.cell.config.sockets is not None:
                        self._start_socket_operator()
            self._start_faults()
        except BaseException:
            self.close()
            raise
        return self

    def _start_faults(self) -> None:
        from drivers.sim.faults import Fault, FaultError, FaultInjector, FaultTimeline

        self.faults = FaultInjector(self, seed=self.cell.config.seed)
        self._closers.append(("faults", self.faults.close))
        steps = []
        for i, f in enumerate(self.cell.config.faults if self.want_fault_timeline else []):
            fault = Fault(f.fault, f.device, f.duration_s, f.probability)
            try:
                self.faults.targets(fault.fault, fault.device)
            except FaultError as exc:
                raise ValueError(f"the cell file's faults[{i}]: {exc}") from None
            steps.append((f.at_s, fault))
        if steps:
            self.timeline = FaultTimeline(self.faults, steps).start()
            self._closers.append(("fault timeline", self.timeline.close))

    def inject(self, fault: str, device: str | None = None, duration_s: float | None = None,
               probability: float | None = None) -> list[str]:
        """Apply a fault now (``drivers.sim.faults.FAULTS``) to ``device`` (a sensor name or
        ``"controller"``; None: every device it applies to) for ``duration_s`` wall s; returns the
        devices hit. Raises ``drivers.sim.faults.FaultError`` (a ValueError) saying what is allowed."""
        from drivers.sim.faults import DEFAULT_LOSS, Fault

        if self.faults is None:
            raise RuntimeError("SimLaunch is not started")
        return self.faults.inject(Fault(fault, device, duration_s, DEFAULT_LOSS if probability is None else probability))

    def close(self) -> None:
        """Stop every fake (in reverse order of starting); idempotent."""
        while self._closers:
            name, close = self._closers.pop()
            try:
                close()
            except OSError as exc:
                log.warning("closing fake %s: %s", name, exc)
        self.addresses.clear()

    def __enter__(self) -> "SimLaunch":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # --- devices ------------------------------------------------------------------------
    def _start_motive(self, sensor: str) -> None:
        from drivers.natnet.fake import FakeMotive

        serve = next(s for s in self.cell.config.sensors if s.name == sensor).natnet
        version = self.natnet_version or _natnet_version(serve.version if serve else "3.0")
        asset = self.mocap_asset or (serve.asset if serve else "rigid_body")
        view = self.views[sensor] = _SensorView(self.cell, sensor,
                                                cluster_radius_mm=serve.cluster_radius_mm if serve else 0.0)
        motive = FakeMotive(
            view, sensor=sensor, rate_hz=self.mocap_rate_hz, natnet_version=version, asset=asset,
            rigid_body_name=serve.asset_name if serve else "tool", multicast=bool(serve and serve.multicast),
            seed=self.cell.config.seed,
        )
        motive.start()
        self._closers.append((sensor, motive.close))
        self.motives[sensor] = motive
        self.addresses[sensor] = DeviceAddress(
            sensor, "natnet", "127.0.0.1", motive.command_port, f"natnet://127.0.0.1:{motive.command_port}",
            f"fake Motive NatNet {version[0]}.{version[1]}, "
            f"{'multicast ' + motive.multicast_group if motive.multicast else 'unicast'}: command port "
            f"{motive.command_port}, data port {motive.data_port}, {self.mocap_rate_hz:.0f} Hz, "
            f"{asset.replace('_', ' ')} {motive.rigid_body_name!r}"
            f"{' (bone ' + repr(_bone_name()) + ')' if asset != 'rigid_body' else ''}, "
            f"markers {self.cell.sensor_markers(sensor)}",
        )

    def _start_tracker(self, sensor: str) -> None:
        from drivers.tracker.fake import FakeTracker, TcpTrackerServer

        view = self.views[sensor] = _SensorView(self.cell, sensor)
        device = FakeTracker(
            view, clock=self.cell.clock, reflector=self.cell.sensor_markers(sensor)[0],
            noise_um=0.0, noise_um_per_m=0.0, seed=self.cell.config.seed,
            six_dof=next(s.six_dof for s in self.cell.config.sensors if s.name == sensor),
        )
        protocols = self.tracker_protocols.get(sensor, ("line",))
        if "line" in protocols:
            server = TcpTrackerServer(device, seed=self.cell.config.seed)
            self._closers.append((sensor, server.close))
            self.trackers[sensor] = (device, server)
            self.addresses[sensor] = DeviceAddress(
                sensor, "tracker", server.host, server.port, server.url,
                f"fake laser tracker, line protocol over TCP, reflector {device.reflector!r}",
            )
        if "emscon" in protocols:
            from drivers.emscon.fake import EmsconServer, FakeEmscon

            emscon = FakeEmscon(device)
            eserver = EmsconServer(emscon, seed=self.cell.config.seed)
            self._closers.append((sensor, eserver.close))
            self.trackers.setdefault(sensor, (device, eserver))
            self.emscon[sensor] = (emscon, eserver)
            key = f"{sensor}-emscon" if "line" in protocols else sensor
            self.addresses[key] = DeviceAddress(
                key, "emscon", eserver.host, eserver.port, eserver.url,
                f"fake Leica emScon server (TPI {'.'.join(map(str, (3, 6)))}) over TCP, reflector {device.reflector!r}",
            )

    def _start_controller(self) -> None:
        fake = self._new_controller()
        if fake is None:
            return
        self.controller = fake
        self._closers.append(("controller", self._close_controller))

    def _new_controller(self):
        """Start the fake controller the robot model names, seeing the arm through the mastering;
        None (with a warning) for a controller without a fake."""
        kind = self.cell.model.controller
        if kind == "sunrise":
            from drivers.kuka_fri.fake import FakeSunrise
            from drivers.protocols import JointLimits

            period = {} if self.fri_send_period_ms is None else {"send_period_ms": self.fri_send_period_ms}
            sockets = self.cell.config.sockets
            inputs = (sockets.confirm_input,) if sockets is not None and sockets.confirm_input else ()
            fake = FakeSunrise(
                ("127.0.0.1", self.fri_port), limits=JointLimits.from_model(self.cell.model), scene=self.robot_view,
                clock=self.cell.clock, seed=self.cell.config.seed, max_runtime_s=self.max_runtime_s,
                application=True, fri_version=self.fri_version, inputs=inputs, record_commands=False,
                rt_priority=self.controller_rt_priority, **period,
            )
            fake.start()
            host, port = fake.address
            self.addresses["controller"] = DeviceAddress(
                "controller", "fri", host, port, f"udp://{host}:{port}",
                f"fake Sunrise (FRI {fake.fri_version}, {fake.send_period_ms} ms send period, robot application "
                f"starts its joint overlay when the client answers) sending to the FRI client on 127.0.0.1:{self.fri_port}",
            )
        elif kind == "kss":
            fake = self._new_krc4()
            self.addresses["controller"] = DeviceAddress(
                "controller", "rsi", fake.address[0], fake.address[1], f"udp://{fake.address[0]}:{fake.address[1]}",
                f"fake KR C4 (RSI) sending to the RSI commander on 127.0.0.1:{self.rsi_port}",
            )
        else:
            log.warning("no fake controller for a %r controller; the robot stays where the cell put it", kind)
            return None
        return fake

    def _close_controller(self) -> None:
        """Stop whichever fake controller runs now (the operator may have replaced it)."""
        fake = self.controller
        if fake is not None:
            (fake.stop if hasattr(fake, "stop") else fake.close)()

    def _new_krc4(self):
        from drivers.kuka_rsi.fake import FakeKrc4

        fake = FakeKrc4(
            ("127.0.0.1", self.rsi_port), n_axes=self.cell.model.n_joints, scene=self.robot_view, clock=self.cell.clock,
            seed=self.cell.config.seed, max_runtime_s=self.max_runtime_s, rt_priority=self.controller_rt_priority,
        )
        fake.start()
        return fake

    def _start_operator(self) -> None:
        """The simulated operator: acknowledges and restarts a KR C4 RSI program that stopped."""
        stop = threading.Event()

        def watch() -> None:
            while not stop.wait(OPERATOR_POLL_S):
                try:
                    if self.restart_stopped_rsi():
                        self.operator_restarts += 1
                except Exception:  # noqa: BLE001 - the operator must not die with a fake
                    log.exception("simulated operator: restarting the KR C4 failed")

        thread = threading.Thread(target=watch, name="sim-operator", daemon=True)
        thread.start()

        def close() -> None:
            stop.set()
            thread.join(timeout=2.0)

        self._closers.append(("operator", close))

    def _start_socket_operator(self) -> None:
        """The person who guides the ball into the cell's sockets (hand-guiding an iiwa)."""
        from drivers.sim.socket_operator import SocketOperator

        if not callable(getattr(self.controller, "hand_guide", None)):
            log.warning("the cell has sockets but its %s controller cannot be hand-guided: the simulated operator "
                        "guides an iiwa (FRI) only", self.cell.model.controller)
            return
        self.socket_operator = SocketOperator(self.cell, self.controller, seed=self.cell.config.seed,
                                              mastering=self.mastering).start()
        self._closers.append(("socket operator", self.socket_operator.close))

    def restart_stopped_rsi(self) -> bool:
        """Start a new fake KR C4 (same ports, from the cell's current pose) if the RSI session
        of the running one has ended (late answers, Stop flag). True if it did."""
        with self._controller_lock:
            fake = self.controller
            if fake is None or self.cell.model.controller != "kss" or not fake.wait_stopped(0):
                return False
            reason = fake.stats().stopped_reason
            fake.close()
            self.controller = self._new_krc4()
        log.info("fake KR C4 restarted after: %s (now from %s)", reason, self.controller.address)
        return True

    # --- the controller's mastering -------------------------------------------------------
    def commanding(self) -> bool:
        """Whether a client commands the robot now (an FRI overlay session, RSI answers in time)."""
        fake = self.controller
        if fake is None:
            return False
        if self.cell.model.controller == "sunrise":
            from drivers.kuka_fri.messages import SessionState

            return fake.session_state in (SessionState.COMMANDING_WAIT, SessionState.COMMANDING_ACTIVE)
        before = fake.stats()
        if before.running and before.answers_on_time > 0 and before.late_consecutive == 0:
            return True
        time.sleep(COMMANDING_WATCH_S)  # a commander answering now: its on-time answers grow
        after = fake.stats()
        return bool(after.running and after.answers_on_time > before.answers_on_time)

    def enter_mastering(self, entries) -> np.ndarray:
        """Enter zero corrections on the controller (``drivers.sim.mastering.MasteringEntry`` list,
        added to the table in order) as an operator does on the real one: only with no client
        commanding the robot; the controller restarts with the new table, from where the arm
        stands (it does not move). Returns the new table (n,) deg. Raises ``MasteringError``."""
        from drivers.sim.mastering import MasteringError

        table = self.mastering.after(list(entries))
        with self._controller_lock:
            if self.commanding():
                raise MasteringError("a client commands the robot (an FRI motion / RSI program runs): a controller takes "
                                     "a new mastering only at standstill with no program running; end the run first")
            if self.controller is None:
                self.mastering.set(table)
            else:
                self._close_controller()
                self.mastering.set(table)
                self.controller = self._new_controller()
                if self.socket_operator is not None:  # the operator hand-guides the controller now running
                    self.socket_operator.controller = self.controller
        log.info("mastering entered; the controller restarted: %s", "; ".join(self.mastering.lines()))
        return self.mastering.corrections_deg

    def mastering_lines(self) -> list[str]:
        """The controller's mastering table, one line per axis."""
        return self.mastering.lines()

    def mastering_corrections_deg(self) -> np.ndarray:
        """The controller's zero corrections (n,) deg."""
        return self.mastering.corrections_deg

    def joint_positions(self) -> np.ndarray:
        """The joints as the controller reports them (n,) rad."""
        return self.robot_view.joint_positions()

    @property
    def seed(self) -> int:
        """The cell's seed."""
        return self.cell.config.seed

    def describe(self) -> list[str]:
        """One line per device, for a person."""
        q = np.degrees(self.robot_view.joint_positions())
        lines = [f"cell: {self.cell.model.name}, seed {self.cell.config.seed}, "
                 f"time scale {self.cell.clock.time_scale:g}, joints as the controller reports them (deg) "
                 f"{np.round(q, 2).tolist()}"]
        if np.any(self.mastering.corrections_deg):
            lines.append("controller mastering: " + "; ".join(self.mastering.lines()))
        lines += [f"{a.name:<14} {a.url:<28} {a.note}" for a in self.addresses.values()]
        return lines
