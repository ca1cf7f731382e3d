"""Self-contained HTML reports (the commissioning report, the fleet report): one file, no external
resources - the style inline, figures as inline SVG (:mod:`rt_ident.outputs.svg_plot`)."""

from __future__ import annotations

import html
import math
from pathlib import Path
from typing import Any

CSS = """body{font-family:system-ui,sans-serif;margin:2em;max-width:1100px;color:#222}
table{border-collapse:collapse;margin:.5em 0 1.5em}td,th{border:1px solid #ccc;padding:.3em .6em;text-align:left;
vertical-align:top}th{background:#f3f3f3}.pass{color:#0a7d2c;font-weight:bold}.fail{color:#b00020;font-weight:bold}
pre{background:#f6f6f6;padding:1em;overflow-x:auto}h1 span{font-size:.7em}"""


def esc(v: Any) -> str:
    """Text for HTML (names and values come from files a user wrote: never markup)."""
    return html.escape(str(v), quote=True)


def value_text(v: Any) -> str:
    """A value as a short text: 4 significant digits, "-" for None, dicts as ``key value, ...``."""
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}" if math.isfinite(v) else str(v)
    if isinstance(v, dict):
        return ", ".join(f"{k} {value_text(x)}" for k, x in v.items())
    return str(v)


def table(head: list[str], rows: list[list[Any]], row_classes: list[str] | None = None) -> str:
    """An HTML table; the head is escaped here, the cells are taken as HTML (escape them first)."""
    h = "".join(f"<th>{esc(c)}</th>" for c in head)
    body = "".join(_row(r, k) for r, k in zip(rows, row_classes or [""] * len(rows)))
    return f"<table><tr>{h}</tr>{body}</table>"


def _row(cells: list[Any], cls: str) -> str:
    attr = f' class="{esc(cls)}"' if cls else ""
    return f"<tr{attr}>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>"


def page(title: str, body: list[str], css: str = "") -> str:
    """A whole HTML document: ``title`` (escaped here) and ``body`` parts (HTML)."""
    return "\n".join([f"<!doctype html><html><head><meta charset='utf-8'><title>{esc(title)}</title>"
                      f"<style>{CSS}{css}</style></head><body>", *body, "</body></html>"])


def write_page(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary name: a reader never sees half a page."""
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(path)


__all__ = ["CSS", "esc", "value_text", "table", "page", "write_page"]
