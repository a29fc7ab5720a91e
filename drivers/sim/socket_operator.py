"""The simulated operator of a socket cell: guides the ball into a socket and holds it there.

A person at a real iiwa takes the arm (the robot application's hand-guiding, joint-impedance
mode) once it has stopped near a socket, pushes the ball into the socket and holds it until the
joint angles are recorded. Here: when the controller's set-point has not changed for
``approach_hold_s`` and the *true* ball (the cell's hidden kinematics, its gravity sag, the
ball where it really sits on the flange) is within ``capture_radius_mm`` of a true socket
point, the operator solves for the joint angles near the set-point that put the true ball at the
socket plus the play of the ball in it (Gauss–Newton, minimum-norm steps: the arm's self-motion
is left alone, as a hand at the ball leaves it) and pushes the arm there
(``FakeSunrise.hand_guide``). With a ``confirm_input`` he presses that button (``FakeSunrise.set_input``)
``PRESS_AFTER_S`` after the push, once the arm has settled in the socket, for ``PRESS_S``, and
again every other ``PRESS_S`` while the robot stays (a person presses again when nothing happens).
He lets go after ``hold_s`` or as soon as the robot is commanded elsewhere. He knows nothing of
the run: only where the ball is and where the sockets are.

Units: mm, rad, simulated seconds (the cell's clock).
"""

from __future__ import annotations

import logging
import threading

import numpy as np

from drivers.sim.cell import SimCell

log = logging.getLogger(__name__)

#: Simulated seconds between two looks at the robot.
POLL_S = 0.02
#: A push larger than this on any axis (rad) is not a hand-guiding correction: the operator
#: leaves the robot alone (the approach was not near this socket).
MAX_PUSH_RAD = np.radians(5.0)
#: Simulated seconds from the push to the first press of the confirm button (the arm has settled),
#: and how long a press lasts (a pause as long follows before the next).
PRESS_AFTER_S = 1.0
PRESS_S = 0.3


class SocketOperator:
    """Guides the ball into the nearest socket of ``cell.config.sockets``; see the module docstring."""

    def __init__(self, cell: SimCell, controller, *, seed: int = 0, mastering=None) -> None:
        """``mastering``: the controller's (``drivers.sim.mastering.Mastering``): its angles are the
        arm's less the corrections; None: the arm's own."""
        spec = cell.config.sockets
        if spec is None:
            raise ValueError("the cell has no sockets section")
        self.cell, self.controller, self.spec = cell, controller, spec
        self.to_arm = mastering.cell_position if mastering is not None else (lambda q: np.asarray(q, dtype=float))
        self.chain = cell.chain
        params = np.array(cell.truth.params, dtype=float)
        ms = self.chain.marker_slice()
        params[ms.start:ms.start + 3] = spec.ball_mm  # the ball takes marker slot 0
        self.params = params
        self.points = np.array([p.xyz_mm for p in spec.points], dtype=float)
        self.names = [f"{p.placement}/{p.socket}" for p in spec.points]
        self.rng = np.random.default_rng([seed, 0x50C7])
        self.guided = 0  # how many times the ball was put into a socket
        self.presses = 0  # how many times the confirm button went down
        self._pressed = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def ball(self, q: np.ndarray) -> np.ndarray:
        """True ball centre (3,) mm in the base frame at the controller's joint angles q (n,), with sag."""
        q = self.to_arm(q)
        qa = q + self.cell.deflection(q)
        return self.chain.marker_positions(qa[None], self.params)[0, 0]

    def solve(self, q0: np.ndarray, target: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Joint angles near ``q0`` (n,) whose true ball sits at ``target`` (3,) mm."""
        q = np.array(q0, dtype=float)
        for _ in range(iterations):
            err = self.ball(q) - target
            if np.max(np.abs(err)) < 1e-7:
                break
            arm = self.to_arm(q)
            qa = arm + self.cell.deflection(arm)
            _, jac = self.chain.marker_jacobian(qa[None], self.params)
            q = q - np.linalg.pinv(jac[0, 0, :, : self.chain.n]) @ err
        return q

    def start(self) -> "SocketOperator":
        self._thread = threading.Thread(target=self._run, name="sim-socket-operator", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def _press(self, down: bool) -> None:
        """Press or release the confirm button, if the cell has one."""
        if self.spec.confirm_input:
            if down and not self._pressed:
                self.presses += 1
            self._pressed = down
            self.controller.set_input(self.spec.confirm_input, down)

    def _run(self) -> None:
        try:
            self._loop()
        except Exception:  # noqa: BLE001 - the operator must not die silently
            log.exception("simulated socket operator stopped")

    def _loop(self) -> None:
        clock = self.cell.clock
        last_sp, t_still, tried = None, clock.now(), False
        holding, held_sp, t_hold = False, None, 0.0
        while not self._stop.is_set():
            clock.sleep(POLL_S)
            now = clock.now()
            sp = self.controller.setpoint()
            if holding:
                if np.max(np.abs(sp - held_sp)) > 1e-9 or now - t_hold >= self.spec.hold_s:
                    self._press(False)
                    self.controller.release()
                    holding, last_sp, t_still, tried = False, sp, now, True
                elif self.spec.confirm_input and now - t_hold >= PRESS_AFTER_S:
                    self._press(int((now - t_hold - PRESS_AFTER_S) / PRESS_S) % 2 == 0)
                continue
            if last_sp is None or np.max(np.abs(sp - last_sp)) > 1e-9:
                last_sp, t_still, tried = sp, now, False
                continue
            if tried or now - t_still < self.spec.approach_hold_s:
                continue
            tried = True
            here = self.ball(sp)
            dist = np.linalg.norm(self.points - here, axis=1)
            g = int(np.argmin(dist))
            if dist[g] > self.spec.capture_radius_mm:
                continue
            target = self.points[g] + self.rng.normal(0.0, self.spec.play_mm, 3)
            q = self.solve(sp, target)
            push = q - sp
            if not np.all(np.isfinite(push)) or np.max(np.abs(push)) > MAX_PUSH_RAD \
                    or np.linalg.norm(self.ball(q) - target) > 1e-3:
                log.info("socket operator: cannot guide the ball into %s from here (%.1f mm away)", self.names[g], dist[g])
                continue
            self.controller.hand_guide(push)
            holding, held_sp, t_hold = True, sp, now
            self.guided += 1
            log.info("socket operator: ball guided into %s from %.2f mm away (largest push %.3f°)",
                     self.names[g], dist[g], np.degrees(np.max(np.abs(push))))
