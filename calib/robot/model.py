"""Robot models: the YAML file format, its validation, and the numbers kinematics needs.

A model file (mm and degrees) describes a serial arm as a chain of joints in one of two
conventions:

``dh``   standard Denavit–Hartenberg, link transform ``Rz(θ) Tz(d) Tx(a) Rx(α)``;
``mdh``  the same with Hayati's torsion β appended, ``Rz(θ) Tz(d) Tx(a) Rx(α) Ry(β)`` — the
         "modified DH" of the pose-selection seed (eq. 1), which stays well conditioned for
         near-parallel axes (β is then the free parameter instead of d).

The controller's axis convention is part of the model: for joint i the DH angle is
``θ_i = theta_i + sign_i · q_i`` where ``q_i`` is the angle the controller shows for that axis.
Joint limits and speeds are in the controller's convention too, so everything a user types or
reads is in the pendant's numbers. A fitted zero-offset ``δ_i`` adds to ``q_i``.

Inside the package everything is mm and radians (see ``calib/__init__``).
"""

from __future__ import annotations

import math
from functools import cached_property
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

from calib.robot.transforms import pose_to_matrix
from calib.io.yamlfile import CrossFieldChecked, load_validated

Convention = Literal["dh", "mdh"]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Frame(_Strict):
    """A fixed transform: translation (mm) then ZYX Euler rotation (deg, yaw-pitch-roll)."""

    xyz: tuple[float, float, float] = (0.0, 0.0, 0.0)
    zyx: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def matrix(self) -> np.ndarray:
        """(4, 4) homogeneous, mm."""
        return pose_to_matrix(np.array(self.xyz), np.radians(self.zyx))


class Joint(_Strict):
    """One revolute joint: its link's nominal parameters and the controller's view of the axis."""

    axis: str = Field(description="Controller's name for the axis, e.g. A1 or J1.")
    theta: float = Field(0.0, description="DH joint-angle offset, deg: θ = theta + sign·q.")
    d: float = Field(0.0, description="Link offset along the previous z, mm.")
    a: float = Field(0.0, description="Link length along the new x, mm.")
    alpha: float = Field(0.0, description="Link twist about the new x, deg.")
    beta: float = Field(0.0, description="Hayati torsion about the new y, deg (mdh only).")
    sign: Literal[1, -1] = Field(1, description="+1 if the controller's positive sense is the DH one.")
    limits: tuple[float, float] = Field(description="[lower, upper] in controller degrees.")
    max_speed: float = Field(gt=0, description="deg/s at 100 % override.")
    max_accel: float = Field(gt=0, description="deg/s² used for planning.")
    mass_kg: float | None = Field(None, ge=0, le=1000, description="Mass of the link this joint moves, kg (gravity model).")
    com_mm: tuple[float, float, float] | None = Field(
        None, description="That link's centre of mass in this joint's DH frame (after its link transform), mm.")

    @field_validator("limits")
    @classmethod
    def _ordered(cls, v: tuple[float, float]) -> tuple[float, float]:
        lo, hi = v
        if not lo < hi:
            raise ValueError(f"lower limit {lo} must be below upper limit {hi}")
        if lo < -720 or hi > 720:
            raise ValueError("limits are in degrees and must lie within ±720")
        return v


class Marker(_Strict):
    """A target on the tool, position in the flange frame (mm)."""

    name: str = Field(min_length=1)
    xyz: tuple[float, float, float]
    kind: Literal["retroreflector", "infrared", "other"] = "other"
    rpy_deg: tuple[float, float, float] | None = Field(
        None, description="A 6-DoF target's frame (T-Mac, rigid body) at this marker: its orientation in the flange "
                          "frame as roll, pitch, yaw, degrees (R = Rz(yaw)·Ry(pitch)·Rx(roll)); omitted: unknown, "
                          "fitted from the measured orientations.")


class Tool(_Strict):
    name: str = "tool"
    markers: list[Marker] = Field(min_length=1)
    mass_kg: float = Field(0.0, ge=0, le=100, description="Tool mass, kg (gravity model).")
    com_mm: tuple[float, float, float] = Field((0.0, 0.0, 0.0), description="Tool centre of mass, flange frame, mm.")

    @field_validator("markers")
    @classmethod
    def _unique(cls, v: list[Marker]) -> list[Marker]:
        names = [m.name for m in v]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"marker names must be unique; repeated: {sorted(dup)}")
        return v


class RobotModel(_Strict, CrossFieldChecked):
    """A validated robot model. Load with ``load_robot_model(path)``."""

    name: str
    manufacturer: str = ""
    controller: Literal["kss", "sunrise", "cs8", "generic"] = "generic"
    convention: Convention
    base: Frame = Frame()
    flange: Frame = Frame()
    joints: list[Joint] = Field(min_length=1, max_length=12)
    tool: Tool
    gravity_m_s2: tuple[float, float, float] = Field((0.0, 0.0, -9.81), description="Gravity in the base frame, m/s².")
    source: str = Field("", description="Where the nominal numbers come from.")

    def deferred_errors(self) -> list[tuple[tuple, str]]:
        """Checks across fields, as (field path, message), so a file loader can point at the
        line of the offending field rather than at the top of the document."""
        errors: list[tuple[tuple, str]] = []
        if self.convention == "dh":
            for i, j in enumerate(self.joints):
                if j.beta != 0.0:
                    errors.append(
                        (("joints", i, "beta"), f"beta is only allowed with convention 'mdh' (axis {j.axis}, given {j.beta})")
                    )
        with_mass = [j.mass_kg is not None for j in self.joints]
        if any(with_mass) and not all(with_mass):
            i = with_mass.index(False)
            errors.append((("joints", i, "mass_kg"), "give mass_kg (and com_mm) for every joint or for none"))
        for i, j in enumerate(self.joints):
            if (j.mass_kg is None) != (j.com_mm is None):
                errors.append((("joints", i, "com_mm" if j.com_mm is None else "mass_kg"),
                               f"mass_kg and com_mm go together (axis {j.axis})"))
            elif j.com_mm is not None and max(abs(c) for c in j.com_mm) > 3000:
                errors.append((("joints", i, "com_mm"), f"com_mm is in mm and must lie within ±3000 (axis {j.axis}, given {j.com_mm})"))
        axes = [j.axis for j in self.joints]
        for i, ax in enumerate(axes):
            if axes.index(ax) != i:
                errors.append((("joints", i, "axis"), f"axis names must be unique; {ax!r} repeats"))
        return errors


    # --- numbers for kinematics (mm, rad, controller convention) -------------------------
    @property
    def n_joints(self) -> int:
        return len(self.joints)

    @property
    def axis_names(self) -> list[str]:
        return [j.axis for j in self.joints]

    @property
    def marker_names(self) -> list[str]:
        return [m.name for m in self.tool.markers]

    @cached_property
    def lower_limits_rad(self) -> np.ndarray:
        return np.radians([j.limits[0] for j in self.joints])

    @cached_property
    def upper_limits_rad(self) -> np.ndarray:
        return np.radians([j.limits[1] for j in self.joints])

    @cached_property
    def max_velocity_rad_s(self) -> np.ndarray:
        return np.radians([j.max_speed for j in self.joints])

    @cached_property
    def max_acceleration_rad_s2(self) -> np.ndarray:
        return np.radians([j.max_accel for j in self.joints])

    def within_limits(self, q_rad: np.ndarray, margin_rad: float = 0.0) -> np.ndarray:
        """Boolean mask over leading dims: every axis of ``q_rad`` (..., n) inside limits − margin."""
        q = np.asarray(q_rad)
        return np.all((q >= self.lower_limits_rad + margin_rad) & (q <= self.upper_limits_rad - margin_rad), axis=-1)

    @property
    def has_dynamics(self) -> bool:
        """True when every joint carries a mass and a centre of mass (the gravity model)."""
        return all(j.mass_kg is not None for j in self.joints)

    def marker_index(self, name: str) -> int:
        try:
            return self.marker_names.index(name)
        except ValueError:
            raise ValueError(f"unknown marker {name!r}; the tool has {self.marker_names}") from None


def load_robot_model(path: str | Path) -> RobotModel:
    """Read and validate a robot model YAML file (mm, degrees), or a model shipped in the package
    by name (``kuka_iiwa14_r820``; ``acquire examples`` lists them) when no such file exists.

    Raises ``calib.io.yamlfile.ConfigError`` naming file, line, column and field on any problem.
    """
    p = Path(path)
    if not p.exists():
        from calib.io.resources import find, packaged
        from calib.io.yamlfile import ConfigError

        found = find("robots", p.name) if p.parent == Path(".") else None
        if found is None:
            names = ", ".join(m.stem for m in packaged("robots"))
            raise ConfigError(f"{path}: cannot read: no such robot model file (allowed: a robot model YAML file, or the name of a "
                              f"packaged model: {names})")
        p = found
    return load_validated(p, RobotModel)


def robot_model_from_dict(data: dict) -> RobotModel:
    """Validate an in-memory model (same layout as the YAML file)."""
    return RobotModel.model_validate(data)


def wrap_to_pi(a: np.ndarray) -> np.ndarray:
    """Angles wrapped to (−π, π]."""
    return np.pi - np.mod(np.pi - np.asarray(a), 2 * math.pi)


def model_yaml(model: RobotModel, comment: str = "") -> str:
    """The model as YAML text in the layout of ``fixtures/robots`` (one flow-style line per joint
    and marker), ``comment`` as leading ``#`` lines; ``load_robot_model`` reads it back."""
    import yaml  # noqa: PLC0415

    def num(v) -> str:
        if isinstance(v, float):
            r = round(v, 12) + 0.0
            if r == int(r) and abs(r) < 1e15:
                return str(int(r))
            text = repr(r)
            mantissa, e, exp = text.partition("e")
            if e and "." not in mantissa:  # PyYAML reads 1e-05 as a string, 1.0e-05 as a number
                text = f"{mantissa}.0e{exp}"
            return text
        return str(v)

    def flow(d: dict) -> str:
        parts = []
        for k, v in d.items():
            if isinstance(v, (list, tuple)):
                v = "[" + ", ".join(str(num(x)) for x in v) + "]"
            elif isinstance(v, str):
                v = yaml.safe_dump(v, default_style=None).strip().removesuffix("...").strip()
            else:
                v = num(v)
            parts.append(f"{k}: {v}")
        return "{" + ", ".join(parts) + "}"

    d = model.model_dump(mode="json", exclude_none=True)
    lines = [f"# {line}".rstrip() for line in comment.strip().splitlines()] if comment.strip() else []
    for key in ("name", "manufacturer", "controller", "convention", "source"):
        if d.get(key) != "" or key == "name":
            lines.append(yaml.safe_dump({key: d[key]}, allow_unicode=True, width=1000).strip())
    for key in ("base", "flange"):
        lines.append(f"{key}: {flow(d[key])}")
    lines.append("joints:")
    lines += [f"  - {flow(j)}" for j in d["joints"]]
    tool = {k: v for k, v in d["tool"].items() if k != "markers"}
    lines.append("tool:")
    lines += [f"  {k}: {flow({k: v})[1:-1].split(': ', 1)[1]}" for k, v in tool.items()]
    lines.append("  markers:")
    lines += [f"    - {flow(m)}" for m in d["tool"]["markers"]]
    lines.append(f"gravity_m_s2: {flow({'g': d['gravity_m_s2']})[1:-1].split(': ', 1)[1]}")
    return "\n".join(lines) + "\n"
