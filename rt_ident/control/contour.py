"""The circular test's figures (ISO 230-4) from the table's path on both axes, and its polar plot.

Definitions as in ISO 230-4 (circular tests for numerically controlled machine tools):

* **circular deviation G** - per direction, the minimum radial separation of two concentric circles
  enclosing the actual path; their centre is the least-squares circle's (here the algebraic fit of
  Kasa 1976: linear in the centre and ``r^2 - |c|^2``);
* **radial deviation F** - per direction, the largest and smallest deviation of the path from the
  nominal circle about its nominal centre (F max >= 0 outside, F min <= 0 inside);
* **circular hysteresis H** - the largest radial difference between the two directions' paths, at
  equal angles about the least-squares centre of both.

Positions are the table's (linear scale, ``x = lead * theta2``), one per loop tick.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np


def fit_circle(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float]:
    """Least-squares circle (algebraic, Kasa): centre (cx, cy) and radius."""
    A = np.column_stack((2 * x, 2 * y, np.ones_like(x)))
    b = x * x + y * y
    (cx, cy, c), *_ = np.linalg.lstsq(A, b, rcond=None)
    return float(cx), float(cy), float(math.sqrt(max(c + cx * cx + cy * cy, 0.0)))


def _radius_at(x: np.ndarray, y: np.ndarray, cx: float, cy: float, grid: np.ndarray) -> np.ndarray:
    """The path's radius about (cx, cy) at the angles ``grid`` (interpolated, angle-sorted)."""
    ang = np.mod(np.arctan2(y - cy, x - cx), 2 * math.pi)
    r = np.hypot(x - cx, y - cy)
    order = np.argsort(ang)
    return np.interp(grid, ang[order], r[order], period=2 * math.pi)


def circle_figures(paths: dict[str, tuple[np.ndarray, np.ndarray]], radius: float,
                   centre: tuple[float, float]) -> dict[str, Any]:
    """G, F (per direction) and H from ``{"ccw": (x, y), "cw": (x, y)}`` [m]; the result in um."""
    out: dict[str, Any] = {"radius_mm": 1e3 * radius}
    fits = {}
    for d, (x, y) in paths.items():
        if x.size < 16:
            continue
        cx, cy, r = fit_circle(x, y)
        dev = np.hypot(x - cx, y - cy) - r
        nominal = np.hypot(x - centre[0], y - centre[1]) - radius
        fits[d] = (cx, cy)
        out[d] = {"G_um": 1e6 * float(dev.max() - dev.min()), "F_max_um": 1e6 * float(nominal.max()),
                  "F_min_um": 1e6 * float(nominal.min()),
                  "centre_offset_um": [1e6 * (cx - centre[0]), 1e6 * (cy - centre[1])],
                  "radius_error_um": 1e6 * (r - radius), "points": int(x.size)}
    if {"ccw", "cw"} <= set(fits):
        allx = np.concatenate([paths["ccw"][0], paths["cw"][0]])
        ally = np.concatenate([paths["ccw"][1], paths["cw"][1]])
        cx, cy, _ = fit_circle(allx, ally)
        grid = np.linspace(0, 2 * math.pi, 720, endpoint=False)
        r1 = _radius_at(*paths["ccw"], cx, cy, grid)
        r2 = _radius_at(*paths["cw"], cx, cy, grid)
        out["H_um"] = 1e6 * float(np.max(np.abs(r1 - r2)))
    # the three headline figures, over both directions
    dirs = [out[d] for d in ("ccw", "cw") if d in out]
    if dirs:
        out["circular_deviation_um"] = max(f["G_um"] for f in dirs)
        out["radius_deviation_um"] = max(max(f["F_max_um"], -f["F_min_um"]) for f in dirs)
    out["circular_hysteresis_um"] = out.get("H_um")
    return out


def polar_plot(paths: dict[str, tuple[np.ndarray, np.ndarray]], radius: float, centre: tuple[float, float],
               figures: dict[str, Any], path: str, title: str = "") -> str:
    """The ballbar-style polar plot: each direction's radial deviation from the nominal circle,
    magnified, around a reference circle; the scale and G, H in the title. Writes ``path`` (PNG)."""
    from matplotlib.figure import Figure

    devs = {d: np.hypot(x - centre[0], y - centre[1]) - radius for d, (x, y) in paths.items()}
    span = max((float(np.max(np.abs(v))) for v in devs.values() if v.size), default=1e-6) or 1e-6
    scale = 10 ** math.ceil(math.log10(span * 1e6))            # um per ring (1, 10, 100 ...)
    fig = Figure(figsize=(5.2, 5.6))
    ax = fig.add_subplot(projection="polar")
    for d, color in (("ccw", "C0"), ("cw", "C3")):
        if d not in paths:
            continue
        x, y = paths[d]
        ang = np.arctan2(y - centre[1], x - centre[0])
        ax.plot(ang, 1.0 + devs[d] * 1e6 / scale, color=color, lw=0.9, label=d.upper())
    th = np.linspace(0, 2 * math.pi, 361)
    ax.plot(th, np.ones_like(th), color="0.5", lw=0.6)
    ax.set_ylim(0, 2)
    ax.set_yticks([0.5, 1.0, 1.5])
    ax.set_yticklabels([f"-{scale / 2:g}", "0", f"+{scale / 2:g} um"], fontsize=7)
    g = " ".join(f"G {d.upper()} {figures[d]['G_um']:.2f} um" for d in ("ccw", "cw") if d in figures)
    h = f", H {figures['H_um']:.2f} um" if "H_um" in figures else ""
    ax.set_title(f"{title}\ncircle R {1e3 * radius:g} mm: {g}{h}", fontsize=8)
    ax.legend(loc="lower right", fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    return path


__all__ = ["fit_circle", "circle_figures", "polar_plot"]
