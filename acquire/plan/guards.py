"""Plan-time guards: inputs that would move the robot wrongly, refused before anything connects.

``acquire.plan.schema.load_plan`` calls these after the schema and the relations are checked. Each
returns problems as ``(field path, message)`` pairs located in the plan file (or, for the robot
model, ready-made ``file:line:col: field: message`` lines), worded ``… (given …; allowed …)``.

**Units.** A plan is in millimetres and degrees. Values in metres or radians pass a schema (they
are numbers in range) but make a run that moves the robot and measures nothing. What is
physically implausible, and therefore refused:

- a position in mm whose every coordinate is within a few millimetres of the origin where a
  real one cannot be: ``sensor_origin_mm`` (the aim point cannot be inside the robot's base:
  |x|, |y|, |z| ≤ 10 mm), a Cartesian flange pose (|x|, |y|, |z| ≤ 5 mm), the ``radius_mm``
  / ``height_mm`` ranges of generated poses (every bound within ±5 mm, not all zero), a tool
  marker within 5 mm of the flange centre (a marker sphere sits on the tool, its centre
  at least its radius off the flange face);
- ``noise_mm`` below 0.001 mm (1 µm: no motion-capture system or laser tracker is that good;
  3e-05 is 0.03 mm written in metres);
- joint targets that all lie within ±π "degrees" (±3.15°, and not all zero) although the
  model's axes move through tens or hundreds of degrees, and that read as radians fall
  within the limits: a calibration plan that never moves any axis more than 3° is useless,
  and this is exactly what a list of radians looks like (``calib.measure.units.radians_problem``, the
  same check measurement CSVs get);
- an angle range or angle whose bounds are ±π/4 multiples in radians (0.785, 1.571, 3.142,
  6.283 within 0.002), e.g. ``angle_deg: [0, 6.283]`` or ``zyx_deg: [0, 1.571, 0]``.

**The commander's limit margin.** Every commander refuses targets within its margin of the
model's joint limits (``drivers.base.CommanderBase.check_target``, 0.5° for FRI and RSI unless
the plan's ``commander.options`` set ``limit_margin_rad``). ``commander_margin_rad`` asks the
plan's driver class for it (``limit_margin_for``), so explicit joint targets inside the margin
are refused here, not mid-run, and generated / Cartesian poses keep at least that far inside.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from calib.robot.model import RobotModel
from calib.measure.units import radians_problem  # noqa: F401  (re-exported: plan.py uses it from here)
from calib.io.yamlfile import Marks, error_line

#: |x|, |y|, |z| all at most this (mm): ``sensor_origin_mm`` looks like metres.
SENSOR_ORIGIN_METRES_MM = 10.0
#: |x|, |y|, |z| all at most this (mm): a Cartesian flange position looks like metres.
FLANGE_METRES_MM = 5.0
#: A tool marker closer than this to the flange centre (mm) looks like metres.
MARKER_METRES_MM = 5.0
#: Every bound of radius_mm / height_mm within this (mm): the range looks like metres.
RANGE_METRES_MM = 5.0
#: A sensor noise below this (mm) looks like metres.
NOISE_METRES_MM = 1e-3
#: An angle within this of a nonzero multiple of π/4 (and within ±2π) looks like radians.
RADIANS_PI_TOLERANCE = 0.002

Problem = tuple[tuple, str]


def _fmt(values: Iterable[float]) -> str:
    return "[" + ", ".join(f"{float(v):g}" for v in values) + "]"


def _looks_like_radian_angle(v: float) -> bool:
    """A nonzero multiple of π/4 within ±2π, to ``RADIANS_PI_TOLERANCE``."""
    if abs(v) > 2 * math.pi + RADIANS_PI_TOLERANCE or abs(v) < math.pi / 4 - RADIANS_PI_TOLERANCE:
        return False
    k = round(v / (math.pi / 4))
    return k != 0 and abs(v - k * math.pi / 4) <= RADIANS_PI_TOLERANCE


def _radian_angles(values: Sequence[float]) -> bool:
    """Angles in degrees that read as radians: all within ±2π and one a multiple of π/4."""
    vals = [float(v) for v in values]
    return (all(abs(v) <= 2 * math.pi + RADIANS_PI_TOLERANCE for v in vals)
            and any(_looks_like_radian_angle(v) for v in vals))


def _metres(values: Sequence[float], limit_mm: float) -> bool:
    """Every coordinate within ±limit_mm and not all zero."""
    a = np.abs(np.asarray(values, dtype=float))
    return bool(np.all(a <= limit_mm) and np.any(a > 0))


# --- the commander's margin ------------------------------------------------------------------
def commander_margin_rad(plan) -> tuple[float, str]:
    """(margin in rad, the driver's name) the plan's commander keeps clear of every joint limit.

    Asks the driver class (``limit_margin_for(options)``); a driver without it keeps none that we
    know of (0). Raises ValueError for a bad ``limit_margin_rad`` option.
    """
    from drivers.registry import load_driver

    spec = plan.commander
    try:
        cls = load_driver(spec.driver)
    except (ValueError, ImportError):  # reported by the driver check
        return 0.0, spec.driver
    ask = getattr(cls, "limit_margin_for", None)
    if not callable(ask):
        return 0.0, spec.driver
    return float(ask(spec.options)), spec.driver


def confirm_input_errors(plan) -> list[Problem]:
    """A joint sensor confirmed by a controller input (``input=`` in its URL, ``drivers.socket``)
    needs a commander whose driver reads the controller's inputs (``digital_input``)."""
    from urllib.parse import parse_qsl, urlsplit

    from drivers.registry import load_driver

    errors: list[Problem] = []
    for i, s in enumerate(plan.sensors):
        name = dict(parse_qsl(urlsplit(s.url).query)).get("input")
        if name is None:
            continue
        try:
            cls = load_driver(plan.commander.driver)
        except (ValueError, ImportError):  # reported by the driver check
            continue
        if not callable(getattr(cls, "digital_input", None)):
            errors.append((("sensors", i, "url"),
                           f"input={name} confirms with a controller input, which the {plan.commander.driver!r} "
                           "commander does not read (given that commander; allowed: a commander that reads inputs, "
                           "e.g. fri — or leave input= out and confirm with Enter or `acquire confirm`)"))
    return errors


def margin_problem(q_deg: Sequence[float], model: RobotModel, margin_rad: float, driver: str) -> list[tuple[int, str]]:
    """Axes of one target (degrees, controller convention) the commander would refuse, as
    (axis index, message). Outside the model's limits and inside the margin are told apart."""
    from drivers.base import target_window
    from drivers.protocols import JointLimits

    q = np.radians(np.asarray(q_deg, dtype=float))
    limits = JointLimits.from_model(model)
    lo, hi = target_window(limits, margin_rad)
    out: list[tuple[int, str]] = []
    m = math.degrees(margin_rad)
    for j in np.flatnonzero((q < lo) | (q > hi)):
        joint = model.joints[j]
        a, b = joint.limits
        v = float(q_deg[j])
        if not a <= v <= b:
            out.append((int(j), f"{joint.axis} outside its limits (given {v:g}°; allowed [{a:g}, {b:g}]°)"))
        else:
            out.append((int(j), f"{joint.axis} within the {driver} commander's {m:g}° margin of its limit, which it "
                                f"would refuse mid-run (given {v:g}°; allowed [{a + m:g}, {b - m:g}]°: the model's "
                                f"limits [{a:g}, {b:g}]° less {m:g}°)"))
    return out


# --- units ---------------------------------------------------------------------------------------
def plan_units_errors(plan, model: RobotModel) -> list[Problem]:
    """Plan fields that look like metres or radians (see the module docstring)."""
    errors: list[Problem] = []
    for i, s in enumerate(plan.sensors):
        if s.noise_mm < NOISE_METRES_MM:
            errors.append((("sensors", i, "noise_mm"),
                           f"{s.noise_mm:g} mm is below what any sensor measures: this looks like metres "
                           f"(given {s.noise_mm:g}; allowed mm ≥ {NOISE_METRES_MM:g}, e.g. 0.03 for 30 µm)"))
    p = plan.poses
    if p is None:  # a socket plan
        return errors
    g = p.generated
    if g is not None:
        loc = ("poses", "generated")
        if _metres(g.sensor_origin_mm, SENSOR_ORIGIN_METRES_MM):
            errors.append((loc + ("sensor_origin_mm",),
                           f"the sensor cannot sit within {SENSOR_ORIGIN_METRES_MM:g} mm of the robot's base origin: "
                           f"this looks like metres (given {_fmt(g.sensor_origin_mm)}; allowed mm in the robot base "
                           f"frame, e.g. {_fmt(np.asarray(g.sensor_origin_mm) * 1000.0)})"))
        for key in ("radius_mm", "height_mm"):
            rng = getattr(g, key)
            if _metres(rng, RANGE_METRES_MM):
                errors.append((loc + (key,), f"a workspace within ±{RANGE_METRES_MM:g} mm of the base looks like metres "
                                             f"(given {_fmt(rng)}; allowed mm, e.g. {_fmt(np.asarray(rng) * 1000.0)})"))
        for key in ("angle_deg", "roll_deg"):
            rng = getattr(g, key)
            if _radian_angles(rng):
                errors.append((loc + (key,), f"this looks like radians (given {_fmt(rng)}; allowed degrees, "
                                             f"e.g. {_fmt(np.round(np.degrees(rng), 1))})"))
        for k, a in enumerate(g.arm_angles_deg or []):
            if _radian_angles([a]):
                errors.append((loc + ("arm_angles_deg", k), f"this looks like radians (given {a:g}; allowed degrees, "
                                                            f"e.g. {math.degrees(a):.1f})"))
    for i, cp in enumerate(p.cartesian or []):
        loc = ("poses", "cartesian", i)
        if _metres(cp.xyz_mm, FLANGE_METRES_MM):
            errors.append((loc + ("xyz_mm",), f"the flange cannot be within {FLANGE_METRES_MM:g} mm of the base "
                                              f"origin: this looks like metres (given {_fmt(cp.xyz_mm)}; allowed mm, "
                                              f"e.g. {_fmt(np.asarray(cp.xyz_mm) * 1000.0)})"))
        if _radian_angles(cp.zyx_deg):
            errors.append((loc + ("zyx_deg",), f"this looks like radians (given {_fmt(cp.zyx_deg)}; allowed degrees, "
                                               f"e.g. {_fmt(np.round(np.degrees(cp.zyx_deg), 1))})"))
        if cp.arm_angle_deg is not None and _radian_angles([cp.arm_angle_deg]):
            errors.append((loc + ("arm_angle_deg",), f"this looks like radians (given {cp.arm_angle_deg:g}; allowed "
                                                     f"degrees, e.g. {math.degrees(cp.arm_angle_deg):.1f})"))
    if isinstance(p.joints, list) and p.joints and all(len(r) == model.n_joints for r in p.joints):
        why = radians_problem(p.joints, model)
        if why:
            errors.append((("poses", "joints"), why))
    return errors


def model_units_errors(model: RobotModel, model_path: Path, marks: Marks) -> list[str]:
    """Tool markers of the robot model that look like metres, as ``file:line:col: field: …`` lines
    of the model file (``marks`` from ``load_yaml_with_marks``)."""
    out = []
    for i, m in enumerate(model.tool.markers):
        r = float(np.linalg.norm(m.xyz))
        if r < MARKER_METRES_MM:
            out.append(error_line(model_path, marks, ("tool", "markers", i, "xyz"),
                                  f"marker {m.name!r} lies {r:.3g} mm from the flange centre, where no marker fits: "
                                  f"the tool offsets look like metres (given {_fmt(m.xyz)}; allowed mm in the flange "
                                  f"frame, e.g. {_fmt(np.asarray(m.xyz) * 1000.0)})"))
    return out


def joints_margin_errors(rows_deg: Sequence[Sequence[float]], model: RobotModel, margin_rad: float,
                         driver: str) -> list[Problem]:
    """Explicit joint targets (rows of degrees) the commander would refuse, at ``poses.joints.<row>.<axis>``."""
    errors: list[Problem] = []
    for i, row in enumerate(rows_deg):
        if len(row) != model.n_joints:
            continue
        for j, msg in margin_problem(row, model, margin_rad, driver):
            errors.append((("poses", "joints", i, j), msg))
    return errors


def describe_config_rows(rows: Sequence[tuple[Any, Sequence[float]]], model: RobotModel, margin_rad: float,
                         driver: str, limit: int = 5) -> list[str]:
    """For a configurations file: ``config <id>: <problem>`` for up to ``limit`` refused rows
    (rows as (config id, degrees))."""
    out = []
    for cid, q in rows:
        for _, msg in margin_problem(q, model, margin_rad, driver):
            out.append(f"config {cid}: {msg}")
            if len(out) >= limit:
                return out
    return out
