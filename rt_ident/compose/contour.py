"""The XY circular test's trace: the table's path on X and Y, one point per tick, when both axes follow a
:class:`~rt_ident.control.reference.Circle` reference, and afterwards the test's figures (ISO 230-4 G, F,
H: :mod:`rt_ident.control.contour`), its polar plot and its dashboard."""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING, Any

import numpy as np

from rt_ident.errors import MissingExtra, require
from rt_ident.loop.loop import IdentificationLoop

if TYPE_CHECKING:
    from rt_ident.control.adaptation import Supervisor
    from rt_ident.control.reference import Circle

log = logging.getLogger(__name__)


#: the longest trace kept (40 bytes a tick): two hours at 1 kHz
MAX_ROWS = 7_200_000


def trace_rows(ref: Circle, tick_s: float, n_ticks: int) -> int:
    """The rows a trace keeps: the ticks up to the circle's end (not the run's: a long run would preallocate
    for nothing), 8 to spare, at most :data:`MAX_ROWS` (then the circle's first part; a warning)."""
    end = max(t1 for _, t1 in ref.windows().values())
    n = min(n_ticks, math.ceil(end / tick_s)) + 8
    if n > MAX_ROWS:
        log.warning("circular test: the trace keeps the first %.0f s of the circle (%d ticks), not all %d",
                    MAX_ROWS * tick_s, MAX_ROWS, n)
    return min(n, MAX_ROWS)


class ContourTrace:
    """The table's path on X and Y, one point per tick, when both axes follow a :class:`Circle` reference
    (``kind = "circle"``, ``axis = "x"`` / ``"y"``): afterwards, the circular test's figures (ISO 230-4 G,
    F, H: :mod:`rt_ident.control.contour`) and its polar plot. Preallocated for the ticks up to the circle's
    end (at most :data:`MAX_ROWS`), whatever the run's duration; a tick stores five floats."""

    def __init__(self, loops: dict[str, IdentificationLoop], n_ticks: int) -> None:
        from rt_ident.control.reference import Circle

        self.ctl: dict[str, Supervisor] = {}
        refs: dict[str, Circle] = {}
        for name in ("x", "y"):
            lp = loops.get(name)
            ctl = lp.control if lp is not None else None
            ref = ctl.reference if ctl is not None else None
            if ctl is not None and isinstance(ref, Circle) and ref.axis == name:
                self.ctl[name], refs[name] = ctl, ref
        self.active = len(self.ctl) == 2 and refs["x"].radius == refs["y"].radius and \
            refs["x"].windows() == refs["y"].windows()
        self.ref = refs.get("x")
        self.tick_s = 1.0 / loops["x"].tick_hz if self.active else 0.0
        n = trace_rows(self.ref, self.tick_s, n_ticks) if self.active and self.ref is not None else 0
        self.buf = np.full((n, 5), np.nan)        # t, x, y of the table, x, y of the reference
        self.n = 0

    def __call__(self) -> None:
        if not self.active or self.n >= self.buf.shape[0]:
            return
        cx, cy = self.ctl["x"], self.ctl["y"]           # relative to each axis's origin: the circle's frame
        ox, oy = cx.anchor.origin, cy.anchor.origin
        self.buf[self.n] = (cx.t, cx.x_ref + cx.error - ox, cy.x_ref + cy.error - oy, cx.x_ref - ox, cy.x_ref - oy)
        self.n += 1

    def result(self, png: str | None, rrd: str | None = None, live_url: str | None = None) -> dict[str, Any] | None:
        ref = self.ref
        if not self.active or ref is None or self.n < 16:     # (active: there is a reference)
            return None
        from rt_ident.control.contour import circle_figures, polar_plot

        t, x, y, xr, yr = self.buf[:self.n].T
        R = ref.radius
        paths, missed = {}, {}
        for d, (t0, t1) in ref.measured().items():               # constant feed: overshoot arcs excluded
            sel = (t >= t0) & (t <= t1) & np.isfinite(x) & np.isfinite(y)
            if sel.sum() >= 16:
                paths[d] = (x[sel], y[sel])
                # ticks the loop did not run (it fell behind and skipped periods): no point for them
                missed[d] = int(np.sum(np.maximum(np.rint(np.diff(t[sel]) / self.tick_s) - 1.0, 0.0)))
        if not paths:
            return {"note": "the run ended before the circle began"}
        fig = circle_figures(paths, R, (0.0, -R))
        for d, n in missed.items():
            fig[d]["ticks_missed"] = n
        fig["feed_mm_min"] = 60e3 * 2 * math.pi * R * ref.frequency_hz
        stalls = [t for c in self.ctl.values() for t, kind, _ in c.stats.events if kind == "stall"]
        for d, (t0, t1) in ref.measured().items():
            hit = [t for t in stalls if t0 - 0.5 <= t <= t1]     # the rejoin after a stall lasts up to ~0.5 s
            if d in fig and hit:                                 # the host, not the axis, made that turn
                fig[d]["disturbed_by_stall_at_s"] = round(hit[0], 3)
        fig["complete"] = {d: d in paths and float(t[-1]) >= ref.measured()[d][1] for d in ("ccw", "cw")}
        fig["overshoot_deg"] = ref.overshoot_deg
        if png:
            try:
                require("matplotlib", "plots", "the circular test's polar plot")
                fig["polar_png"] = polar_plot(paths, R, (0.0, -R), fig, png, title="XY circular test (table scale)")
            except MissingExtra as exc:                          # the figures stand without the picture
                fig["polar_png_error"] = str(exc)
        if rrd or live_url:
            from rt_ident.outputs.dashboard import write_contour_rrd

            try:
                fig["rrd"] = write_contour_rrd(rrd, (xr, yr), paths, R, (0.0, -R), fig, connect_url=live_url)
            except Exception as exc:  # noqa: BLE001 - the figures are in hand; the dashboard is extra
                log.warning("contour dashboard %s not written: %s", rrd or live_url, exc)
                fig["rrd_error"] = f"{type(exc).__name__}: {exc}"
        return fig
