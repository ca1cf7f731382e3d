"""How the command line prints numbers and JSON (shared by every command)."""

from __future__ import annotations

import math
from typing import Any


def fmt(x: float | None) -> str:
    """Four significant digits; "-" for a missing or NaN value."""
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.4g}"


def um(v: float | None) -> float | None:
    """Metres to micrometres (None stays None)."""
    return None if v is None else 1e6 * v


def json_default(o: Any) -> Any:
    """numpy scalars and arrays as JSON values; anything else as its text."""
    import numpy as np

    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)
