"""A small trend plot drawn as SVG text (no plotting library): estimates with their intervals, bands,
reference lines and event markers, with a legend below the axes.

The y-range always holds every interval, band and in-range line given, so nothing drawn leaves the
axes. Elements carry classes (``frame``, ``point``, ``interval``, ``legend``) that tests and style sheets
can find.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from rt_ident.outputs.html import esc

BLUE, GREY, RED, GREEN, ORANGE = "#1f77b4", "#7f7f7f", "#d62728", "#2ca02c", "#ff7f0e"


def nice_ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    """About ``n`` round tick values (1, 2, 2.5 or 5 times a power of ten apart) within [lo, hi]."""
    if not (math.isfinite(lo) and math.isfinite(hi)) or hi <= lo:
        return [lo] if math.isfinite(lo) else []
    mag = 10.0 ** math.floor(math.log10((hi - lo) / max(1, n)))

    def ticks(step: float) -> list[float]:
        return [k * step for k in range(math.ceil(lo / step - 1e-9), math.floor(hi / step + 1e-9) + 1)]

    # the finest round step that gives at most n + 1 ticks
    return next(t for t in (ticks(m * mag) for m in (1.0, 2.0, 2.5, 5.0, 10.0, 20.0)) if len(t) <= n + 1)


def tick_text(v: float, step: float) -> str:
    """A tick label with as many decimals as the tick step needs (no "-0")."""
    dec = 0
    while dec < 12 and abs(round(step * 10**dec) - step * 10**dec) > 1e-6 * step * 10**dec:
        dec += 1
    return f"{0.0 if abs(v) < 1e-9 * step else v:.{dec}f}"


@dataclass
class TrendPlot:
    title: str
    ylabel: str
    width: int = 540
    height: int = 200                  # the axes' frame and its tick labels; the legend adds below
    x_ticks: Callable[[float, float], list[tuple[float, str]]] | None = None
    items: list[dict[str, Any]] = field(default_factory=list)

    def points(self, x: Iterable[float], y: Iterable[float], lo: Iterable[float], hi: Iterable[float], label: str,
               color: str = BLUE, tips: Sequence[str] | None = None) -> None:
        """Estimates with their intervals (lo, hi; NaN: none drawn)."""
        self.items.append({"kind": "points", "x": list(x), "y": list(y), "lo": list(lo), "hi": list(hi),
                           "label": label, "color": color, "tips": list(tips) if tips else None})

    def band(self, y0: float, y1: float, label: str, color: str = GREY) -> None:
        self.items.append({"kind": "band", "y0": y0, "y1": y1, "label": label, "color": color})

    def hline(self, y: float, label: str, color: str = GREY, dash: bool = False, in_range: bool = True) -> None:
        """A level; ``in_range=False``: drawn only if the data's range holds it (it does not widen it)."""
        self.items.append({"kind": "hline", "y": y, "label": label, "color": color, "dash": dash,
                           "in_range": in_range})

    def vspan(self, x0: float, x1: float, label: str, color: str = GREEN) -> None:
        self.items.append({"kind": "vspan", "x0": x0, "x1": x1, "label": label, "color": color})

    def vline(self, x: float, label: str, color: str = RED) -> None:
        self.items.append({"kind": "vline", "x": x, "label": label, "color": color})

    def marks(self, x: Iterable[float], label: str, color: str = GREY) -> None:
        """Ticks along the bottom of the axes (events with no value to plot)."""
        self.items.append({"kind": "marks", "x": list(x), "label": label, "color": color})

    # ------------------------------------------------------------------ drawing
    def _ranges(self) -> tuple[float, float, float, float]:
        xs: list[float] = []
        ys: list[float] = []
        for it in self.items:
            k = it["kind"]
            if k == "points":
                xs += it["x"]
                for y, lo, hi in zip(it["y"], it["lo"], it["hi"]):
                    ys += [v for v in (y, lo, hi) if math.isfinite(v)]
            elif k == "band":
                ys += [it["y0"], it["y1"]]
            elif k == "hline" and it["in_range"]:
                ys.append(it["y"])
            elif k == "vspan":
                xs += [it["x0"], it["x1"]]
            elif k in ("vline",):
                xs.append(it["x"])
            elif k == "marks":
                xs += it["x"]
        xs = [v for v in xs if math.isfinite(v)]
        ys = [v for v in ys if math.isfinite(v)]
        x0, x1 = (min(xs), max(xs)) if xs else (0.0, 1.0)
        y0, y1 = (min(ys), max(ys)) if ys else (0.0, 1.0)
        xpad = (x1 - x0) * 0.03 or 0.5
        ypad = (y1 - y0) * 0.08 or max(abs(y0) * 1e-3, 1e-12)
        return x0 - xpad, x1 + xpad, y0 - ypad, y1 + ypad

    def svg(self) -> str:
        left, right, top, bottom = 62, 12, 22, 30
        w, h = self.width, self.height
        pw, ph = w - left - right, h - top - bottom
        x0, x1, y0, y1 = self._ranges()

        def px(x: float) -> float:
            return left + (x - x0) / (x1 - x0) * pw

        def py(y: float) -> float:
            return top + (y1 - y) / (y1 - y0) * ph

        out: list[str] = []
        legend: list[tuple[str, str, str]] = []
        for it in self.items:
            k, c = it["kind"], it["color"]
            if k == "vspan":
                a, b = px(max(it["x0"], x0)), px(min(it["x1"], x1))
                out.append(f'<rect x="{a:.1f}" y="{top}" width="{max(b - a, 1):.1f}" height="{ph}" fill="{c}" '
                           f'fill-opacity="0.10"/>')
                legend.append(("span", c, it["label"]))
            elif k == "band":
                a, b = py(max(it["y0"], it["y1"])), py(min(it["y0"], it["y1"]))
                out.append(f'<rect x="{left}" y="{a:.1f}" width="{pw}" height="{max(b - a, 0.5):.1f}" fill="{c}" '
                           f'fill-opacity="0.18"/>')
                legend.append(("span", c, it["label"]))
        for it in self.items:
            k, c = it["kind"], it["color"]
            if k == "hline":
                if not y0 <= it["y"] <= y1:
                    continue
                dash = ' stroke-dasharray="5 3"' if it["dash"] else ""
                out.append(f'<line x1="{left}" x2="{left + pw}" y1="{py(it["y"]):.1f}" y2="{py(it["y"]):.1f}" '
                           f'stroke="{c}" stroke-width="1"{dash}/>')
                legend.append(("dash" if it["dash"] else "line", c, it["label"]))
            elif k == "vline":
                out.append(f'<line class="event" x1="{px(it["x"]):.1f}" x2="{px(it["x"]):.1f}" y1="{top}" '
                           f'y2="{top + ph}" stroke="{c}" stroke-width="1.5"/>')
                legend.append(("vline", c, it["label"]))
            elif k == "marks":
                for x in it["x"]:
                    out.append(f'<line class="mark" x1="{px(x):.1f}" x2="{px(x):.1f}" y1="{top + ph - 7}" '
                               f'y2="{top + ph}" stroke="{c}" stroke-width="2"/>')
                legend.append(("vline", c, it["label"]))
            elif k == "points":
                tips = it["tips"] or [""] * len(it["x"])
                for x, y, lo, hi, tip in zip(it["x"], it["y"], it["lo"], it["hi"], tips):
                    if not math.isfinite(y):
                        continue
                    if math.isfinite(lo) and math.isfinite(hi):
                        out.append(f'<line class="interval" x1="{px(x):.1f}" x2="{px(x):.1f}" y1="{py(hi):.1f}" '
                                   f'y2="{py(lo):.1f}" stroke="{c}" stroke-width="1"/>')
                    title = f"<title>{esc(tip)}</title>" if tip else ""
                    out.append(f'<circle class="point" cx="{px(x):.1f}" cy="{py(y):.1f}" r="2.6" fill="{c}">{title}'
                               "</circle>")
                legend.append(("point", c, it["label"]))
        axes = [f'<rect class="frame" x="{left}" y="{top}" width="{pw}" height="{ph}" fill="none" stroke="#444"/>']
        yt = nice_ticks(y0, y1, 4)
        step = yt[1] - yt[0] if len(yt) > 1 else abs(y1 - y0) or 1.0
        for v in yt:
            label = esc(tick_text(v, step))
            axes.append(f'<line x1="{left - 4}" x2="{left}" y1="{py(v):.1f}" y2="{py(v):.1f}" stroke="#444"/>'
                        f'<text x="{left - 6}" y="{py(v) + 3.5:.1f}" text-anchor="end">{label}</text>')
        xt = self.x_ticks(x0, x1) if self.x_ticks else [(v, f"{v:g}") for v in nice_ticks(x0, x1, 5)]
        for v, text in xt:
            axes.append(f'<line x1="{px(v):.1f}" x2="{px(v):.1f}" y1="{top + ph}" y2="{top + ph + 4}" stroke="#444"/>'
                        f'<text x="{px(v):.1f}" y="{top + ph + 16}" text-anchor="middle">{esc(text)}</text>')
        axes.append(f'<text x="{left}" y="14" font-weight="bold">{esc(self.title)}</text>')
        axes.append(f'<text transform="translate(12 {top + ph / 2:.0f}) rotate(-90)" text-anchor="middle">'
                    f"{esc(self.ylabel)}</text>")
        leg, height = self._legend(legend, left, h + 4, w - left - right)
        return (f'<svg xmlns="http://www.w3.org/2000/svg" class="trend" width="{w}" height="{height}" '
                f'viewBox="0 0 {w} {height}" font-family="system-ui,sans-serif" font-size="10">'
                + "".join(out) + "".join(axes) + leg + "</svg>")

    @staticmethod
    def _legend(entries: list[tuple[str, str, str]], x: float, y: float, width: float) -> tuple[str, int]:
        """Entries flowed left to right below the axes; returns the SVG and the plot's total height."""
        seen: list[tuple[str, str, str]] = []
        for e in entries:
            if e not in seen and e[2]:
                seen.append(e)
        parts = ['<g class="legend">']
        cx, cy = x, y + 8
        for kind, c, label in seen:
            size = 26 + 5.6 * len(label)
            if cx + size > x + width and cx > x:
                cx, cy = x, cy + 14
            sy = cy - 3
            if kind == "point":
                parts.append(f'<line x1="{cx + 7}" x2="{cx + 7}" y1="{sy - 5}" y2="{sy + 5}" stroke="{c}"/>'
                             f'<circle cx="{cx + 7}" cy="{sy}" r="2.6" fill="{c}"/>')
            elif kind == "span":
                parts.append(f'<rect x="{cx}" y="{sy - 5}" width="14" height="10" fill="{c}" fill-opacity="0.25"/>')
            elif kind == "vline":
                parts.append(f'<line x1="{cx + 7}" x2="{cx + 7}" y1="{sy - 6}" y2="{sy + 6}" stroke="{c}" '
                             'stroke-width="1.5"/>')
            else:
                dash = ' stroke-dasharray="5 3"' if kind == "dash" else ""
                parts.append(f'<line x1="{cx}" x2="{cx + 14}" y1="{sy}" y2="{sy}" stroke="{c}"{dash}/>')
            parts.append(f'<text x="{cx + 18}" y="{cy}">{esc(label)}</text>')
            cx += size
        parts.append("</g>")
        return "".join(parts), int(cy + 8)


__all__ = ["TrendPlot", "nice_ticks", "tick_text", "BLUE", "GREY", "RED", "GREEN", "ORANGE"]
