"""``acquire sim``: run a simulated cell — every fake device on loopback around one truth model.

Example::

    acquire sim --seed 3 --time-scale 1
    acquire sim --config fixtures/sim/default.yaml --fri-port 30200 --duration 600 --fri-version 2.7
    acquire sim --natnet-version 4.1 --mocap-asset skeleton --tracker-protocols line,emscon

A Sunrise cell's fake controller runs the robot application we ship: it opens the FRI session
and starts its joint-position overlay once the client answers in time, so any FRI client
(ours, KUKA's SDK examples) can be tried against it without code. A KR C4 cell (robot model
with a ``kss`` controller) gets a fake KR C4 speaking RSI.

What each device speaks comes from the cell file (``drivers/sim/config.py``: a mocap sensor's
``natnet:`` version/asset, a tracker's ``protocols:``, ``controller.fri_version``); the options
here override it for every device of that kind.

The devices run in a process of their own at SCHED_FIFO where the host permits it
(``drivers/sim/process.py``), as a real cell's controller and sensors are machines of their own:
this process only reads the keys or lines and prints.

Prints where each fake listens (NatNet command port, tracker ``socket://`` / ``emscon://`` URL)
or sends (the robot controller, to the commander's port), then runs until Ctrl-C, ``q`` or
``--duration`` wall seconds. ``--show-truth`` also prints the hidden zero-offsets.

Faults on demand (``drivers/sim/faults.py``): the cell file's ``faults:`` timeline fires by
itself; on a terminal one key injects a fault (the keys are printed at start); with stdin not a
terminal (a pipe) every line ``FAULT [DEVICE|all] [DURATION_S] [PROBABILITY]`` is one fault,
answered on stdout with ``fault FAULT on DEVICE, ...`` or ``error: ...``.

The controller's mastering (``drivers/sim/mastering.py``), entered as on the real controller
(with no run commanding the robot; the controller restarts with it): a line ``master AXIS
CORRECTION_DEG`` (``master A2 -0.0123``: the axis zero shifts by the correction, KSS ``$MAMES[2] =
$MAMES[2] -0.0123``, which is also taken as written), ``enter RESULT.json`` (every correction the
result tells the operator to enter), ``mastering`` (show the table) or ``save CELL.yaml`` (a copy
of the cell file with the mastering: the cell a later ``--fake`` run starts with, as a controller
keeps its mastering through a restart); on a terminal, key ``m`` asks for such a line. The answer
is the new table, or ``error: ...``.
"""

from __future__ import annotations

import os
import select
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from calib.io.yamlfile import ConfigError
from drivers.sim.cell import SimCell
from drivers.sim.clock import SimClock
from drivers.sim.config import DEFAULT_CONFIG_PATH
from drivers.sim.faults import DEFAULT_DURATION_S, DEFAULT_LOSS, KEY_HELP, KEYS, FaultError, parse_command
from drivers.sim.launch import FRI_CLIENT_PORT, RSI_CLIENT_PORT
from drivers.sim.process import CellProcess, CellProcessError

#: Wall seconds between checks of the fakes (and of Ctrl-C).
POLL_S = 0.2
NATNET_VERSIONS = ("3.0", "3.1", "4.0", "4.1")
MOCAP_ASSETS = ("rigid_body", "skeleton", "trained_markerset")


def _protocols(text: str | None) -> tuple[str, ...] | None:
    if text is None:
        return None
    protos = tuple(p.strip() for p in text.split(",") if p.strip())
    bad = [p for p in protos if p not in ("line", "emscon")]
    if bad or not protos:
        raise typer.BadParameter(f"given {text!r}; allowed: line, emscon or line,emscon", param_hint="--tracker-protocols")
    return protos


def sim(
    seed: Optional[int] = typer.Option(None, "--seed", min=0, help="Override the config's seed."),
    config: Path = typer.Option(DEFAULT_CONFIG_PATH, "--config",
                                help="Cell YAML (drivers/sim/config.py), or the name of a packaged cell (acquire examples)."),
    time_scale: float = typer.Option(1.0, "--time-scale", help="Simulated seconds per wall second (> 0)."),
    fri_port: int = typer.Option(FRI_CLIENT_PORT, "--fri-port", help="UDP port of the FRI client to send to."),
    rsi_port: int = typer.Option(RSI_CLIENT_PORT, "--rsi-port", help="UDP port of the RSI commander to send to."),
    rate: float = typer.Option(120.0, "--mocap-rate", help="NatNet frame rate, 120–360 Hz."),
    duration: float = typer.Option(3600.0, "--duration", help="Stop by itself after this many wall seconds."),
    show_truth: bool = typer.Option(False, "--show-truth", help="Also print the hidden zero-offsets."),
    fri_version: Optional[str] = typer.Option(
        None, "--fri-version", help="FRI message layout of the fake Sunrise: 1.15, 2.5 or 2.7 (default: the cell file's, else 1.15)."
    ),
    natnet_version: Optional[str] = typer.Option(
        None, "--natnet-version", help="NatNet version of every fake Motive: 3.0, 3.1, 4.0 or 4.1 (default: the cell file's, else 3.0)."
    ),
    mocap_asset: Optional[str] = typer.Option(
        None, "--mocap-asset", help="The tool in Motive: rigid_body, skeleton (bone 'plate') or trained_markerset (4.1) "
                                    "(default: the cell file's, else rigid_body)."
    ),
    tracker_protocols: Optional[str] = typer.Option(
        None, "--tracker-protocols", help="Every fake tracker's protocols: line, emscon or line,emscon (default: the cell file's, else line)."
    ),
    no_faults: bool = typer.Option(False, "--no-faults", help="Do not fire the cell file's faults: timeline."),
) -> None:
    """Run the fake devices of a simulated cell on 127.0.0.1 until Ctrl-C; inject faults on demand."""
    if not time_scale > 0:
        raise typer.BadParameter(f"must be positive, given {time_scale}", param_hint="--time-scale")
    if not duration > 0:
        raise typer.BadParameter(f"must be positive, given {duration}", param_hint="--duration")
    if natnet_version is not None and natnet_version not in NATNET_VERSIONS:
        raise typer.BadParameter(f"given {natnet_version!r}; allowed: {', '.join(NATNET_VERSIONS)}", param_hint="--natnet-version")
    if mocap_asset is not None and mocap_asset not in MOCAP_ASSETS:
        raise typer.BadParameter(f"given {mocap_asset!r}; allowed: {', '.join(MOCAP_ASSETS)}", param_hint="--mocap-asset")
    protos = _protocols(tracker_protocols)
    try:
        if not config.exists():
            from calib.io.resources import find

            config = find("sim", str(config)) or config  # a packaged cell by name, e.g. "default"
        cell = SimCell.from_yaml(config, seed=seed, clock=SimClock(time_scale))  # (checks the file here)
    except ConfigError as exc:
        typer.echo(f"error: {exc}", err=True)
        raise typer.Exit(2) from None
    trackers = {s.name: protos for s in cell.config.sensors if s.kind == "tracker"} if protos else None
    try:
        launch = CellProcess(config, clock=cell.clock, seed=cell.config.seed, launch_options=dict(
            fri_port=fri_port, rsi_port=rsi_port, mocap_rate_hz=rate, max_runtime_s=duration, fri_version=fri_version,
            natnet_version=natnet_version, mocap_asset=mocap_asset, tracker_protocols=trackers,
            fault_timeline=not no_faults), start_method="fork")  # (this process has the fakes imported)
        launch.start()
    except (ValueError, OSError, CellProcessError) as exc:
        typer.echo(f"error: cannot start the simulated cell ({config}): {exc}", err=True)
        raise typer.Exit(2) from None
    try:
        for line in launch.describe():
            typer.echo(line)
        if show_truth:
            offsets = ", ".join(f"{a} {v:+.4f}" for a, v in zip(cell.truth.axis_names, launch.truth_offsets_deg()))
            typer.echo(f"truth: zero-offsets (deg, controller convention): {offsets}")
        if launch.timeline_steps:
            typer.echo("fault timeline: " + "; ".join(
                f"{f.fault} on {f.device or 'all'} at {at:g} s" for at, f in launch.timeline_steps))
        interactive = sys.stdin is not None and sys.stdin.isatty()
        typer.echo(KEY_HELP + "; m: enter mastering" if interactive else
                   "faults: one line on stdin 'FAULT [DEVICE|all] [DURATION_S] [PROBABILITY]'; mastering: "
                   "'master AXIS CORRECTION_DEG', 'enter RESULT.json', 'mastering', 'save CELL.yaml'")
        try:
            with _sigterm_as_interrupt():
                (_keys if interactive else _lines)(launch, time.monotonic() + duration, Path(config))
        except KeyboardInterrupt:
            typer.echo("stopping")
        q = np.degrees(launch.joint_positions())
    finally:
        launch.close()
    typer.echo(f"stopped; final joints as the controller reports them (deg) {np.round(q, 3).tolist()}")


class _sigterm_as_interrupt:
    """SIGTERM (systemd, ``kill``) stops the cell like Ctrl-C: every fake is closed properly."""

    def __enter__(self):
        self._old = None
        if threading.current_thread() is threading.main_thread():
            def stop(_signum, _frame):
                raise KeyboardInterrupt
            self._old = signal.signal(signal.SIGTERM, stop)
        return self

    def __exit__(self, *exc) -> None:
        if self._old is not None:
            signal.signal(signal.SIGTERM, self._old)


def _inject(launch: CellProcess, fault: str, device: str | None, duration_s: float | None, probability: float) -> str:
    try:
        hit = launch.inject(fault, device, duration_s, probability)
    except FaultError as exc:
        return f"error: {exc}"
    when = "" if fault == "controller_restart" else f" for {duration_s or DEFAULT_DURATION_S:g} s"
    return f"fault {fault} on {', '.join(hit)}{when}"


def _running(deadline: float) -> None:
    typer.echo(f"running for up to {max(0.0, deadline - time.monotonic()):.0f} s; Ctrl-C to stop")
    sys.stdout.flush()


#: The first words of a stdin line that speaks to the controller's mastering, not a fault.
MASTERING_WORDS = ("master", "enter", "mastering", "save")


def _mastering(launch: CellProcess, line: str, source: Path | None = None) -> str:
    """Do one mastering line (``master AXIS C``, ``$MAMES[i] = $MAMES[i] ±C``, ``enter RESULT.json``,
    ``mastering``, ``save CELL.yaml`` — a copy of the cell file ``source`` with the mastering); the
    answer to print: the table after it, or ``error: …``."""
    from calib.robot.entered import read_entered
    from drivers.sim.config import save_with_mastering
    from drivers.sim.mastering import MasteringEntry, MasteringError, parse_entry

    words = line.split()
    try:
        if words == ["mastering"]:
            return "\n".join(["mastering:"] + launch.mastering_lines())
        if words[0] == "save":
            if len(words) != 2:
                raise MasteringError(f"give 'save CELL.yaml'; given {line.strip()!r}")
            path = save_with_mastering(source, words[1], launch.mastering_corrections_deg(), seed=launch.seed)
            return f"saved {path}: this cell with the controller's mastering (--config it, or a plan's fake.sim_config)"
        if words[0] == "enter":
            if len(words) != 2:
                raise MasteringError(f"give 'enter RESULT.json'; given {line.strip()!r}")
            values = read_entered(words[1])
            if not values.axes:
                why = "; ".join(values.refused) or "no axis has a value to enter"
                raise MasteringError(f"{words[1]} enters nothing ({why})")
            entries = [MasteringEntry(a.axis, a.correction_deg) for a in values.axes]
            what = f"entered from {words[1]} ({values.source}): " + ", ".join(
                f"{e.axis} {e.correction_deg:+.4f}°" for e in entries)
        else:
            entries = parse_entry(line)
            what = "entered: " + ", ".join(f"{e.axis} {e.correction_deg:+.4f}°" for e in entries)
        launch.enter_mastering(entries)
    except (ValueError, OSError) as exc:  # MasteringError, ConfigError, a file that cannot be read or written
        return f"error: {exc}"
    return "\n".join([what, "mastering (the controller restarted with it):"] + launch.mastering_lines())


def _answer(launch: CellProcess, line: str, source: Path | None = None) -> str:
    """What one stdin line does: a mastering entry (``source``: the cell file) or a fault."""
    if line.split()[0] in MASTERING_WORDS or line.lstrip().startswith("$MAMES"):
        return _mastering(launch, line, source)
    try:
        f = parse_command(line)
    except FaultError as exc:
        return f"error: {exc} (or a mastering line: 'master AXIS CORRECTION_DEG', 'enter RESULT.json', 'mastering')"
    return _inject(launch, f.fault, f.device, f.duration_s, f.probability)


def _lines(launch: CellProcess, deadline: float, source: Path | None = None) -> None:
    """stdin is a pipe (or closed): one fault or mastering line at a time until the deadline (EOF: just wait)."""
    done = threading.Event()

    def read() -> None:
        for line in sys.stdin if sys.stdin is not None else ():
            if done.is_set():
                return
            if not line.strip():
                continue
            # one write with its newline: unbuffered (PYTHONUNBUFFERED), print() writes the text and
            # the newline apart, and a log line on the same pipe can land between them
            typer.echo(_answer(launch, line, source))

    threading.Thread(target=read, name="sim-stdin", daemon=True).start()
    _running(deadline)
    try:
        while time.monotonic() < deadline:
            time.sleep(min(POLL_S, max(0.0, deadline - time.monotonic())))
    finally:
        done.set()


def _keys(launch: CellProcess, deadline: float, source: Path | None = None) -> None:
    """stdin is a terminal: single keys (no Enter) inject faults; ``q`` quits."""
    import termios
    import tty

    fd = sys.stdin.fileno()
    saved = termios.tcgetattr(fd)
    try:
        tty.setcbreak(fd)  # before saying we run: a key typed from then on is read at once
        _running(deadline)
        while time.monotonic() < deadline:
            ready, _, _ = select.select([fd], [], [], min(POLL_S, max(0.0, deadline - time.monotonic())))
            if not ready:
                continue
            key = os.read(fd, 1).decode(errors="replace").lower()
            if key == "q":
                typer.echo("stopping")
                return
            if key in KEYS:
                typer.echo(_inject(launch, KEYS[key], None, None, DEFAULT_LOSS))
            elif key == "m":  # a whole line: the terminal reads it cooked, then single keys again
                termios.tcsetattr(fd, termios.TCSADRAIN, saved)
                try:
                    line = input("mastering ('master AXIS CORRECTION_DEG', 'enter RESULT.json', 'mastering'): ")
                finally:
                    tty.setcbreak(fd)
                if line.strip():
                    typer.echo(_mastering(launch, line if line.split()[0] in MASTERING_WORDS or
                                          line.lstrip().startswith("$MAMES") else f"master {line}", source))
            elif key in ("h", "?"):
                typer.echo(KEY_HELP + "; m: enter mastering")
    finally:
        termios.tcsetattr(fd, termios.TCSADRAIN, saved)


def register(app: typer.Typer) -> None:
    """Add the ``sim`` sub-command to ``app``."""
    app.command("sim")(sim)
