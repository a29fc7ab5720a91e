"""The JSON encoding shared by the Zenoh bus and the MCAP run log.

Payloads are UTF-8 JSON objects, compact (no spaces), keys in insertion order. numpy arrays and
scalars are written as lists and numbers. Non-finite floats (NaN, ±inf) are not JSON: they are
written as ``null``, which every reader of our streams takes to mean "missing" (a lost marker, a
standard deviation of a single sample). Units follow the field names (``_mm``, ``_deg``, ``_s``).
"""

from __future__ import annotations

import json
import math
from typing import Any

# numpy is recognised by its ``tolist`` method, not imported: the thin clients (``acquire status``)
# start without it.


class PayloadError(ValueError):
    """A payload that is not a JSON object we can encode or decode."""


def _is_numpy(obj: Any) -> bool:
    """A numpy array or scalar (``ndarray`` / ``generic``), without importing numpy."""
    return type(obj).__module__.partition(".")[0] == "numpy" and hasattr(obj, "tolist")


def _numpy_default(obj: Any) -> Any:
    if _is_numpy(obj):
        return obj.tolist()  # an array → nested lists; a scalar → the Python number
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def _finite(obj: Any) -> Any:
    """``obj`` with non-finite floats replaced by None (recursively)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if _is_numpy(obj):
        return _finite(obj.tolist())
    return obj


def encode_json(obj: dict) -> bytes:
    """Encode a dict as compact UTF-8 JSON bytes; non-finite floats become null.

    Raises PayloadError for non-dicts and for values JSON cannot hold (sets, objects, bytes).
    """
    if not isinstance(obj, dict):
        raise PayloadError(f"payload must be a dict (a JSON object), given {type(obj).__name__}")
    try:
        return json.dumps(obj, separators=(",", ":"), allow_nan=False, default=_numpy_default).encode("utf-8")
    except ValueError:
        pass  # non-finite floats: take the slow path below
    except TypeError as exc:
        raise PayloadError(f"payload is not JSON serialisable: {exc}; allowed: dict/list/str/int/float/bool/None and numpy arrays") from exc
    try:
        return json.dumps(_finite(obj), separators=(",", ":"), allow_nan=False, default=_numpy_default).encode("utf-8")
    except (TypeError, ValueError) as exc:
        raise PayloadError(f"payload is not JSON serialisable: {exc}") from exc


def decode_json(data: bytes | bytearray | memoryview) -> dict:
    """Decode UTF-8 JSON bytes that must hold an object; PayloadError otherwise."""
    try:
        obj = json.loads(bytes(data).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise PayloadError(f"not UTF-8 JSON ({len(data)} bytes): {exc}") from exc
    if not isinstance(obj, dict):
        raise PayloadError(f"JSON payload must be an object, got {type(obj).__name__}")
    return obj
