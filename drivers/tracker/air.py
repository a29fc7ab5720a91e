"""Air for a laser tracker's refraction correction, and the reflectors a tracker knows.

A tracker measures an optical path and divides it by the refractive index of the air it was
told (or that its weather station read). Telling it the wrong air scales every distance by
n_true / n_told: 1 °C is about 1 ppm (1 µm per metre), 1 hPa about 0.27 ppm, 10 % humidity
about 0.1 ppm. Both tracker drivers take the air in the same form (``Air``) and fakes of both
apply the same model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from drivers.tracker.codec import HUMIDITY_RANGE_PCT, PRESSURE_RANGE_HPA, TEMPERATURE_RANGE_C


@dataclass(frozen=True)
class Air:
    """Temperature (°C), pressure (hPa) and relative humidity (%) along the beam."""

    temperature_c: float = 20.0
    pressure_hpa: float = 1013.25
    humidity_pct: float = 50.0

    def __post_init__(self) -> None:
        for name, v, (lo, hi) in (("temperature_c", self.temperature_c, TEMPERATURE_RANGE_C),
                                  ("pressure_hpa", self.pressure_hpa, PRESSURE_RANGE_HPA),
                                  ("humidity_pct", self.humidity_pct, HUMIDITY_RANGE_PCT)):
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and lo <= v <= hi):
                raise ValueError(f"{name} must be a number in [{lo:g}, {hi:g}], got {v!r}")


def refractive_index(air: Air) -> float:
    """Group index of air for a tracker's red laser by the NIST shop-floor form of the
    Edlén equation: n = 1 + 7.86e-4·p/(273 + t) − 1.5e-11·RH·(t² + 160), p in kPa, t in °C,
    RH in % (good to about 1e-7 over ordinary workshop air)."""
    t, p_kpa, rh = air.temperature_c, air.pressure_hpa / 10.0, air.humidity_pct
    return 1.0 + 7.86e-4 * p_kpa / (273.0 + t) - 1.5e-11 * rh * (t * t + 160.0)


def range_scale(true_air: Air, assumed_air: Air) -> float:
    """Factor a distance measured through ``true_air`` but corrected for ``assumed_air`` is
    multiplied by (1 + a few ppm for a few degrees of error)."""
    return refractive_index(true_air) / refractive_index(assumed_air)


@dataclass(frozen=True)
class Reflector:
    """A reflector a tracker knows: type name (the line protocol's ``type=``), emScon
    ``ES_TargetType`` number, surface offset (mm: centre to the surface it touches)."""

    name: str
    target_type: int
    surface_offset_mm: float


#: The reflectors the fakes know (Leica's names; offsets are the balls' radii).
REFLECTORS: tuple[Reflector, ...] = (
    Reflector("RRR15", 5, 19.05),   # red-ring reflector, 1.5 in ball
    Reflector("RRR05", 6, 6.35),    # 0.5 in
    Reflector("BRR15", 7, 19.05),   # break-resistant 1.5 in
    Reflector("BRR05", 8, 6.35),
    Reflector("TBR05", 9, 6.35),    # tooling ball reflector 0.5 in
    Reflector("CATSEYE", 2, 0.0),
)


STATION = "station"


def parse_environment(value) -> "Air | str | None":
    """The air a tracker driver is given: None (leave the tracker's setting), ``"station"``
    (use the tracker's weather station), an ``Air``, or a mapping as a plan writes it:
    ``{temperature_c, pressure_hpa, humidity_pct}`` or ``{source: station}``."""
    if value is None or isinstance(value, Air):
        return value
    if isinstance(value, str):
        if value.lower() == STATION:
            return STATION
        raise ValueError(f"environment must be 'station' or temperature_c/pressure_hpa/humidity_pct, got {value!r}")
    if isinstance(value, dict):
        v = dict(value)
        source = v.pop("source", None)
        if source is not None and str(source).lower() == STATION and not v:
            return STATION
        if source not in (None, "host", "HOST"):
            raise ValueError(f"environment source must be 'station' or 'host', got {source!r}")
        keys = {"temperature_c", "pressure_hpa", "humidity_pct"}
        if set(v) != keys:
            raise ValueError(f"environment needs exactly {sorted(keys)} (°C, hPa, %), got {sorted(v)}")
        return Air(**v)
    raise ValueError(f"environment must be an Air, 'station' or a mapping, got {value!r}")


def parse_reflector(value) -> "tuple[str, float | None] | None":
    """The reflector a tracker driver is given: None, a type name (``"RRR15"``), or a mapping
    ``{type, offset_mm}`` (offset optional, mm) → ``(type, offset_mm or None)``."""
    if value is None:
        return None
    if isinstance(value, str):
        value = {"type": value}
    if not isinstance(value, dict) or "type" not in value or not set(value) <= {"type", "offset_mm"}:
        raise ValueError(f"reflector must be a type name or {{type, offset_mm}}, got {value!r}")
    name, offset = value["type"], value.get("offset_mm")
    if not isinstance(name, str) or not name:
        raise ValueError(f"reflector type must be a non-empty name such as RRR15, got {name!r}")
    if offset is not None and (isinstance(offset, bool) or not isinstance(offset, (int, float))
                               or not (math.isfinite(offset) and 0 <= offset <= 1000)):
        raise ValueError(f"reflector offset_mm must be a number in [0, 1000] mm, got {offset!r}")
    return name, None if offset is None else float(offset)
