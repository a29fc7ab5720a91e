"""The measurement plan: ``plan.yaml``, its validation, and the joint configurations it names.

A plan says which robot, which controller and sensors, which configurations to visit, how to
visit them, where to write the log and how to fit it. ``load_plan(path)`` reads and checks it
completely — schema, then every relation between fields and against the robot model — before
anything connects or moves; ``resolve_configurations(lp)`` turns its ``poses`` section into
joint configurations (seeded: the same plan gives the same configurations, with the same ids).

Units: a file holds mm and degrees (each field's name or description says which); inside,
everything is mm and radians. Relative paths are taken from the plan file's folder.

Plan format (every section; defaults in brackets; ``fixtures/plans/example.yaml`` is a
commented example)::

    cell: lab1                       # cell id: [a-z0-9_-], the Zenoh key prefix remaster/<cell>/…
    robot: ../robots/kuka_iiwa14_r820.yaml   # robot model YAML (calib.robot.model)
    commander:                       # the robot controller's JointCommander
      driver: fri                    # a name from drivers.registry (built-in: fri, rsi)
      url: fri://127.0.0.1:30200     # the driver's URL (scheme fri:// for fri, rsi:// for rsi)
      options: {}                    # extra keyword arguments for the driver [{}]
    sensors:                         # one or more PositionSensors
      - name: mocap                  # [A-Za-z0-9_-]; the fake cell's sensor of that name in --fake
        driver: natnet               # built-in: natnet, tracker
        url: natnet://127.0.0.1:1510
        markers: {sir: "ms:tool:sir"}   # tool marker (robot model) → driver selector
        noise_mm: 0.03               # expected noise, 1σ per axis, mm
        options: {}                  # [{}]
        # laser trackers (drivers tracker, emscon) only:
        # environment: {temperature_c: 20.5, pressure_hpa: 1008, humidity_pct: 45}  # or {source: station}
        # reflector: {type: RRR15, offset_mm: 19.05}   # offset optional, checked where the tracker knows it
        # placement: {xyz: [2000, 0, 900], zyx: [180, -80, 0]}  # rough sensor pose, base frame (mm, deg) [null]
    poses:                           # exactly ONE of generated / cartesian / joints
      generated:                     # the remastering paper's plan (calib.plan.poses.plan_poses)
        n: 60                        # Latin-hypercube candidate poses
        seed: 1
        sensor_origin_mm: [2000, 0, 900]   # where the flange z-axis aims (robot base frame)
        radius_mm: [200, 500]        # [low, high] in the base X–Y plane [200, 500]
        height_mm: [400, 800]        # [400, 800]
        angle_deg: [0, 360]          # base angle about Z [0, 360]
        roll_deg: [0, 360]           # extra tool roll about the aimed z-axis [0, 360]
        arm_angles_deg: [180]        # 7-axis arms: also solve at these arm angles [none]
        min_solutions: 2             # drop poses with fewer feasible IK solutions [2]
        limit_margin_deg: 0          # keep configurations this far inside the limits, and at
                                     # least the commander's margin (0.5° for fri, rsi) [0]
      # cartesian:                   # explicit flange poses, every IK solution within limits
      #   - {xyz_mm: [500, 0, 600], zyx_deg: [0, 90, 0], group: front, arm_angle_deg: 30}
      # joints: [[0, 30, 0, -60, 0, 45, 0], ...]     # explicit configurations, degrees
      # joints: {file: configs.csv}  # or a configurations file (calib.plan.poses format)
    # socket:                        # INSTEAD of poses: socket (sensorless) calibration, with one
    #   ball_mm: [0, 0, 60]          # sensor {driver: socket, url: operator://terminal}; nominal ball
    #   distance_mm: 50              # on the flange, mm; sockets' distance (caliper) [null: no scale]
    #   configurations: 8            # per socket [8]
    #   seed: 0                      # [0]
    #   tilt_deg: [0, 45]            # ball axis from the vertical [0, 45]
    #   placements:                  # socket positions from a tape, robot base frame, mm
    #     - {name: front, sockets: [{name: "0", xyz_mm: [600, 0, 150]}, {name: "1", xyz_mm: [600, 50, 150]}]}
    selection:                       # optional: keep the m most informative (IOOPS)
      index: O6                      # O1 … O6 [O6]
      m: 40
      seed: 0                        # [0]
      k: null                        # weight of O3 in O6 [null: O1/O3 of the start set]
    adaptive:                        # optional: measure until the answer is good enough (issue 27)
      stop_when:                     # every criterion given must hold (acquire/run/adaptive.py)
        interval_deg: 0.01           # every determinable offset's 95 % half-width ≤ this, deg
        region_error_mm: 0.05        # predicted model error at new poses of the plan's region ≤ this, mm
        joint_space_error_mm: 0.1    # the same over the working joint space (joint_space below), mm
        workspace_within_pct: 10     # predicted workspace error within this % of the full plan's
        held_out_within_pct: 5       # predicted held-out error (model + sensor noise) within this %
        joint_space_within_pct: 30   # predicted joint-space model error within this % of the full plan's
      min_configurations: null       # never stop before [null: twice what the fit needs, ≥ 12]
      max_configurations: null       # stop here anyway [null: the plan's size]
      candidates:                    # optional: generated candidates beyond the plan's (poses.generated only)
        extra_poses: 300             # further poses of the plan's generator, every feasible IK branch
        seed: null                   # their seed, not the plan's [null: the plan's seed + 1]
      joint_space:                   # optional: the robot's working joint space (joint_space_* criteria)
        ranges_deg: null             # [low, high] per joint [null: the model's limits less the margin]
        samples: 200                 # configurations drawn (Latin hypercube) [200]
        seed: 0                      # [0]
    sequencing:
      speed: 0.3                     # fraction (0, 1] of the model's joint speeds [0.3]
      settle_window_s: 0.5           # robot still and sensor stable this long [0.5]
      settle_tolerance_deg: 0.01     # "still": every joint within this [0.01]
      sensor_stable_mm: 0.05         # "stable": readings within this [0.05]
      samples: 20                    # samples averaged per sensor and configuration [20]
      move_timeout_s: 120            # [120]
      measure_timeout_s: 10          # [10]
      retries: 2                     # re-tries of a failed configuration [2]
      on_lost_target: reacquire      # wait | reacquire | ask | skip [reacquire]
      lost_target_wait_s: 30         # how long "wait" (and re-acquisition; "skip": the target's own return) may take [30]
      robot_fault_wait_s: 30         # drives off, session dropped, controller restart, stale state: waited out this long [30]
      sensor_fault_wait_s: 30        # a sensor not answering or disconnected: waited out this long [30]
    output:
      folder: runs                   # where RUN.mcap, result.json and report.html go [runs]
    fit:
      method: auto                   # auto | fast | paper [auto: the data choose the model]
      joints: null                   # axis numbers to fit, e.g. [2, 3, 4] [null: all]
      error: gaussian                # gaussian | student [gaussian]
      fix_registration: false        # [false]
      validate_fraction: null        # share of configurations held out for validation, (0, 0.5] [null]
    fake:                            # optional: what --fake runs against (checked by --fake)
      sim_config: ../sim/default.yaml   # [null: fixtures/sim/default.yaml]
      seed: null                     # overrides the cell's seed [null]
      time_scale: 1.0                # simulated seconds per wall second [1.0]

Errors: ``load_plan`` raises ``ConfigError`` (a ``ValueError``) listing every problem, one a
line, sorted by position, as ``file:line:col: field: message (given …; allowed …)``, e.g.
``plan.yaml:14:10: sequencing.speed: Input should be less than or equal to 1 (given 1.5;
allowed (0, 1])``. Relations are checked too: driver names (the known ones are listed), a
sensor marker the tool does not carry, joint lists of the wrong length or outside the model's
limits (the joint and its limit are named), a robot or configurations file that does not exist
(pointing at its line), a selection larger than the configurations it selects from.

Inputs that would move the robot wrongly are refused too (``acquire.plan.guards``): explicit
joint targets within the commander's margin of a limit (the driver class says how much,
``limit_margin_for``; the commander would refuse them mid-run), and values that look like
metres or radians (``sensor_origin_mm`` in metres, joint targets in radians, the robot model's
tool markers in metres — pointing at the model file's line). Generated and Cartesian poses
keep at least the commander's margin inside the limits.

Configuration ids (``PlannedConfig.config_id``; a resumed run matches on them):

- generated: ``p07-b3`` — candidate pose 7 (index in the seeded candidate list, zero-padded to
  the width of ``n - 1``), its 4th feasible IK solution; pose group ``p07``;
- cartesian: ``<group>-b<k>``, group defaulting to ``c00``, ``c01``, … (the pose's index);
- joints list: ``j000``, ``j001``, … (pose and branch empty);
- joints file: ``c<config>`` from the file's config column; pose group ``p<pose>``;
- socket: ``<placement>-s<socket>-k<kk>`` — the kk-th approach to that socket
  (``calib.plan.socket_poses``); pose group ``<placement>/<socket>``; ``PlannedConfig.socket`` set.

A selection keeps the ids of the configurations it keeps.
"""

from __future__ import annotations

import logging
import math
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal, Union

import annotated_types
import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
    ValidationError,
    ValidationInfo,
    field_validator,
)
from pydantic.fields import FieldInfo

from calib.robot.model import Frame, RobotModel, load_robot_model
from calib.io.resources import default_sim_config
from calib.io.yamlfile import (ConfigError, CrossFieldChecked, Marks, error_line, load_yaml_with_marks, locate,
                            parse_yaml_text, read_yaml_text)
from acquire.plan.guards import (
    commander_margin_rad,
    confirm_input_errors,
    describe_config_rows,
    joints_margin_errors,
    model_units_errors,
    plan_units_errors,
    radians_problem,
)

log = logging.getLogger(__name__)

Vec3 = tuple[float, float, float]
Range = tuple[float, float]

#: Commander drivers that speak to one kind of controller (RobotModel.controller).
CONTROLLER_OF_DRIVER = {"fri": "sunrise", "rsi": "kss"}
#: URL schemes of the built-in drivers (the tracker takes any pyserial URL).
URL_SCHEMES = {"fri": ("fri",), "rsi": ("rsi",), "natnet": ("natnet",), "emscon": ("emscon",), "socket": ("operator",)}
#: Drivers that record joint angles, not marker positions (no ``markers``; a plan ``socket`` section).
JOINT_SENSOR_DRIVERS = ("socket",)
#: Sensor drivers that are laser trackers: one reflector, air for refraction, reflector choice.
TRACKER_DRIVERS = ("tracker", "emscon")

OnLostTarget = Literal["wait", "reacquire", "ask", "skip"]
#: What the run may do when a sensor loses its target (``sequencing.on_lost_target``).
ON_LOST_TARGET: tuple[str, ...] = typing.get_args(OnLostTarget)


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    @field_validator("*", mode="before")
    @classmethod
    def _no_booleans_for_numbers(cls, v: Any, info: ValidationInfo) -> Any:
        # YAML's true/false would otherwise pass as 1/0 for a number.
        if isinstance(v, bool) and info.field_name is not None:
            ann, _ = _unwrap(cls.model_fields[info.field_name].annotation)
            if ann in (int, float):
                raise ValueError(f"expected a number, not {str(v).lower()}")
        return v


# --- sections ------------------------------------------------------------------------------
class CommanderSpec(_Strict):
    """The robot controller's JointCommander: a registry driver name, its URL and options."""

    driver: str = Field(min_length=1, description="Driver name from drivers.registry (built-in: fri, rsi).")
    url: str = Field(min_length=1, description="Where the controller is, e.g. fri://127.0.0.1:30200.")
    options: dict[str, Any] = Field(default_factory=dict, description="Extra keyword arguments for the driver.")


class EnvironmentSpec(_Strict):
    """Air for a laser tracker's refraction correction: the three values (from a thermometer,
    barometer and hygrometer next to the beam), or ``source: station`` for the tracker's own
    weather station."""

    source: Literal["host", "station"] = Field("host", description="host: the values below; station: the tracker's weather station.")
    temperature_c: float | None = Field(None, ge=-40, le=60, description="Air temperature, °C.")
    pressure_hpa: float | None = Field(None, ge=500, le=1200, description="Air pressure, hPa.")
    humidity_pct: float | None = Field(None, ge=0, le=100, description="Relative humidity, %.")

    def driver_value(self) -> dict:
        """What a tracker driver's ``environment=`` takes."""
        values = {"temperature_c": self.temperature_c, "pressure_hpa": self.pressure_hpa,
                  "humidity_pct": self.humidity_pct}
        if self.source == "station":
            if any(v is not None for v in values.values()):
                raise ValueError("environment: source station takes no temperature_c/pressure_hpa/humidity_pct "
                                 "(the station measures them); give one or the other")
            return {"source": "station"}
        missing = [k for k, v in values.items() if v is None]
        if missing:
            raise ValueError(f"environment: {', '.join(missing)} missing; give all three (°C, hPa, %) "
                             "or source: station")
        return values


class ReflectorSpec(_Strict):
    """The reflector a laser tracker follows: its type name as the tracker knows it (e.g.
    RRR15 for a 1.5 in red-ring SMR) and, optionally, its surface offset to check against."""

    type: str = Field(min_length=1, max_length=32, pattern=r"^[A-Za-z0-9._:+ -]+$", description="Reflector type name.")
    offset_mm: float | None = Field(None, ge=0, le=1000, description="Surface offset (centre to contact surface), mm.")


class SensorSpec(_Strict):
    """One reference PositionSensor and the tool markers it measures."""

    name: str = Field(pattern=r"^[A-Za-z0-9_-]+$", max_length=64, description="Device name on the bus.")
    driver: str = Field(min_length=1, description="Driver name from drivers.registry (built-in: natnet, tracker).")
    url: str = Field(min_length=1, description="natnet://host[:port]?… or a pyserial URL (socket://host:port).")
    markers: dict[str, str] = Field(
        default_factory=dict,
        description="Tool marker name (from the robot model) → the driver's selector for it (none for a socket sensor).")
    noise_mm: float = Field(gt=0, le=100, description="Expected measurement noise, 1σ per axis, mm.")
    options: dict[str, Any] = Field(default_factory=dict, description="Extra keyword arguments for the driver.")
    environment: EnvironmentSpec | None = Field(
        None, description="Laser trackers: air for the refraction correction (values or source: station).")
    reflector: ReflectorSpec | None = Field(None, description="Laser trackers: reflector type and surface offset.")
    placement: Frame | None = Field(
        None, description="Where the sensor roughly is: its pose in the robot base frame (xyz mm, zyx deg; a tape "
                          "measure will do). Aims a tracker back at its reflector before three configurations are "
                          "measured; null: a lost beam is searched for until then.")


class GeneratedPoses(_Strict):
    """The paper's plan: seeded Latin-hypercube poses aimed at ``sensor_origin_mm``, every IK
    solution of each (``calib.plan.poses.plan_poses``)."""

    n: int = Field(ge=1, le=10000, description="Number of candidate poses.")
    seed: int = Field(ge=0, description="Seed of the Latin hypercube.")
    sensor_origin_mm: Vec3 = Field(description="Aim point of the flange z-axis, robot base frame, mm.")
    radius_mm: Range = Field((200.0, 500.0), description="[low, high] radius in the base X–Y plane, mm.")
    height_mm: Range = Field((400.0, 800.0), description="[low, high] height along base Z, mm.")
    angle_deg: Range = Field((0.0, 360.0), description="[low, high] base angle about Z, degrees.")
    roll_deg: Range = Field((0.0, 360.0), description="[low, high] tool roll about the aimed axis, degrees.")
    arm_angles_deg: list[float] | None = Field(
        None, description="7-axis arms: further arm angles (degrees) at which to solve every pose."
    )
    min_solutions: int = Field(2, ge=1, le=64, description="Poses with fewer feasible IK solutions are dropped.")
    limit_margin_deg: float = Field(0.0, ge=0, le=45, description="Keep configurations this far inside the limits, degrees "
                                                                  "(at least the commander's margin).")


class CartesianPose(_Strict):
    """One explicit flange pose (robot base frame): every IK solution within limits is visited."""

    xyz_mm: Vec3 = Field(description="Flange position, mm.")
    zyx_deg: Vec3 = Field(description="Flange orientation, ZYX Euler (A, B, C), degrees.")
    group: str | None = Field(
        None, pattern=r"^[A-Za-z0-9_-]+$", max_length=32, description="Pose group id (default c<index>)."
    )
    arm_angle_deg: float | None = Field(None, description="7-axis arms: arm angle, degrees (default: picked).")


class JointsFile(_Strict):
    """Explicit configurations from a configurations file (``calib.plan.poses`` format, degrees)."""

    file: str = Field(min_length=1, description="Path of the CSV file, relative to the plan's folder.")


def _joints_kind(v: Any) -> str:
    return "joint-file" if isinstance(v, dict) else "joint-list"


JointsSpec = Annotated[
    Union[
        Annotated[list[list[float]], Tag("joint-list")],
        Annotated[JointsFile, Tag("joint-file")],
    ],
    Discriminator(_joints_kind),
]
_TAGS = {"joint-list", "joint-file"}


class PosesSpec(_Strict):
    """Exactly one of ``generated``, ``cartesian`` or ``joints``."""

    generated: GeneratedPoses | None = None
    cartesian: list[CartesianPose] | None = Field(None, min_length=1)
    joints: JointsSpec | None = Field(None, description="Lists of joint angles in degrees, or {file: …}.")

    @property
    def kind(self) -> str:
        """"generated", "cartesian", "joints" or "file"."""
        if self.generated is not None:
            return "generated"
        if self.cartesian is not None:
            return "cartesian"
        return "file" if isinstance(self.joints, JointsFile) else "joints"


class SelectionSpec(_Strict):
    """Keep the ``m`` configurations that maximise an observability index (IOOPS)."""

    index: Literal["O1", "O2", "O3", "O4", "O5", "O6"] = "O6"
    m: int = Field(ge=1, description="How many configurations to keep.")
    seed: int = Field(0, ge=0, description="Seed of the random start and exchanges.")
    k: float | None = Field(None, gt=0, description="Weight of O3 in O6 = O1 + k·O3 (default: O1/O3 of the start set).")


class SequencingSpec(_Strict):
    """How each configuration is visited and measured."""

    speed: float = Field(0.3, gt=0, le=1, description="Fraction of the model's joint speeds and accelerations.")
    settle_window_s: float = Field(0.5, gt=0, le=60, description="Robot still and sensor stable for this long, s.")
    settle_tolerance_deg: float = Field(0.01, gt=0, le=1, description="Robot 'still': every joint within this, degrees.")
    sensor_stable_mm: float = Field(0.05, gt=0, le=10, description="Sensor 'stable': readings within this, mm.")
    samples: int = Field(20, ge=1, le=10000, description="Samples averaged per sensor and configuration.")
    move_timeout_s: float = Field(120.0, gt=0, le=3600, description="Longest a move plus settling may take, s.")
    measure_timeout_s: float = Field(10.0, gt=0, le=600, description="Longest one measurement may take, s.")
    retries: int = Field(2, ge=0, le=10, description="Re-tries of a configuration that failed.")
    on_lost_target: OnLostTarget = Field(
        "reacquire", description="On a lost target: wait for it, re-acquire (aim + search), ask the operator, or skip."
    )
    lost_target_wait_s: float = Field(30.0, ge=0, le=3600, description="How long waiting / re-acquiring may take, s "
                                      "(skip: how long a lost target may come back by itself first).")
    robot_fault_wait_s: float = Field(
        30.0, ge=0, le=3600, description="How long a robot fault at a configuration (drives off, safety stop, session "
        "dropped, controller restarted, stale joint state) is waited out before the configuration fails, s.")
    sensor_fault_wait_s: float = Field(
        30.0, ge=0, le=3600, description="How long a sensor that stopped answering or dropped its connection is "
        "waited out at a configuration before the configuration fails, s.")


class OutputSpec(_Strict):
    folder: str = Field("runs", min_length=1, description="Folder of the run logs and results, relative to the plan.")


#: Candidate model names of the default fit (``calib.fit.model_choice``, ``calib.fit.socket_choice``).
FIT_MODELS = tuple(f"{k}{c}" for k in ("offsets", "offsets+tool", "offsets+tool+links", "offsets+ball",
                                       "offsets+ball+links", "full") for c in ("", "+compliance"))


class FitSpec(_Strict):
    """Options of the fit that runs on the log at the end (as ``acquire fit``)."""

    method: Literal["auto", "fast", "paper"] = Field(
        "auto", description="auto: the data choose the model by cross-validation (calib.fit.model_choice; socket data: "
        "calib.fit.socket_choice); fast: the link-prior model with the independence sampler; paper: the paper's "
        "Metropolis (socket data: identification without a link prior).")
    model: Literal[FIT_MODELS] | None = Field(  # type: ignore[valid-type]
        None, description="auto: force this candidate model (as `acquire fit --model`); the comparison table is still written.")
    joints: list[int] | None = Field(None, min_length=1, description="Axis numbers (1-based) to fit; default all.")
    error: Literal["gaussian", "student"] = "gaussian"
    fix_registration: bool = False
    validate_fraction: float | None = Field(None, gt=0, le=0.5, description="Share of the measured configurations held out for validation.")
    link_tolerance_mm: float | None = Field(
        0.2, gt=0, le=5, description="Prior std of link lengths/offsets d, a (mm) marginalised by the fast fit; null: the paper's model."
    )
    link_tolerance_deg: float | None = Field(0.02, gt=0, le=1, description="Prior std of link twists α (and β), degrees.")
    compliance: bool = Field(False, description="Also fit one joint compliance per axis (gravity sag; the robot model needs link masses).")
    tool_prior_mm: float = Field(10.0, ge=0, le=100, description="Prior std (mm per coordinate) of the measured markers' "
                                 "positions on the flange about the robot model's; 0: the model's positions are exact.")


class FakeSpec(_Strict):
    """The simulated cell ``--fake`` runs against."""

    sim_config: str | None = Field(None, min_length=1, description="Cell YAML (drivers.sim.config); default the bundled one.")
    seed: int | None = Field(None, ge=0, description="Overrides the cell's seed.")
    time_scale: float = Field(1.0, gt=0, le=100, description="Simulated seconds per wall second.")


class SocketPoint(_Strict):
    """One socket of a placement: its name and where it roughly is (tape measure, ±10 mm)."""

    name: str = Field(pattern=r"^[A-Za-z0-9_-]+$", max_length=32, description="Socket name, e.g. 0 or 1.")
    xyz_mm: Vec3 = Field(description="Approximate socket centre, robot base frame, mm.")


class SocketPlacement(_Strict):
    """One placement of the socket tool, with its sockets."""

    name: str = Field(pattern=r"^[A-Za-z0-9_-]+$", max_length=32, description="Placement name, e.g. front.")
    sockets: list[SocketPoint] = Field(min_length=1, description="The tool's sockets in this placement.")


class SocketSpec(_Strict):
    """Sensorless socket calibration (``calib.fit.socket``): the robot approaches each socket of each
    placement in ``configurations`` orientations (``calib.plan.socket_poses``), the operator guides
    the ball in, and the socket sensor records the joint angles."""

    ball_mm: Vec3 = Field(description="Nominal ball centre in the flange frame, mm (from the drawing).")
    distance_mm: float | None = Field(None, gt=0, le=5000, description="Distance between the sockets of a "
                                                                       "placement (caliper), mm; null: unknown (no scale).")
    placements: list[SocketPlacement] = Field(min_length=1, description="Where the tool stands, one entry per placement.")
    configurations: int = Field(8, ge=4, le=200, description="Configurations per socket.")
    seed: int = Field(0, ge=0, description="Seed of the orientations tried.")
    tilt_deg: Range = Field((0.0, 45.0), description="[low, high] tilt of the ball axis from the vertical, degrees.")



# --- adaptive: measure until the answer is good enough (issue 27) -------------------------------
class StopWhenSpec(_Strict):
    """The stop rule of an adaptive run, as a metrologist states it; every given criterion must hold."""

    interval_deg: float | None = Field(None, gt=0, le=1, description="Every determinable offset's 95 % interval "
                                       "half-width at most this, degrees (predicted from the configurations measured).")
    workspace_within_pct: float | None = Field(None, ge=0, le=1000, description="Predicted workspace error (the "
                                               "model's uncertainty) within this many % of what the full plan would reach.")
    held_out_within_pct: float | None = Field(None, ge=0, le=1000, description="Predicted held-out error (the model's "
                                              "uncertainty and the sensor's noise) within this many % of the full plan's.")
    region_error_mm: float | None = Field(None, gt=0, le=100, description="Predicted model error (rms, 3-D: the "
                                          "calibrated model's uncertainty and misfit, no sensor noise) at new poses of "
                                          "the plan's region at most this, mm.")
    joint_space_error_mm: float | None = Field(None, gt=0, le=100, description="The same over the robot's working "
                                               "joint space (adaptive.joint_space) at most this, mm.")
    joint_space_within_pct: float | None = Field(None, ge=0, le=1000, description="Predicted model error over the "
                                                 "working joint space within this many % of the full plan's.")


class JointSpaceSpec(_Strict):
    """The robot's working joint space, where ``joint_space_error_mm`` and ``joint_space_within_pct``
    average the predicted model error: configurations drawn uniformly (Latin hypercube) within
    ``ranges_deg``."""

    ranges_deg: list[Range] | None = Field(None, description="[low, high] per joint, degrees, within the model's "
                                           "limits [null: the model's joint limits less the commander's margin].")
    samples: int = Field(200, ge=10, le=5000, description="How many configurations to draw.")
    seed: int = Field(0, ge=0, description="Seed of the draw.")


class CandidatePoolSpec(_Strict):
    """More candidates for the adaptive design than the plan measures: ``extra_poses`` further
    poses of the plan's own generator (``poses.generated``: its ranges, sensor origin, arm angles,
    ``min_solutions`` and limit margin; another seed), every feasible IK branch of each — the
    same region and the same checks as the plan's configurations. The design may choose them;
    the stop rule's errors and "the full plan" stay the plan's configurations."""

    extra_poses: int = Field(ge=1, le=2000, description="How many further candidate poses to generate (each gives "
                                                        "every feasible IK branch as a candidate configuration).")
    seed: int | None = Field(None, ge=0, description="Seed of their Latin hypercube; must differ from the plan's "
                                                     "[null: the plan's seed + 1].")


class AdaptiveSpec(_Strict):
    """Sequential design (``calib.plan.adaptive``): after each configuration the next is chosen among
    the plan's remaining ones by expected gain per second of motion; the run stops when ``stop_when``
    holds (or at ``max_configurations``, or when the plan is exhausted)."""

    stop_when: StopWhenSpec = Field(description="interval_deg, workspace_within_pct, held_out_within_pct (each given must hold).")
    min_configurations: int | None = Field(None, ge=1, le=10000, description="Never stop before this many "
                                           "configurations are measured [null: twice what the fit needs, at least 12].")
    max_configurations: int | None = Field(None, ge=1, le=10000, description="Stop at this many even if the rule "
                                           "is not met [null: the plan's size].")
    candidates: CandidatePoolSpec | None = Field(None, description="A pool of generated configurations beyond the "
                                                 "plan's for the design to choose from [null: the plan's only].")
    joint_space: JointSpaceSpec | None = Field(None, description="The robot's working joint space the joint-space "
                                               "errors average over [null: the model's limits less the margin].")

    def deferred_errors(self) -> list[tuple[tuple, str]]:
        errors: list[tuple[tuple, str]] = []
        w = self.stop_when
        if all(v is None for v in w.model_dump().values()):
            errors.append((("adaptive", "stop_when"), "a stop rule needs a criterion (given none; allowed any of "
                                                      "interval_deg: (0, 1], region_error_mm: (0, 100], "
                                                      "joint_space_error_mm: (0, 100], workspace_within_pct: [0, 1000], "
                                                      "held_out_within_pct: [0, 1000], joint_space_within_pct: [0, 1000])"))
        lo, hi = self.min_configurations, self.max_configurations
        if lo is not None and hi is not None and hi < lo:
            errors.append((("adaptive", "max_configurations"), f"fewer than min_configurations (given {hi}; "
                                                               f"allowed ≥ {lo})"))
        return errors


class Plan(_Strict, CrossFieldChecked):
    """The ``plan.yaml`` schema; see the module docstring."""

    cell: str = Field(pattern=r"^[a-z0-9_-]+$", max_length=64, description="Cell id, the Zenoh key prefix.")
    robot: str = Field(min_length=1, description="Robot model YAML, relative to the plan's folder.")
    commander: CommanderSpec
    sensors: list[SensorSpec] = Field(min_length=1)
    poses: PosesSpec | None = None
    socket: SocketSpec | None = None
    selection: SelectionSpec | None = None
    sequencing: SequencingSpec = SequencingSpec()
    output: OutputSpec = OutputSpec()
    fit: FitSpec = FitSpec()
    fake: FakeSpec | None = None
    adaptive: AdaptiveSpec | None = None  # issue 27: sequential design and its stop rule

    def deferred_errors(self) -> list[tuple[tuple, str]]:
        """Relations between fields that need no robot model, as (field path, message)."""
        errors: list[tuple[tuple, str]] = []
        errors += self._socket_errors()
        errors += self._adaptive_errors()
        given = [k for k in ("generated", "cartesian", "joints") if getattr(self.poses, k, None) is not None]
        if self.poses is not None and len(given) != 1:
            errors.append((("poses",), f"give exactly one pose source (given: {', '.join(given) or 'none'}; "
                                       "allowed: one of generated, cartesian, joints)"))
        for i, sp in enumerate(self.sensors):
            if not sp.markers and sp.driver not in JOINT_SENSOR_DRIVERS:
                errors.append((("sensors", i, "markers"), "List should have at least 1 item after validation, not 0 "
                                                          "(given {}; allowed at least 1 items: tool marker → selector)"))
            if sp.markers and sp.driver in JOINT_SENSOR_DRIVERS:
                errors.append((("sensors", i, "markers"), f"a {sp.driver} sensor records joint angles, not markers "
                                                          f"(given {dict(sp.markers)}; allowed: leave out)"))
        names = [s.name for s in self.sensors]
        for i, name in enumerate(names):
            if names.index(name) != i:
                errors.append((("sensors", i, "name"), f"sensor names must be unique (given {name!r} again; "
                                                       f"allowed: a name not yet used by {', '.join(names[:i])})"))
        g = self.poses.generated if self.poses is not None else None
        if g is not None:
            for key in ("radius_mm", "height_mm", "angle_deg", "roll_deg"):
                lo, hi = getattr(g, key)
                if lo > hi:
                    errors.append((("poses", "generated", key), f"low must not exceed high (given [{lo:g}, {hi:g}]; "
                                                                 "allowed [low, high] with low ≤ high)"))
            if g.radius_mm[0] < 0:
                errors.append((("poses", "generated", "radius_mm"),
                               f"a radius cannot be negative (given low {g.radius_mm[0]:g}; allowed ≥ 0 mm)"))
        if self.poses is not None and self.poses.cartesian:
            groups = [c.group or f"c{i:02d}" for i, c in enumerate(self.poses.cartesian)]
            for i, grp in enumerate(groups):
                if groups.index(grp) != i:
                    errors.append((("poses", "cartesian", i, "group"),
                                   f"pose groups must be unique (given {grp!r}, also pose {groups.index(grp)}; "
                                   "allowed: a new name)"))
        if self.poses is not None and isinstance(self.poses.joints, list) and self.selection is not None:
            n = len(self.poses.joints)
            if self.selection.m > n:
                errors.append((("selection", "m"), f"cannot select more configurations than the plan has "
                                                   f"(given {self.selection.m}; allowed 1…{n})"))
        s = self.sequencing
        if s.settle_window_s >= s.move_timeout_s:
            errors.append((("sequencing", "settle_window_s"),
                           f"the settle window must be shorter than the move timeout (given {s.settle_window_s:g} s; "
                           f"allowed < move_timeout_s = {s.move_timeout_s:g} s)"))
        if self.fit.joints is not None:
            for i, j in enumerate(self.fit.joints):
                if self.fit.joints.index(j) != i:
                    errors.append((("fit", "joints", i), f"axis {j} is listed twice (given {self.fit.joints}; "
                                                         "allowed: each axis once)"))
        return errors

    def _adaptive_errors(self) -> list[tuple[tuple, str]]:
        """The adaptive section's own relations, and that it applies to pose plans only."""
        if self.adaptive is None:
            return []
        errors = self.adaptive.deferred_errors()
        if self.socket is not None:
            errors.append((("adaptive",), "an adaptive order applies to pose plans (given a socket plan; allowed: "
                                          "leave adaptive out — the operator guides every socket)"))
        pool = self.adaptive.candidates
        if pool is not None and self.poses is not None:
            g = self.poses.generated
            if g is None:
                errors.append((("adaptive", "candidates"), f"a candidate pool is generated in the region poses.generated "
                                                           f"declares (given poses.{self.poses.kind}; allowed: "
                                                           "poses.generated, or leave candidates out)"))
            elif pool.seed is not None and pool.seed == g.seed:
                errors.append((("adaptive", "candidates", "seed"), f"the pool's poses must be other than the plan's "
                                                                   f"(given {pool.seed}, the seed of poses.generated; "
                                                                   "allowed: another seed ≥ 0, or null)"))
        return errors

    def _socket_errors(self) -> list[tuple[tuple, str]]:
        """A plan has poses or a socket section (not both); a socket plan has one socket sensor."""
        errors: list[tuple[tuple, str]] = []
        joint_sensors = [i for i, s in enumerate(self.sensors) if s.driver in JOINT_SENSOR_DRIVERS]
        if self.poses is None and self.socket is None:
            errors.append((("poses",), "Field required: the configurations to visit (given: neither poses nor socket; "
                                       "allowed: poses, or a socket section for socket calibration)"))
        elif self.poses is not None and self.socket is not None:
            errors.append((("socket",), "a plan visits poses or sockets, not both (given poses and socket; "
                                        "allowed: one of them — split it into two plans)"))
        if self.socket is not None:
            if len(joint_sensors) != 1 or len(self.sensors) != 1:
                errors.append((("sensors",), f"a socket plan records with exactly one socket sensor and nothing else "
                                             f"(given drivers {[s.driver for s in self.sensors]}; allowed "
                                             "[socket])"))
            sp = self.socket
            lo, hi = sp.tilt_deg
            if not 0 <= lo <= hi <= 90:
                errors.append((("socket", "tilt_deg"), f"tilts run 0 ≤ low ≤ high ≤ 90 (given [{lo:g}, {hi:g}]; "
                                                       "allowed e.g. [0, 45])"))
            names = [p.name for p in sp.placements]
            for i, name in enumerate(names):
                if names.index(name) != i:
                    errors.append((("socket", "placements", i, "name"), f"placement names must be unique (given "
                                                                         f"{name!r} again; allowed a new name)"))
            for i, p in enumerate(sp.placements):
                sn = [s.name for s in p.sockets]
                for j, name in enumerate(sn):
                    if sn.index(name) != j:
                        errors.append((("socket", "placements", i, "sockets", j, "name"),
                                       f"socket names must be unique within a placement (given {name!r} again; "
                                       "allowed a new name)"))
                if sp.distance_mm is not None and len(p.sockets) >= 2:
                    for j in range(1, len(p.sockets)):
                        d = float(np.linalg.norm(np.subtract(p.sockets[j].xyz_mm, p.sockets[0].xyz_mm)))
                        if abs(d - sp.distance_mm) > max(20.0, 0.5 * sp.distance_mm):
                            errors.append((("socket", "placements", i, "sockets", j, "xyz_mm"),
                                           f"{d:.0f} mm from socket {p.sockets[0].name!r}, but distance_mm is "
                                           f"{sp.distance_mm:g} (given {list(p.sockets[j].xyz_mm)}; allowed within "
                                           f"±{max(20.0, 0.5 * sp.distance_mm):.0f} mm of it)"))
        elif joint_sensors:
            i = joint_sensors[0]
            errors.append((("sensors", i, "driver"), f"a {self.sensors[i].driver} sensor needs a socket section "
                                                     "(given no socket section; allowed: add socket:, or another driver)"))
        return errors


# --- loaded and resolved plans ---------------------------------------------------------------
@dataclass(frozen=True)
class LoadedPlan:
    """A validated plan with its robot model, and the exact texts that go into the run log."""

    plan: Plan
    path: Path  # the plan file
    text: str  # its exact text
    model: RobotModel
    model_path: Path
    model_text: str
    marks: Marks = field(default_factory=dict, repr=False, compare=False)  # field path → (line, col)

    @property
    def folder(self) -> Path:
        """The plan file's folder: relative paths in the plan start here."""
        return self.path.resolve().parent

    @property
    def output_dir(self) -> Path:
        """``output.folder`` resolved against the plan's folder."""
        return _resolve(self.folder, self.plan.output.folder)

    @property
    def sim_config_path(self) -> Path:
        """The simulated cell's YAML for ``--fake`` (the bundled default without a ``fake`` section)."""
        if self.plan.fake is not None and self.plan.fake.sim_config:
            return _resolve(self.folder, self.plan.fake.sim_config)
        return default_sim_config()

    @property
    def commander_margin_rad(self) -> float:
        """What the plan's commander keeps clear of every joint limit, rad (asked of its driver
        class, ``CommanderBase.limit_margin_for``): configurations stay at least this far inside."""
        return commander_margin_rad(self.plan)[0]

    def error(self, loc: tuple, message: str) -> ConfigError:
        """A ConfigError ``file:line:col: field: message`` for a problem found after loading."""
        return ConfigError(error_line(self.path, self.marks, loc, message))


@dataclass(frozen=True, eq=False)
class PlannedConfig:
    """One configuration to visit. q_rad: (n_joints,) rad, controller convention (read-only).

    Equal when id, pose, branch and angles are; hashed by ``config_id`` (usable in sets and
    as dict keys).
    """

    config_id: str  # stable id, e.g. "p07-b3"; unique in the run; resume matches on it
    pose: str  # pose group id ("" for explicit joint lists)
    branch: str  # IK branch label ("" when not from IK)
    q_rad: np.ndarray
    socket: tuple[str, str] | None = None  # (placement, socket) of a socket plan: the operator guides the ball in

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, PlannedConfig):
            return NotImplemented
        return (self.config_id, self.pose, self.branch) == (other.config_id, other.pose, other.branch) and bool(
            np.array_equal(self.q_rad, other.q_rad)
        )

    def __hash__(self) -> int:
        return hash(self.config_id)


@dataclass(frozen=True)
class ResolvedPlan:
    """What ``poses`` (and ``selection``) resolve to, with the numbers a dry run reports.

    source: "generated" | "cartesian" | "joints" | "file"; candidates: poses tried (or rows
    read); pose_groups: the kept pose groups in order; dropped: (pose group, reason);
    before_selection: configuration count before ``selection``; selection: the IOOPS result
    (``calib.plan.observability.Selection``) or None.
    """

    configs: list[PlannedConfig]
    source: str
    candidates: int
    pose_groups: list[str]
    dropped: list[tuple[str, str]]
    before_selection: int
    selection: Any = None


# --- errors ------------------------------------------------------------------------------------


def _short(value: Any, limit: int = 60) -> str:
    """``value`` as the plan file spells it (YAML's true/false/null), cut to ``limit`` characters."""
    text = {True: "true", False: "false", None: "null"}.get(value, None) if isinstance(value, (bool, type(None))) else None
    text = text or repr(value)
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _unwrap(ann: Any) -> tuple[Any, list]:
    """Strip Annotated (keeping its metadata) and Optional."""
    meta: list = []
    while True:
        if typing.get_origin(ann) is Annotated:
            meta += list(ann.__metadata__)
            ann = ann.__origin__
            continue
        if typing.get_origin(ann) in (Union, types.UnionType):
            members = [a for a in typing.get_args(ann) if a is not type(None)]
            if len(members) == 1:
                ann = members[0]
                continue
        return ann, meta


def _union_member(ann: Any, tag: str) -> Any | None:
    for member in typing.get_args(ann):
        for m in getattr(member, "__metadata__", ()):
            if isinstance(m, Tag) and m.tag == tag:
                return member
    return None


def _field_at(loc: tuple) -> tuple[Any, FieldInfo | None, list]:
    """The annotation, FieldInfo and metadata at ``loc`` (raw pydantic loc) inside ``Plan``."""
    ann: Any = Plan
    info: FieldInfo | None = None
    meta: list = []
    for part in loc:
        ann, extra = _unwrap(ann)
        meta += extra
        if isinstance(part, str) and part in _TAGS:
            member = _union_member(ann, part)
            if member is None:
                return None, None, []
            ann = member
            continue
        if isinstance(ann, type) and issubclass(ann, BaseModel) and isinstance(part, str):
            f = ann.model_fields.get(part)
            if f is None:
                return None, None, []
            ann, info, meta = f.annotation, f, list(f.metadata)
            continue
        origin, args = typing.get_origin(ann), typing.get_args(ann)
        if origin in (list, tuple) and isinstance(part, int) and args:
            ann, info, meta = args[0], None, []
        elif origin is dict and len(args) == 2:
            ann, info, meta = args[1], None, []
        else:
            return None, None, []
    ann, extra = _unwrap(ann)
    return ann, info, meta + extra


def _describe(ann: Any, plural: bool = False) -> str:
    """Plain words for what a field of type ``ann`` takes (``plural``: for items of a list)."""
    ann, _ = _unwrap(ann)
    origin, args = typing.get_origin(ann), typing.get_args(ann)
    if ann is float:
        return "finite numbers" if plural else "a finite number"
    if ann is int:
        return "integers" if plural else "an integer"
    if ann is bool:
        return "true or false"
    if ann is str:
        return "texts" if plural else "text"
    if origin is Literal:
        return "one of " + ", ".join(str(a) for a in args)
    if origin is tuple:
        names = {2: "[low, high]", 3: "[x, y, z]"}.get(len(args), "")
        return f"{len(args)} numbers {names}".rstrip()
    if origin is list:
        inner = _describe(args[0], plural=True) if args else "items"
        return f"lists of {inner}" if plural else f"a list of {inner}"
    if origin is dict:
        return "mappings" if plural else "a mapping"
    if origin in (Union, types.UnionType):
        return " or ".join(_describe(a, plural) for a in args if a is not type(None))
    if isinstance(ann, type) and issubclass(ann, BaseModel):
        keys = ", ".join(ann.model_fields)
        return f"mappings with keys {keys}" if plural else f"a mapping with keys {keys}"
    return getattr(ann, "__name__", str(ann))


def _bounds(meta: list) -> str | None:
    lo = hi = None
    lo_open = hi_open = False
    for m in meta:
        if isinstance(m, annotated_types.Gt):
            lo, lo_open = m.gt, True
        elif isinstance(m, annotated_types.Ge):
            lo, lo_open = m.ge, False
        elif isinstance(m, annotated_types.Lt):
            hi, hi_open = m.lt, True
        elif isinstance(m, annotated_types.Le):
            hi, hi_open = m.le, False
    if lo is None and hi is None:
        return None
    if hi is None:
        return f"{'>' if lo_open else '≥'} {lo:g}"
    if lo is None:
        return f"{'<' if hi_open else '≤'} {hi:g}"
    return f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"


def _allowed(err: dict) -> str:
    loc = tuple(err["loc"])
    kind = err["type"]
    ctx = err.get("ctx") or {}
    if kind == "extra_forbidden":
        parent, _, _ = _field_at(loc[:-1])
        if isinstance(parent, type) and issubclass(parent, BaseModel):
            return "keys " + ", ".join(parent.model_fields)
        return "no other keys"
    if loc and loc[-1] in _TAGS and kind in ("list_type", "model_type", "dict_type"):
        return "lists of joint angles in degrees, or {file: <configurations file>}"
    ann, _, meta = _field_at(loc)
    if kind == "literal_error":
        return str(ctx.get("expected", ""))
    if kind == "string_pattern_mismatch":
        return f"text matching {ctx.get('pattern')}"
    if kind in ("too_short", "too_long") and typing.get_origin(ann) is tuple:
        return _describe(ann)
    if kind in ("too_short", "too_long", "string_too_short", "string_too_long"):
        lo = ctx.get("min_length")
        hi = ctx.get("max_length")
        what = "characters" if kind.startswith("string") else "items"
        if kind.endswith("too_short"):
            return f"at least {lo} {what}"
        return f"at most {hi} {what}"
    bounds = _bounds(meta)
    if bounds is not None and kind in ("greater_than", "greater_than_equal", "less_than", "less_than_equal"):
        return bounds
    if ann is not None:
        text = _describe(ann)
        if not bounds:
            return text
        return f"{text} in {bounds}" if bounds[0] in "([" else f"{text} {bounds}"
    return "see the plan format in acquire/plan/schema.py"


def format_plan_errors(path: Path | str, exc: ValidationError, marks: Marks) -> list[tuple[tuple[int, int], str]]:
    """Each pydantic error as ((line, col), ``file:line:col: field: message (given …; allowed …)``)."""
    out = []
    for err in exc.errors(include_url=False):
        raw = tuple(err["loc"])
        if err["type"] == "missing" and raw and isinstance(raw[-1], int):
            # A fixed-length tuple given too few values: report the tuple, not its missing slot.
            ann, _, _ = _field_at(raw[:-1])
            err = {**err, "loc": raw[:-1], "type": "too_short",
                   "msg": f"Expected {len(typing.get_args(ann)) or 'more'} values"}
            raw = raw[:-1]
        loc = tuple(p for p in raw if not (isinstance(p, str) and (p in _TAGS or "[" in p or "function-" in p)))
        where = locate(loc, marks) or (0, 0)
        msg = err["msg"]
        allowed = _allowed(err)
        if err["type"] == "missing":
            detail = f"(given nothing; allowed: {allowed})"
        elif err["type"] == "extra_forbidden":
            detail = f"(given {loc[-1]!r}; allowed {allowed})"
        else:
            detail = f"(given {_short(err.get('input'))}; allowed {allowed})"
        out.append((where, error_line(path, marks, loc, f"{msg} {detail}")))
    return out


# --- loading -----------------------------------------------------------------------------------
def _resolve(folder: Path, name: str) -> Path:
    p = Path(name).expanduser()
    return p if p.is_absolute() else (folder / p).resolve()


def _driver_role(name: str) -> tuple[str | None, str | None]:
    """("sensor" | "commander" | None, problem) for registry driver ``name`` (imports it)."""
    from drivers.registry import load_driver

    try:
        cls = load_driver(name)
    except (ValueError, ImportError) as exc:
        return None, str(exc)
    if callable(getattr(cls, "move_to", None)):
        return "commander", None
    if callable(getattr(cls, "measure", None)) or callable(getattr(cls, "capture", None)):
        return "sensor", None
    return None, f"driver {name!r} ({cls.__module__}.{cls.__qualname__}) is neither a sensor nor a commander"


def _check_driver(loc: tuple, name: str, role: str) -> list[tuple[tuple, str]]:
    from drivers.registry import known_drivers

    known = known_drivers()
    if name not in known:
        return [(loc, f"unknown driver (given {name!r}; allowed: {', '.join(sorted(known))})")]
    got, problem = _driver_role(name)
    if problem:
        return [(loc, f"{problem} (given {name!r})")]
    if got != role:
        want = [n for n in sorted(known) if _driver_role(n)[0] == role]
        return [(loc, f"driver {name!r} is a {got}, not a {role} (given {name!r}; allowed {', '.join(want)})")]
    return []


def _check_url(loc: tuple, driver: str, url: str) -> list[tuple[tuple, str]]:
    schemes = URL_SCHEMES.get(driver)
    if not schemes:
        return []
    scheme = url.partition("://")[0] if "://" in url else ""
    if scheme not in schemes:
        return [(loc, f"the {driver} driver takes a {schemes[0]}:// URL "
                      f"(given {url!r}; allowed {schemes[0]}://host:port[?options])")]
    return []


def model_errors(plan: Plan, model: RobotModel, folder: Path) -> list[tuple[tuple, str]]:
    """Relations between the plan, the robot model, the driver registry and the files it names."""
    errors: list[tuple[tuple, str]] = []
    c = plan.commander
    errors += _check_driver(("commander", "driver"), c.driver, "commander")
    errors += _check_url(("commander", "url"), c.driver, c.url)
    wanted = CONTROLLER_OF_DRIVER.get(c.driver)
    if wanted and model.controller not in (wanted, "generic"):
        ok = [d for d, ctl in CONTROLLER_OF_DRIVER.items() if ctl == model.controller]
        errors.append((("commander", "driver"),
                       f"{model.name} has a {model.controller!r} controller, the {c.driver} driver speaks to "
                       f"{wanted!r} (given {c.driver!r}; allowed {', '.join(ok) or 'a driver for ' + model.controller})"))

    tool = model.marker_names
    for i, s in enumerate(plan.sensors):
        errors += _check_driver(("sensors", i, "driver"), s.driver, "sensor")
        errors += _check_url(("sensors", i, "url"), s.driver, s.url)
        for name, selector in s.markers.items():
            loc = ("sensors", i, "markers", name)
            if name not in tool:
                errors.append((loc, f"marker not on the robot's tool {model.tool.name!r} "
                                    f"(given {name!r}; allowed {', '.join(tool)})"))
            if s.driver == "natnet":
                from drivers.natnet.client import MarkerSelector

                try:
                    MarkerSelector.parse(selector)
                except (TypeError, ValueError):
                    errors.append((loc, f"not a NatNet marker selector (given {selector!r}; "
                                        f"allowed {MarkerSelector.SYNTAX})"))
        if s.environment is not None:
            try:
                s.environment.driver_value()
            except ValueError as exc:
                errors.append((("sensors", i, "environment"), str(exc)))
        if (s.environment is not None or s.reflector is not None) and s.driver not in TRACKER_DRIVERS:
            key = "environment" if s.environment is not None else "reflector"
            errors.append((("sensors", i, key), f"{key} applies to laser trackers "
                                                f"(given driver {s.driver!r}; allowed drivers {', '.join(TRACKER_DRIVERS)})"))
        if s.driver in TRACKER_DRIVERS and len(s.markers) != 1:
            errors.append((("sensors", i, "markers"), f"a laser tracker follows one reflector "
                                                      f"(given {len(s.markers)}: {', '.join(s.markers)}; allowed 1)"))

    n = model.n_joints
    p = plan.poses if plan.poses is not None else PosesSpec()
    if p.generated is not None and p.generated.arm_angles_deg and n != 7:
        errors.append((("poses", "generated", "arm_angles_deg"),
                       f"arm angles apply to 7-axis arms; {model.name} has {n} axes "
                       f"(given {p.generated.arm_angles_deg}; allowed: leave out)"))
    for i, cp in enumerate(p.cartesian or []):
        if cp.arm_angle_deg is not None and n != 7:
            errors.append((("poses", "cartesian", i, "arm_angle_deg"),
                           f"arm angles apply to 7-axis arms; {model.name} has {n} axes "
                           f"(given {cp.arm_angle_deg:g}; allowed: leave out)"))
    try:
        margin, driver = commander_margin_rad(plan)
    except ValueError as exc:
        errors.append((("commander", "options", "limit_margin_rad"), f"{exc} (allowed: an angle ≥ 0 in radians)"))
        margin, driver = 0.0, c.driver
    if isinstance(p.joints, list):
        errors += _joint_list_errors(p.joints, model, margin, driver)
    elif isinstance(p.joints, JointsFile):
        errors += _joints_file_errors(p.joints, model, folder, plan.selection, margin, driver)
    errors += plan_units_errors(plan, model)
    errors += confirm_input_errors(plan)
    errors += _joint_space_errors(plan, model)

    if plan.fit.joints is not None:
        for i, j in enumerate(plan.fit.joints):
            if not 1 <= j <= n:
                errors.append((("fit", "joints", i), f"no such axis on {model.name} (given {j}; allowed 1…{n}: "
                                                     f"{', '.join(model.axis_names)})"))
    out = _resolve(folder, plan.output.folder)
    if out.exists() and not out.is_dir():
        errors.append((("output", "folder"), f"exists and is not a folder (given {plan.output.folder!r} → {out}; "
                                             "allowed: a folder, created if missing)"))
    return errors


def _joint_space_errors(plan: Plan, model: RobotModel) -> list[tuple[tuple, str]]:
    """``adaptive.joint_space.ranges_deg``: one [low, high] per joint, low < high, within the model's limits."""
    spec = plan.adaptive.joint_space if plan.adaptive is not None else None
    if spec is None or spec.ranges_deg is None:
        return []
    loc, n = ("adaptive", "joint_space", "ranges_deg"), model.n_joints
    if len(spec.ranges_deg) != n:
        return [(loc, f"{model.name} has {n} joints (given {len(spec.ranges_deg)} ranges; allowed one [low, high] "
                      f"per joint: {', '.join(model.axis_names)})")]
    errors = []
    lo_lim, hi_lim = np.degrees(model.lower_limits_rad), np.degrees(model.upper_limits_rad)
    for i, (lo, hi) in enumerate(spec.ranges_deg):
        if not lo < hi:
            errors.append(((*loc, i), f"low must be below high (given [{lo:g}, {hi:g}]; allowed [low, high], low < high)"))
        elif lo < lo_lim[i] - 1e-9 or hi > hi_lim[i] + 1e-9:
            errors.append(((*loc, i), f"outside {model.axis_names[i]}'s limits (given [{lo:g}, {hi:g}]; allowed within "
                                      f"[{lo_lim[i]:g}, {hi_lim[i]:g}] degrees)"))
    return errors


def _joint_list_errors(rows: list[list[float]], model: RobotModel, margin_rad: float = 0.0,
                       driver: str = "") -> list[tuple[tuple, str]]:
    errors: list[tuple[tuple, str]] = []
    n = model.n_joints
    for i, row in enumerate(rows):
        if len(row) != n:
            errors.append((("poses", "joints", i), f"wrong number of joint angles for {model.name} "
                                                   f"(given {len(row)}; allowed {n}: {', '.join(model.axis_names)})"))
    # Outside the limits, or inside the margin the commander keeps from them (it would refuse mid-run).
    return errors + joints_margin_errors(rows, model, margin_rad, driver)


def _joints_file_errors(spec: JointsFile, model: RobotModel, folder: Path, selection: SelectionSpec | None,
                        margin_rad: float = 0.0, driver: str = ""):
    from calib.plan.poses import read_configurations

    loc = ("poses", "joints", "file")
    path = _resolve(folder, spec.file)
    if not path.is_file():
        return [(loc, f"file not found (given {spec.file!r} → {path}; allowed: a configurations file, "
                      f"relative to the plan's folder {folder})")]
    try:
        cf = read_configurations(path, model)
    except ConfigError as exc:
        return [(loc, f"the configurations file is not usable: {exc}")]
    errors: list[tuple[tuple, str]] = []
    if not cf.configurations:
        errors.append((loc, f"the configurations file has no rows (given {path}; allowed: at least one configuration)"))
    numbers = [c.config for c in cf.configurations]
    dup = sorted({k for k in numbers if numbers.count(k) > 1})
    if dup:
        errors.append((loc, f"config numbers repeat in {path.name} (given {dup[:5]}; allowed: each number once)"))
    rows = [(c.config, np.degrees(c.q)) for c in cf.configurations]
    refused = describe_config_rows(rows, model, margin_rad, driver)
    if refused:
        errors.append((loc, f"{path.name}: the commander would refuse these targets mid-run: " + "; ".join(refused)))
    why = radians_problem([q for _, q in rows], model) if rows else None
    if why:
        errors.append((loc, f"{path.name}: {why}"))
    if selection is not None and selection.m > len(numbers):
        errors.append((("selection", "m"), f"cannot select more configurations than {path.name} has "
                                           f"(given {selection.m}; allowed 1…{len(numbers)})"))
    return errors


def load_plan(path: str | Path) -> LoadedPlan:
    """Read, validate and cross-check a plan file; load its robot model.

    Raises ``ConfigError`` (a ValueError) listing every problem found, one a line, as
    ``file:line:col: field: message (given …; allowed …)``. Connects to nothing.
    """
    path = Path(path)
    text = read_yaml_text(path)  # read once: the text recorded is the text validated
    data, marks = parse_yaml_text(text, path)
    if not isinstance(data, dict):
        raise ConfigError(f"{path}:1:1: (top level): a plan is a mapping of sections "
                          f"(given {type(data).__name__}; allowed keys {', '.join(Plan.model_fields)})")
    try:
        plan = Plan.model_validate(data, context={"defer_cross_field_checks": True})
    except ValidationError as exc:
        problems = format_plan_errors(path, exc, marks)
        raise ConfigError("\n".join(msg for _, msg in sorted(problems, key=lambda p: p[0]))) from None

    errors = plan.deferred_errors()
    folder = path.resolve().parent
    model_path = _resolve(folder, plan.robot)
    model: RobotModel | None = None
    if not model_path.is_file():
        here = sorted(q.name for q in model_path.parent.glob("*.yaml")) if model_path.parent.is_dir() else []
        hint = f"; models in {model_path.parent}: {', '.join(here)}" if here else ""
        errors.append((("robot",), f"robot model file not found (given {plan.robot!r} → {model_path}; "
                                   f"allowed: a robot model YAML, relative to the plan's folder{hint})"))
    else:
        try:
            model = load_robot_model(model_path)
        except ConfigError as exc:
            errors.append((("robot",), f"the robot model is not valid (given {plan.robot!r}):\n{exc}"))
    model_lines: list[str] = []
    if model is not None:
        errors += model_errors(plan, model, folder)
        model_lines = model_units_errors(model, model_path, load_yaml_with_marks(model_path)[1])
        if model_lines:
            errors.append((("robot",), f"the robot model's units are wrong (given {plan.robot!r}; allowed: a model "
                                       "in mm and degrees; see below)"))
    if errors:
        located = sorted(((locate(tuple(loc), marks) or (0, 0)), error_line(path, marks, loc, msg)) for loc, msg in errors)
        raise ConfigError("\n".join([msg for _, msg in located] + model_lines))
    assert model is not None
    lp = LoadedPlan(plan=plan, path=path, text=text, model=model, model_path=model_path,
                    model_text=model_path.read_text(encoding="utf-8"), marks=marks)
    log.info("plan %s: cell %s, robot %s, %s poses, %d sensor(s)", path, plan.cell, model.name,
             plan.poses.kind if plan.poses is not None else "socket", len(plan.sensors))
    return lp


# --- resolution --------------------------------------------------------------------------------
def _frozen(q: np.ndarray) -> np.ndarray:
    a = np.array(q, dtype=float)
    a.flags.writeable = False
    return a


def _generated(lp: LoadedPlan) -> ResolvedPlan:
    from calib.plan.poses import PoseRanges, plan_poses

    g = lp.plan.poses.generated
    assert g is not None
    ranges = PoseRanges(
        radius_mm=g.radius_mm,
        height_mm=g.height_mm,
        angle_rad=(math.radians(g.angle_deg[0]), math.radians(g.angle_deg[1])),
        roll_rad=(math.radians(g.roll_deg[0]), math.radians(g.roll_deg[1])),
    )
    try:
        pp = plan_poses(
            lp.model, g.sensor_origin_mm, n=g.n, seed=g.seed, ranges=ranges,
            extra_arm_angles_rad=[math.radians(a) for a in (g.arm_angles_deg or [])],
            min_solutions=g.min_solutions,
            # At least the commander's margin: a configuration it would refuse is not planned.
            limit_margin_rad=max(math.radians(g.limit_margin_deg), lp.commander_margin_rad),
        )
    except ValueError as exc:  # a sample on the sensor origin, a model the IK cannot solve
        raise lp.error(("poses", "generated"), f"cannot plan these poses: {exc}") from exc
    width = max(2, len(str(g.n - 1)))
    configs: list[PlannedConfig] = []
    within: dict[int, int] = {}
    for c in pp.configurations:
        b = within.get(c.pose, 0)
        within[c.pose] = b + 1
        group = f"p{c.pose:0{width}d}"
        configs.append(PlannedConfig(f"{group}-b{b}", group, c.branch, _frozen(c.q)))
    return ResolvedPlan(
        configs=configs, source="generated", candidates=pp.candidates.n,
        pose_groups=[f"p{k:0{width}d}" for k in pp.valid],
        dropped=[(f"p{d.pose:0{width}d}", d.reason) for d in pp.dropped],
        before_selection=len(configs),
    )


def _cartesian(lp: LoadedPlan) -> ResolvedPlan:
    from calib.ik import ik
    from calib.robot.transforms import pose_to_matrix

    poses = lp.plan.poses.cartesian or []
    configs: list[PlannedConfig] = []
    groups: list[str] = []
    margin = lp.commander_margin_rad
    for i, cp in enumerate(poses):
        group = cp.group or f"c{i:02d}"
        pose = pose_to_matrix(np.array(cp.xyz_mm), np.radians(cp.zyx_deg))
        psi = None if cp.arm_angle_deg is None else math.radians(cp.arm_angle_deg)
        try:
            sol = ik.solve_all(lp.model, pose, arm_angle=psi, within_limits=True)
        except ValueError as exc:  # e.g. no feasible arm angle, a model outside the solvers' class
            raise lp.error(("poses", "cartesian", i), f"no inverse kinematics for this pose: {exc}") from exc
        if len(sol) == 0:
            raise lp.error(("poses", "cartesian", i),
                           f"no IK solution of {lp.model.name} within its joint limits "
                           f"(given xyz_mm {list(cp.xyz_mm)}, zyx_deg {list(cp.zyx_deg)}; allowed: a pose it reaches "
                           f"within its limits) — {sol.status}: {sol.message}")
        if sol.status == "singular":
            log.warning("cartesian pose %s is singular: %s", group, sol.message)
        # Solutions inside the commander's limit margin would be refused mid-run: not planned.
        keep = lp.model.within_limits(np.asarray(sol.q), margin)
        if not np.any(keep):
            raise lp.error(("poses", "cartesian", i),
                           f"every IK solution of {lp.model.name} for this pose lies within the commander's "
                           f"{math.degrees(margin):g}° margin of a joint limit (given xyz_mm "
                           f"{list(cp.xyz_mm)}, zyx_deg {list(cp.zyx_deg)}; allowed: a pose it reaches at least that "
                           "far inside its limits)")
        if not np.all(keep):
            log.info("cartesian pose %s: %d of %d IK solutions lie within the commander's limit margin; not planned",
                     group, int(np.sum(~keep)), len(keep))
        groups.append(group)
        kept = [(q, label) for q, label, k in zip(sol.q, sol.branch, keep) if k]
        for b, (q, label) in enumerate(kept):
            configs.append(PlannedConfig(f"{group}-b{b}", group, label, _frozen(q)))
    return ResolvedPlan(configs=configs, source="cartesian", candidates=len(poses), pose_groups=groups,
                        dropped=[], before_selection=len(configs))


def _joints(lp: LoadedPlan) -> ResolvedPlan:
    from calib.plan.poses import read_configurations

    spec = lp.plan.poses.joints
    if isinstance(spec, JointsFile):
        cf = read_configurations(_resolve(lp.folder, spec.file), lp.model)
        configs = [PlannedConfig(f"c{c.config:03d}", f"p{c.pose:02d}", c.branch, _frozen(c.q)) for c in cf.configurations]
        groups = list(dict.fromkeys(c.pose for c in configs))
        return ResolvedPlan(configs=configs, source="file", candidates=len(configs), pose_groups=groups,
                            dropped=[], before_selection=len(configs))
    rows = spec or []
    width = max(3, len(str(len(rows) - 1)))
    configs = [PlannedConfig(f"j{i:0{width}d}", "", "", _frozen(np.radians(r))) for i, r in enumerate(rows)]
    return ResolvedPlan(configs=configs, source="joints", candidates=len(configs), pose_groups=[],
                        dropped=[], before_selection=len(configs))


def _socket(lp: LoadedPlan) -> ResolvedPlan:
    """Approach configurations for every socket of every placement (``calib.plan.socket_poses``).
    Ids ``<placement>-s<socket>-k<kk>``; pose group ``<placement>/<socket>``; ``socket`` set."""
    from calib.plan.socket_poses import socket_approaches

    sp = lp.plan.socket
    assert sp is not None
    configs: list[PlannedConfig] = []
    groups: list[str] = []
    margin = lp.commander_margin_rad
    width = max(2, len(str(sp.configurations - 1)))
    for i, pl in enumerate(sp.placements):
        for j, so in enumerate(pl.sockets):
            seed = sp.seed + 1000 * i + j  # each socket its own orientations, same plan → same ones
            try:
                found = socket_approaches(lp.model, so.xyz_mm, sp.ball_mm, sp.configurations, seed=seed,
                                          tilt_deg=sp.tilt_deg, limit_margin_rad=margin)
            except ValueError as exc:
                raise lp.error(("socket", "placements", i, "sockets", j, "xyz_mm"), str(exc)) from exc
            group = f"{pl.name}/{so.name}"
            groups.append(group)
            for k, a in enumerate(found):
                configs.append(PlannedConfig(f"{pl.name}-s{so.name}-k{k:0{width}d}", group, a.branch, _frozen(a.q),
                                             socket=(pl.name, so.name)))
    return ResolvedPlan(configs=configs, source="socket", candidates=len(configs), pose_groups=groups,
                        dropped=[], before_selection=len(configs))


def _select(lp: LoadedPlan, resolved: ResolvedPlan) -> ResolvedPlan:
    from calib.fit.identification import information_blocks
    from calib.plan.observability import ioops

    sel = lp.plan.selection
    assert sel is not None
    n = len(resolved.configs)
    if sel.m > n:
        raise lp.error(("selection", "m"), f"cannot select more configurations than the poses give "
                                           f"(given {sel.m}; allowed 1…{n})")
    if sel.m == n:
        log.info("selection keeps all %d configurations", n)
        return resolved
    q = np.stack([c.q_rad for c in resolved.configs])
    blocks, names, _ = information_blocks(lp.model, q)
    chosen = ioops(blocks, sel.m, index=sel.index, k=sel.k, seed=sel.seed)
    keep = [resolved.configs[i] for i in chosen.chosen]
    log.info("selection: %d of %d configurations by IOOPS on %s (%d parameters): %.6g → %.6g",
             sel.m, n, sel.index, len(names), chosen.start_value, chosen.value)
    groups = [g for g in resolved.pose_groups if any(c.pose == g for c in keep)]
    return ResolvedPlan(configs=keep, source=resolved.source, candidates=resolved.candidates, pose_groups=groups,
                        dropped=resolved.dropped, before_selection=n, selection=chosen)


def resolve_plan(lp: LoadedPlan) -> ResolvedPlan:
    """The configurations of ``lp`` with what a dry run reports (dropped poses, selection).

    Deterministic: generated poses and the selection are seeded. Raises ConfigError pointing
    at the plan's line when a pose has no IK solution or a selection is larger than the
    configurations it selects from.
    """
    kind = lp.plan.poses.kind if lp.plan.poses is not None else "socket"
    if kind == "socket":
        resolved = _socket(lp)
    elif kind == "generated":
        resolved = _generated(lp)
    elif kind == "cartesian":
        resolved = _cartesian(lp)
    else:
        resolved = _joints(lp)
    if not resolved.configs:
        raise lp.error(("poses",), f"the poses give no configuration within the limits of {lp.model.name} "
                                   f"(given {resolved.candidates} candidate(s); allowed: at least one configuration)")
    if lp.plan.selection is not None:
        resolved = _select(lp, resolved)
    margin = lp.commander_margin_rad
    refused = [c for c in resolved.configs if not lp.model.within_limits(c.q_rad, margin)]
    if refused:  # a safety net: the checks above keep every kind of pose inside the margin
        raise lp.error(("poses",), f"{len(refused)} configuration(s) lie within the commander's "
                                   f"{math.degrees(margin):g}° margin of a joint limit (given {refused[0].config_id} "
                                   f"at {np.round(np.degrees(refused[0].q_rad), 3).tolist()}°; allowed: inside the "
                                   "limits less the margin)")
    ids = [c.config_id for c in resolved.configs]
    assert len(set(ids)) == len(ids), "configuration ids must be unique"
    return resolved


def resolve_configurations(lp: LoadedPlan) -> list[PlannedConfig]:
    """The plan's joint configurations (not yet ordered), each with a stable id."""
    return resolve_plan(lp).configs


def resolve_candidate_pool(lp: LoadedPlan) -> list[PlannedConfig]:
    """The adaptive design's generated candidates beyond the plan (``adaptive.candidates``; [] without
    one): ``extra_poses`` poses of the plan's own generator with the pool's seed, every feasible IK
    branch, through the same checks as the plan's configurations (``plan_poses``: FK reproduces the
    aimed pose, joint limits less the larger of the plan's and the commander's margin,
    ``min_solutions``; then the commander's margin again). Ids ``x07-b1`` (extra pose 7, its second
    branch), pose group ``x07``: seeded, so a resumed run finds the same ones. Deterministic."""
    ad = lp.plan.adaptive
    pool = ad.candidates if ad is not None else None
    if pool is None:
        return []
    g = lp.plan.poses.generated if lp.plan.poses is not None else None
    assert g is not None, "load_plan refuses a pool without poses.generated"
    seed = g.seed + 1 if pool.seed is None else pool.seed
    return region_configurations(lp, pool.extra_poses, seed, "x", ("adaptive", "candidates"), "candidate")


def region_configurations(lp: LoadedPlan, n: int, seed: int, prefix: str, loc: tuple = ("poses", "generated"),
                          what: str = "configuration") -> list[PlannedConfig]:
    """``n`` more poses of the plan's generated region (``poses.generated``: its ranges, sensor,
    arm angles and ``min_solutions``) with another ``seed``, every feasible IK branch, through the
    checks of the plan's own configurations; ids ``<prefix>07-b1``, pose groups ``<prefix>07``.
    Deterministic. Raises ConfigError at ``loc`` when the region cannot be sampled so."""
    from calib.plan.poses import PoseRanges, plan_poses

    g = lp.plan.poses.generated if lp.plan.poses is not None else None
    if g is None:
        raise lp.error(("poses",), f"fresh configurations come from the plan's generated region (given a "
                                   f"{lp.plan.poses.kind if lp.plan.poses is not None else 'socket'} plan; allowed: "
                                   "a plan with poses.generated)")
    ranges = PoseRanges(radius_mm=g.radius_mm, height_mm=g.height_mm,
                        angle_rad=(math.radians(g.angle_deg[0]), math.radians(g.angle_deg[1])),
                        roll_rad=(math.radians(g.roll_deg[0]), math.radians(g.roll_deg[1])))
    margin = lp.commander_margin_rad
    try:
        pp = plan_poses(lp.model, g.sensor_origin_mm, n=n, seed=seed, ranges=ranges,
                        extra_arm_angles_rad=[math.radians(a) for a in (g.arm_angles_deg or [])],
                        min_solutions=g.min_solutions, limit_margin_rad=max(math.radians(g.limit_margin_deg), margin))
    except ValueError as exc:
        raise lp.error(loc, f"cannot generate these {what}s: {exc}") from exc
    width = max(2, len(str(n - 1)))
    out: list[PlannedConfig] = []
    within: dict[int, int] = {}
    for c in pp.configurations:
        b = within[c.pose] = within.get(c.pose, -1) + 1
        group = f"{prefix}{c.pose:0{width}d}"
        out.append(PlannedConfig(f"{group}-b{b}", group, c.branch, _frozen(c.q)))
    refused = [c for c in out if not lp.model.within_limits(c.q_rad, margin)]
    if refused:  # the same safety net as the plan's own configurations (resolve_plan)
        raise lp.error(loc, f"{len(refused)} generated {what}(s) lie within the commander's {math.degrees(margin):g}° margin of "
                            f"a joint limit (given {refused[0].config_id}; allowed: inside the limits less the margin)")
    return out
