"""Configuration of the simulated cell (``SimConfig``), loadable from YAML.

File units are mm and degrees (converted to radians inside ``SimCell``). Layout, with the
defaults this module applies (see ``fixtures/sim/default.yaml`` for a documented example):

    seed: 0                       # every random draw of the cell derives from this
    robot: ../robots/x.yaml       # robot model; a relative path is taken from the YAML's folder
    initial_joint_positions_deg: [..]   # n values (default all zero)
    end_stop_margin_deg: 2.0      # the arm refuses positions this far beyond its limits
    truth:                        # the hidden errors of the real robot
      offsets_deg: null           # n explicit zero-offsets, or null → drawn N(0, offset_std_deg)
      offset_std_deg: 0.3
      link_errors: {d_std_mm, a_std_mm, alpha_std_deg, beta_std_deg, d_mm, a_mm, alpha_deg, beta_deg}
      marker_std_mm: 0.0          # true marker positions vs the tool's nominal ones
    deflection: {gravity_m_s2, link_masses_kg, tool_mass_kg, tool_com_mm, compliance_rad_per_nm}
    occlusion: {link_radii_mm, obstacles: [{a_mm, b_mm, radius_mm}]}
    cones_deg: {retroreflector: 30, infrared: 60, other: 90}
    sensors: [{name, kind, origin_mm + look_at_mm | frame, noise_mm, noise_mm_per_m,
               field_of_view_deg, markers,
               natnet: {version: "3.0", asset: rigid_body, asset_name: tool, multicast: false},  # mocap
               protocols: [line]}]                  # tracker: line and/or emscon
    allowances: {silence_ms: 300, state_age_ms: 300}   # the commander's timing allowances, wall ms
    controller: {fri_version: "1.15",  # the fake Sunrise's FRI layout: 1.15, 2.5 or 2.7
                 mastering_deg: null}  # the controller's zero corrections (drivers/sim/mastering.py)
    faults:                       # scripted faults (drivers/sim/faults.py), wall s after the cell starts
      - {at_s: 12, fault: beam_break, device: tracker, duration_s: 3}

Lists whose length depends on the robot (n joints) are checked against the model when the
cell is built, with an error naming the field, the length given and the length needed.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from calib.robot.model import Frame
from calib.io.resources import default_sim_config
from calib.io.yamlfile import CrossFieldChecked, load_validated
from drivers.sim.faults import FAULTS, INSTANT

Vec3 = tuple[float, float, float]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class LinkErrors(_Strict):
    """Small errors of the true link parameters relative to the model's nominal ones.

    Each kind is either given explicitly (a list with one value per joint) or drawn from a
    seeded normal with the given standard deviation. ``beta`` errors are only drawn for
    ``mdh`` models (a standard-DH model has no β to fit); explicit β values always apply.
    """

    d_std_mm: float = Field(0.2, ge=0)
    a_std_mm: float = Field(0.2, ge=0)
    alpha_std_deg: float = Field(0.02, ge=0)
    beta_std_deg: float = Field(0.02, ge=0)
    d_mm: list[float] | None = None
    a_mm: list[float] | None = None
    alpha_deg: list[float] | None = None
    beta_deg: list[float] | None = None


class Truth(_Strict):
    """What the real robot is, hidden from everything but tests and the ``--fake`` summary."""

    offsets_deg: list[float] | None = Field(
        None, description="Explicit true zero-offsets (controller convention, deg), one per joint."
    )
    offset_std_deg: float = Field(
        0.3, ge=0, description="Std of drawn zero-offsets; the paper's Table I is 0.1–0.5°, one ≈1°."
    )
    link_errors: LinkErrors = LinkErrors()
    marker_std_mm: float = Field(0.0, ge=0, description="Std per axis of the true marker positions' error.")


class Deflection(_Strict):
    """Joint-compliance model of the arm sagging under gravity.

    Each link's mass sits at the middle of the segment between its joint origins, the tool's at
    ``tool_com_mm`` (flange frame). Joint i's gravity torque is τ_i = z_i · Σ_j (c_j − o_i) ×
    m_j g over the masses beyond it; the joint yields by Δθ_i = compliance_i · τ_i (DH sense).
    """

    gravity_m_s2: Vec3 = Field((0.0, 0.0, -9.81), description="Gravity in the robot base frame.")
    link_masses_kg: list[float] | None = Field(None, description="One per link (joint); None → no deflection.")
    tool_mass_kg: float = Field(0.0, ge=0)
    tool_com_mm: Vec3 = (0.0, 0.0, 0.0)
    compliance_rad_per_nm: list[float] | None = Field(None, description="One per joint, rad/(N·m); None → rigid.")

    @field_validator("link_masses_kg", "compliance_rad_per_nm")
    @classmethod
    def _non_negative(cls, v: list[float] | None) -> list[float] | None:
        if v is not None and any(x < 0 for x in v):
            raise ValueError(f"values must be non-negative, got {v}")
        return v


class Obstacle(_Strict):
    """A fixed capsule in the robot base frame (a column, a fixture, a person)."""

    a_mm: Vec3
    b_mm: Vec3
    radius_mm: float = Field(gt=0)


class Occlusion(_Strict):
    """Bodies that can block a sight line: one capsule per link, plus fixed obstacles.

    Link i's capsule runs between the origins of DH frames i−1 and i; the last link's ends
    flush with the flange face (its axis stops one radius short of the flange) so the plate's
    markers are never inside it.
    """

    link_radii_mm: list[float] | None = Field(None, description="One per link; None → the arm occludes nothing.")
    obstacles: list[Obstacle] = []

    @field_validator("link_radii_mm")
    @classmethod
    def _non_negative(cls, v: list[float] | None) -> list[float] | None:
        if v is not None and any(x < 0 for x in v):
            raise ValueError(f"radii must be non-negative, got {v}")
        return v


class Cones(_Strict):
    """Acceptance half-angles (deg) about the marker normal (the flange's z axis), per kind."""

    retroreflector: float = Field(30.0, gt=0, le=180)
    infrared: float = Field(60.0, gt=0, le=180)
    other: float = Field(90.0, gt=0, le=180)


def _version_text(v):
    """YAML reads ``4.1`` / ``2.5`` as numbers: keep them as the text the user wrote."""
    return str(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else v


class NatNetServe(_Strict):
    """How the cell's fake Motive serves a motion-capture sensor (``drivers.natnet.fake``).

    ``asset``: the tool's markers as a rigid body, a skeleton with one bone ``plate`` (select
    ``sk:<asset_name>:plate``), or a NatNet 4.1 trained markerset (asset) with that bone. The body
    / bone origin is the centroid of the markers the sensor sees; Motive tracks it with ≥ 3 of them.
    """

    version: Literal["3.0", "3.1", "4.0", "4.1"] = Field("3.0", description="NatNet version of the fake Motive.")
    asset: Literal["rigid_body", "skeleton", "trained_markerset"] = "rigid_body"
    asset_name: str = Field("tool", min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")
    multicast: bool = Field(False, description="Stream to 239.255.42.99 (Motive's default) instead of unicast.")
    cluster_radius_mm: float = Field(
        0.0, ge=0, le=200, description="A rigid-body cluster at each marker the sensor measures: three more infrared "
                                       "markers at 120° on a circle of this radius about it, in the plane facing the "
                                       "sensor (the flange's xy plane), so that Motive tracks a rigid body whose origin "
                                       "(the centroid) is that marker; each with the sensor's noise. 0: no cluster.")

    _text = field_validator("version", mode="before")(lambda cls, v: _version_text(v))

    @model_validator(mode="after")
    def _markerset_needs_41(self) -> "NatNetServe":
        if self.asset == "trained_markerset" and self.version != "4.1":
            raise ValueError(f"a trained_markerset needs NatNet version 4.1 (given {self.version})")
        return self


class SensorConfig(_Strict):
    """One reference sensor: where it is, how noisy, which markers it measures.

    The pose is either ``origin_mm`` + ``look_at_mm`` (its +z looks at that point, +x
    horizontal) or ``frame``: the sensor's pose in the robot base frame (xyz mm, ZYX deg),
    i.e. ``sensor2base``. Noise per axis has std ``noise_mm + noise_mm_per_m · range_m``.
    """

    name: str = Field(min_length=1, pattern=r"^[A-Za-z0-9_.-]+$")
    kind: Literal["mocap", "tracker"]
    origin_mm: Vec3 | None = None
    look_at_mm: Vec3 | None = None
    frame: Frame | None = None
    noise_mm: float = Field(ge=0, description="Constant part of the per-axis noise std, mm.")
    noise_mm_per_m: float = Field(0.0, ge=0, description="Range-proportional part, mm per m of range.")
    attitude_noise_deg: float = Field(
        0.005, ge=0, le=10, description="A 6-DoF target's attitude noise, 1σ per axis of the rotation vector, degrees "
                                        "(a T-Mac on a tracker: about 0.005°; Motive derives a rigid body's from its markers).")
    field_of_view_deg: float = Field(180.0, gt=0, le=180, description="Half-angle about +z; 180 = everywhere.")
    markers: list[str] | None = Field(
        None, description="Tool markers this sensor measures; None → infrared/other for mocap, retroreflector for a tracker."
    )
    natnet: NatNetServe | None = Field(None, description="mocap only: how the fake Motive serves it (default NatNet 3.0, rigid body).")
    protocols: list[Literal["line", "emscon"]] | None = Field(
        None, min_length=1, description="tracker only: the fake's protocols, line and/or emscon (default [line]).")
    six_dof: bool = Field(False, description="tracker only: its target is a 6-DoF target (a T-Mac at the marker, "
                                             "its frame the flange's, or the marker's rpy_deg): the line protocol's "
                                             "POSE and emScon's 6D stationary mode measure its orientation too.")

    @model_validator(mode="after")
    def _kind_fields(self) -> "SensorConfig":
        if self.natnet is not None and self.kind != "mocap":
            raise ValueError(f"sensor {self.name!r}: natnet is for a mocap sensor, this one is a {self.kind}")
        if self.six_dof and self.kind != "tracker":
            raise ValueError(f"sensor {self.name!r}: six_dof is for a tracker sensor, this one is a {self.kind}")
        if self.protocols is not None and self.kind != "tracker":
            raise ValueError(f"sensor {self.name!r}: protocols is for a tracker sensor, this one is a {self.kind}")
        return self

    @model_validator(mode="after")
    def _one_pose(self) -> "SensorConfig":
        look = self.origin_mm is not None or self.look_at_mm is not None
        if look and (self.origin_mm is None or self.look_at_mm is None):
            raise ValueError(f"sensor {self.name!r}: give both origin_mm and look_at_mm, or a frame")
        if look == (self.frame is not None):
            raise ValueError(f"sensor {self.name!r}: give exactly one pose: origin_mm + look_at_mm, or frame")
        return self


class SocketTruth(_Strict):
    """Where one socket of one placement really is (robot base frame, mm)."""

    placement: str = Field(pattern=r"^[A-Za-z0-9_-]+$", max_length=32)
    socket: str = Field(pattern=r"^[A-Za-z0-9_-]+$", max_length=32)
    xyz_mm: Vec3


class Sockets(_Strict):
    """A socket tool in the cell and the operator who guides the ball into it
    (``drivers.sim.socket_operator``)."""

    ball_mm: Vec3 = Field(description="True ball centre in the flange frame, mm.")
    play_mm: float = Field(0.02, ge=0, le=1, description="The ball's play in a socket, 1σ per axis, mm.")
    capture_radius_mm: float = Field(30.0, gt=0, le=200, description="The operator guides the ball in from this far.")
    approach_hold_s: float = Field(0.3, gt=0, le=60, description="Robot held still this long before the operator takes it, s.")
    hold_s: float = Field(3.0, gt=0, le=600, description="How long the operator holds the ball in, s (less if the robot moves on).")
    confirm_input: str | None = Field(
        None, min_length=1, max_length=63,
        description="A BOOLEAN input the robot application shares over FRI (e.g. MediaFlange.UserButton) that the "
                    "operator presses once the ball sits in the socket, again while the robot stays; None: he only holds still.")
    points: list[SocketTruth] = Field(min_length=1)


class Allowances(_Strict):
    """What a commander must allow this cell's controller, in wall milliseconds: the cell's
    timing, as an integrator writes it into the commander URL for a slow controller. The fake
    controller is a thread a busy host can stall for longer than a real controller's 100 ms, so
    the default is looser; a simulated run carries these (times its time scale, in simulated
    ms) in the commander URL (``drivers.sim.running``)."""

    silence_ms: float = Field(300.0, gt=0, le=60000, description="Longest silence between controller packets, wall ms.")
    state_age_ms: float = Field(300.0, gt=0, le=60000, description="Oldest measured state a command may be based on, wall ms.")


class ControllerServe(_Strict):
    """How the cell's fake controller speaks (the controller kind comes from the robot model)."""

    fri_version: Literal["1.15", "2.5", "2.7"] = Field("1.15", description="FRI layout of a fake Sunrise.")
    mastering_deg: list[float] | None = Field(
        None, description="The controller's mastering at start: one zero correction per axis, deg, relative to the "
                          "mastering the arm was built with (drivers/sim/mastering.py; KSS: the change of $MAMES[i]). "
                          "Entering a fit's corrections here is entering them on the controller. None: all zero.")

    @field_validator("mastering_deg")
    @classmethod
    def _sane_corrections(cls, v: list[float] | None) -> list[float] | None:
        if v is not None and any(not abs(x) <= 180.0 for x in v):
            raise ValueError(f"corrections must be numbers within ±180°, got {v}")
        return v

    _text = field_validator("fri_version", mode="before")(lambda cls, v: _version_text(v))


class FaultStep(_Strict):
    """One scripted fault (``drivers.sim.faults``): ``fault`` on ``device`` (a sensor's name or
    ``controller``; omitted: every device it applies to) ``at_s`` wall seconds after the cell
    started, for ``duration_s`` (default 3 s; none for controller_restart)."""

    at_s: float = Field(ge=0, le=86400)
    fault: Literal[tuple(FAULTS)]  # type: ignore[valid-type]
    device: str | None = Field(None, min_length=1)
    duration_s: float | None = Field(None, gt=0, le=3600)
    probability: float = Field(0.2, gt=0, le=1, description="packet_loss: chance of losing each datagram.")

    @model_validator(mode="after")
    def _duration_fits(self) -> "FaultStep":
        if self.fault in INSTANT and self.duration_s is not None:
            raise ValueError(f"{self.fault} is an event and takes no duration_s (given {self.duration_s})")
        return self


class SimConfig(_Strict, CrossFieldChecked):
    """The whole simulated cell. Build a cell with ``SimCell(config)``."""

    seed: int = Field(0, ge=0)
    robot: str = Field(description="Robot model YAML; relative paths are taken from the config file's folder.")
    initial_joint_positions_deg: list[float] | None = None
    end_stop_margin_deg: float = Field(
        2.0,
        ge=0,
        le=10,
        description="The mechanical end stops sit this far beyond the model's (software) limits: "
        "a servo may overshoot a limit a little, but the arm cannot pass its stops.",
    )
    truth: Truth = Truth()
    deflection: Deflection = Deflection()
    occlusion: Occlusion = Occlusion()
    cones_deg: Cones = Cones()
    sensors: list[SensorConfig] = Field(default_factory=list)
    sockets: Sockets | None = None
    allowances: Allowances = Field(default_factory=Allowances, description="The commander's timing allowances for this cell.")
    controller: ControllerServe = ControllerServe()
    faults: list[FaultStep] = Field(default_factory=list, description="Scripted faults, fired by SimLaunch.")

    def deferred_errors(self) -> list[tuple[tuple, str]]:
        """A fault's device must be in the cell and of a kind the fault applies to."""
        kinds = {s.name: ({"mocap": ("natnet",)}.get(s.kind) or tuple(
            {"line": "tracker", "emscon": "emscon"}[p] for p in (s.protocols or ["line"]))) for s in self.sensors}
        kinds["controller"] = ("fri", "rsi")
        errors = []
        for i, f in enumerate(self.faults):
            allowed = FAULTS[f.fault]
            if f.device is None:
                continue
            if f.device not in kinds:
                errors.append((("faults", i, "device"), f"no device {f.device!r} in this cell (given {f.device!r}; "
                                                        f"allowed: {', '.join(kinds)})"))
            elif not set(kinds[f.device]) & set(allowed):
                fits = [n for n, k in kinds.items() if set(k) & set(allowed)]
                errors.append((("faults", i, "device"), f"{f.fault} does not apply to {f.device!r} (given {f.device!r}; "
                                                        f"allowed: {', '.join(fits) or 'no device of this cell'})"))
        return errors

    @model_validator(mode="after")
    def _something_measures(self) -> "SimConfig":
        if not self.sensors and self.sockets is None:
            raise ValueError("a cell needs sensors or sockets (given neither)")
        return self

    @field_validator("sensors")
    @classmethod
    def _unique_names(cls, v: list[SensorConfig]) -> list[SensorConfig]:
        names = [s.name for s in v]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"sensor names must be unique; repeated: {dup}")
        return v

    @property
    def sensor_names(self) -> list[str]:
        return [s.name for s in self.sensors]


#: The documented default cell: an iiwa 14, a motion-capture bar and a tracker. Shipped in the
#: package (``calib.io.resources``): it exists in an installed wheel as in a checkout.
DEFAULT_CONFIG_PATH = default_sim_config()


def load_sim_config(path: str | Path) -> SimConfig:
    """Read and validate a cell YAML file; the robot path becomes absolute (from the file's folder).

    Raises ``calib.io.yamlfile.ConfigError`` naming file, line, column and field on any problem.
    """
    path = Path(path)
    config = load_validated(path, SimConfig)
    robot = Path(config.robot)
    if not robot.is_absolute():
        robot = (path.resolve().parent / robot).resolve()
    return config.model_copy(update={"robot": str(robot)})


def save_with_mastering(source: str | Path, target: str | Path, mastering_deg, *, seed: int | None = None) -> Path:
    """Write a copy of the cell file ``source`` to ``target`` with ``controller.mastering_deg`` set
    (n values, deg): the cell the next ``--fake`` run starts with — a controller keeps its mastering
    through a restart. A relative robot path is made absolute when the folder changes. The copy is
    checked by loading it (ConfigError naming the line otherwise); ``target`` is written only then.
    ``seed``: the seed the cell runs with, when it was overridden."""
    import yaml

    from calib.io.yamlfile import load_yaml_with_marks

    source, target = Path(source), Path(target)
    data, _ = load_yaml_with_marks(source)
    controller = dict(data.get("controller") or {})
    controller["mastering_deg"] = [round(float(v), 9) for v in mastering_deg]
    data["controller"] = controller
    if seed is not None:
        data["seed"] = int(seed)
    robot = Path(str(data.get("robot", "")))
    if not robot.is_absolute() and source.resolve().parent != target.resolve().parent:
        data["robot"] = str((source.resolve().parent / robot).resolve())
    text = ("# " + f"{source.name} with the controller's mastering entered (acquire sim 'save')\n"
            + yaml.safe_dump(data, sort_keys=False))
    tmp = target.with_name(f".{target.name}.tmp")
    tmp.write_text(text, encoding="utf-8")
    try:
        load_sim_config(tmp)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    tmp.replace(target)
    return target
