"""Compensation: Cartesian targets pre-corrected so that a controller with its nominal kinematics
lands where the calibrated model says the target is.

The controller turns a Cartesian target T (TCP pose in its base frame) into joint angles with its
own, nominal kinematics — the drawing's arm, on the angles it shows (after offsets are entered,
the shifted ones). The real arm at those angles is somewhere else: where the calibrated model
(offsets, links, tool, sag — ``calib.robot.calibrated.Calibrated``) puts it. Pre-distortion
undoes that for every target:

1. solve the calibrated arm's inverse kinematics for T (sag included): the controller angles q*
   at which the real arm's TCP is at T — Gauss–Newton from the controller's own solution of T in
   the chosen configuration (``calibrated_joints``);
2. the corrected target is what the controller's nominal kinematics calls q*:
   T' = FK_nominal(q*) · tool. Commanded T' (in the same configuration), the controller solves
   its nominal IK back to q*, and the real arm lands on T.

No iteration over the controller is needed: the controller's IK inverts its own FK exactly. q*
themselves are the joint targets, for a program that moves in joint space.

Frames: T and T' are TCP poses (4, 4) mm in the robot base frame of the calibrated model — the
frame the fit's registration defines — with the TCP at ``tool`` (4, 4) mm in the flange frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib.ik.ik import arm_angle_of, solve_all
from calib.robot.calibrated import Calibrated
from calib.robot.kinematics import Chain
from calib.robot.model import RobotModel
from calib.robot.transforms import invert, log_so3

#: The calibrated arm's IK is solved to this (mm, rad): far below any robot's repeatability.
IK_TOLERANCE_MM = 1e-7
IK_TOLERANCE_RAD = 1e-10
IK_ITERATIONS = 30


class CompensationError(ValueError):
    """A target that cannot be compensated (out of reach, no configuration as asked)."""


def pose_error(target: np.ndarray, reached: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position (..., 3) mm and rotation vector (..., 3) rad from ``reached`` to ``target`` (..., 4, 4)."""
    dp = target[..., :3, 3] - reached[..., :3, 3]
    dw = log_so3(target[..., :3, :3] @ np.swapaxes(reached[..., :3, :3], -1, -2))
    return dp, dw


def calibrated_joints(arm: Calibrated, flange_target: np.ndarray, q0: np.ndarray) -> np.ndarray:
    """Controller angles (n,) rad at which the calibrated arm (sag included) has its flange at
    ``flange_target`` (4, 4) mm, by Gauss–Newton from ``q0`` (n,) rad (least-norm steps for a
    redundant arm). ``CompensationError`` if it does not converge."""
    chain = arm.chain
    n = chain.n
    q = np.array(q0, dtype=float)
    for _ in range(IK_ITERATIONS):
        dp, dw = pose_error(flange_target, arm.fk(q))
        if np.linalg.norm(dp) <= IK_TOLERANCE_MM and np.linalg.norm(dw) <= IK_TOLERANCE_RAD:
            return q
        fj = chain.flange_jacobian(q + arm.joint_sag(q))
        jac = np.concatenate([fj.jp[:, :n], fj.jw[:, :n]])  # ∂/∂δ_i = ∂/∂q_i; the sag's own slope is ~1e-4 of it
        q = q + np.linalg.lstsq(jac, np.concatenate([dp, dw]), rcond=None)[0]
    dp, dw = pose_error(flange_target, arm.fk(q))
    raise CompensationError(f"the calibrated arm's inverse kinematics did not converge ({np.linalg.norm(dp):.3g} mm, "
                            f"{np.degrees(np.linalg.norm(dw)):.3g}° left): the target is at a singularity or out of reach")


@dataclass(frozen=True)
class Compensated:
    """One target: ``corrected`` (4, 4) mm to give the controller, ``joints`` (n,) rad the
    controller angles it will reach (the joint target), ``nominal_joints`` (n,) rad where the
    controller would have gone uncompensated, ``shift_mm`` / ``shift_deg`` the correction's size;
    ``arm_angle`` (7-axis arms, rad): the arm angle ψ (``calib.ik.ik.arm_angle_of``) the controller
    must hold for ``corrected`` to come back to ``joints`` — a redundant arm reaches a pose in a
    continuum of configurations, so the pose alone does not fix them; None for 6 axes."""

    corrected: np.ndarray
    joints: np.ndarray
    nominal_joints: np.ndarray
    shift_mm: float
    shift_deg: float
    arm_angle: float | None = None


class Compensator:
    """Pre-corrects targets for the controller's ``nominal`` model and the calibrated ``arm``
    (both in the controller's current angles: see ``calib.robot.calibrated.Calibrated.after_entering``);
    ``tool`` (4, 4) mm: the TCP in the flange frame, as the controller has it."""

    def __init__(self, nominal: RobotModel, arm: Calibrated, tool: np.ndarray | None = None) -> None:
        if nominal.axis_names != arm.model.axis_names:
            raise ValueError(f"the calibrated arm's axes {arm.model.axis_names} are not the controller model's {nominal.axis_names}")
        self.nominal = nominal
        self.arm = arm
        self.tool = np.eye(4) if tool is None else np.asarray(tool, dtype=float)
        self._tool_inv = invert(self.tool)
        self._chain = Chain(nominal)

    def controller_solutions(self, target: np.ndarray, arm_angle: float | None = None):
        """The controller's own IK of the TCP pose ``target`` (``calib.ik.ik.IkSolutions``, within
        limits); 7-axis arms at ``arm_angle`` (rad; None: the solver picks one)."""
        return solve_all(self.nominal, target @ self._tool_inv, arm_angle=arm_angle)

    def controller_pose(self, q: np.ndarray) -> np.ndarray:
        """The TCP pose (..., 4, 4) the controller's nominal kinematics gives for angles q."""
        return self._chain.fk(q) @ self.tool

    def true_pose(self, q: np.ndarray) -> np.ndarray:
        """The TCP pose the calibrated arm reaches at controller angles q (sag included)."""
        return self.arm.fk(q) @ self.tool

    def compensate(self, target: np.ndarray, nominal_joints: np.ndarray) -> Compensated:
        """Pre-correct TCP pose ``target`` (4, 4) mm for the configuration the controller reaches it in,
        ``nominal_joints`` (n,) rad (one of ``controller_solutions``)."""
        q = calibrated_joints(self.arm, target @ self._tool_inv, nominal_joints)
        if not self.nominal.within_limits(q):
            raise CompensationError("the compensated joints leave the joint limits (the target is at the edge of the range)")
        corrected = self.controller_pose(q)
        dp, dw = pose_error(corrected, target)
        psi = float(arm_angle_of(self.nominal, q)) if self.nominal.n_joints == 7 else None
        return Compensated(corrected, q, np.asarray(nominal_joints, dtype=float), float(np.linalg.norm(dp)),
                           float(np.degrees(np.linalg.norm(dw))), psi)

    def calibrated_solutions(self, target: np.ndarray) -> tuple[np.ndarray, str]:
        """Every configuration (k, n) rad, within the joint limits, at which the calibrated arm's TCP
        is at ``target`` (4, 4) mm — one per branch of the nominal IK, each polished onto the
        calibrated arm — and, when there is none, why (else "")."""
        sols = self.controller_solutions(target)
        if len(sols) == 0:
            return np.zeros((0, self.nominal.n_joints)), f"{sols.status}: {sols.message}"
        rows = []
        for q0 in sols.q:
            try:
                q = calibrated_joints(self.arm, target @ self._tool_inv, q0)
            except CompensationError:
                continue
            if self.nominal.within_limits(q):
                rows.append(q)
        if not rows:
            return np.zeros((0, self.nominal.n_joints)), "the calibrated arm reaches it only outside the joint limits"
        return np.array(rows), ""
