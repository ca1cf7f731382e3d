"""The commissioning report: one self-contained HTML file (figures inline as SVG)."""

from __future__ import annotations

import html
import io
from pathlib import Path
from typing import Any

import numpy as np

from rt_ident.config import RunConfig
from rt_ident.outputs.html import page, table, write_page
from rt_ident.outputs.html import value_text as fmt


def _model_frf(p: dict[str, float], w: np.ndarray) -> np.ndarray:
    """theta1 / torque of the two-inertia model (Eq. 1-2 of the paper in the Laplace domain)."""
    s = 1j * w
    i1, i2, b, k = (p[n] for n in ("I1", "I2", "B", "K"))
    return (i2 * s**2 + b * s + k) / (s**2 * (i1 * i2 * s**2 + (i1 + i2) * (b * s + k)))


def _measured_frf(path: str, period: int, band: tuple[int, int]) -> tuple[np.ndarray, np.ndarray] | None:
    """theta1 / torque at the multisine's harmonics, averaged over the recording's whole periods."""
    from rt_ident.outputs.recording_reader import read_recording

    rec = read_recording(path)
    n = (len(rec.theta1) // period - 2) * period
    if n < period:
        return None
    th = rec.theta1[-n:].reshape(-1, period)
    tq = rec.torque[-n:].reshape(-1, period)
    th = th - th.mean(axis=1, keepdims=True)
    k = np.arange(band[0], band[1] + 1)
    g = np.fft.rfft(th, axis=1)[:, k].mean(axis=0) / np.fft.rfft(tq, axis=1)[:, k].mean(axis=0)
    dt = float(np.median(np.diff(rec.t)))
    return 2 * np.pi * k / (period * dt), g


def _phase(g: np.ndarray) -> np.ndarray:
    """Phase in degrees, in [-360, 0) (a double integrator's -180 is drawn once, not at +-180)."""
    return (np.degrees(np.angle(g)) + 360.0) % 360.0 - 360.0


def _frf_svg(result: dict[str, Any], cfg: RunConfig) -> str:
    try:
        from matplotlib.figure import Figure
    except ImportError:
        return "<p>Figures need the plots extra: <code>pip install 'rt-ident[plots]'</code>.</p>"
    ident = result.get("identification") or {}
    prm, ci = ident.get("parameters"), ident.get("ci95") or {}
    rec = Path(result["out"]) / "identify.parquet"
    meas = _measured_frf(str(rec), cfg.excitation.period_samples, cfg.excitation.band) if rec.is_file() else None
    if prm is None or meas is None:
        return "<p>No FRF: the identification stage did not run.</p>"
    w, g = meas
    wf = np.geomspace(w[0], w[-1], 400)
    fig = Figure(figsize=(9, 6))
    ax = fig.subplots(2, 1, sharex=True)
    ax[0].loglog(w / 2 / np.pi, np.abs(g), "o", ms=3, label="measured (multisine harmonics)")
    ax[0].loglog(wf / 2 / np.pi, np.abs(_model_frf(prm, wf)), "-", label="identified model")
    keys = [k for k in ("I1", "I2", "B", "K") if ci.get(k)]
    if keys:
        corners = []
        for bits in range(1 << len(keys)):
            q = dict(prm) | {k: ci[k][(bits >> i) & 1] for i, k in enumerate(keys)}
            corners.append(np.abs(_model_frf(q, wf)))
        c = np.array(corners)
        ax[0].fill_between(wf / 2 / np.pi, c.min(axis=0), c.max(axis=0), alpha=0.3, label="95 % band")
    ax[1].semilogx(w / 2 / np.pi, _phase(g), "o", ms=3)
    ax[1].semilogx(wf / 2 / np.pi, _phase(_model_frf(prm, wf)), "-")
    ax[0].set_ylabel("|theta1 / torque| [rad/N m]")
    ax[1].set_ylabel("phase [deg]")
    ax[1].set_xlabel("frequency [Hz]")
    ax[0].legend()
    for a in ax:
        a.grid(True, which="both", alpha=0.3)
    buf = io.StringIO()
    fig.savefig(buf, format="svg", bbox_inches="tight")
    svg = buf.getvalue()
    return svg[svg.index("<svg"):]


def write(result: dict[str, Any], cfg: RunConfig, path: Path) -> None:
    verdict = result.get("verdict", "fail")
    parts = [f"<h1>Commissioning <span class='{'pass' if verdict == 'pass' else 'fail'}'>{verdict.upper()}</span></h1>",
             f"<p>Config <code>{html.escape(str(result.get('config')))}</code>; stage reached: "
             f"{html.escape(str(result.get('stage_reached')))}; table moved at most "
             f"{fmt((result.get('max_travel_m') or 0) * 1e3)} mm at {fmt((result.get('max_speed_m_s') or 0) * 1e3)}"
             " mm/s while probing.</p>"]
    if result.get("failed"):
        f = result["failed"]
        parts.append(f"<p class='fail'>{html.escape(f['check'])} failed. Fix: {html.escape(str(f['fix']))}</p>")
    parts.append("<h2>Checks</h2>")
    parts.append(table(["check", "result", "measured", "expected", "fix, or what a pass leaves to look at"], [
        [html.escape(c["name"]), "<span class='pass'>pass</span>" if c["ok"] else "<span class='fail'>FAIL</span>",
         html.escape(fmt(c["measured"])), html.escape(fmt(c["expected"])),
         html.escape(fmt(c.get("fix") or c.get("note")))]
        for c in result.get("checks", [])]))
    if result.get("identity"):
        parts.append("<h2>Device</h2>" + table(["object", "value"], [
            [html.escape(k), html.escape(fmt(v))] for k, v in result["identity"].items()]))
    if result.get("pulses"):
        parts.append("<h2>Torque pulses (controller off)</h2>" + table(
            ["direction", "breakaway [N m]", "push [N m]", "theta1 [rad]", "x [mm]", "x/theta1 [m/rad]",
             "acceleration per N m"],
            [[q["direction"], fmt(q["breakaway_nm"]), fmt(q["push_nm"]), fmt(q["theta1_rad"]),
              fmt(q["x_m"] * 1e3), fmt(q["ratio_m_per_rad"]), fmt(q["accel_per_nm"])] for q in result["pulses"]]))
    ident = result.get("identification") or {}
    if ident.get("parameters"):
        ci = ident.get("ci95") or {}
        parts.append("<h2>Identified parameters</h2>" + table(
            ["parameter", "value", "95 % interval"],
            [[k, fmt(v), f"{fmt(ci[k][0])} .. {fmt(ci[k][1])}" if ci.get(k) else "-"]
             for k, v in ident["parameters"].items()]))
        tries = ident.get("attempts") or []
        if len(tries) > 1:
            first = tries[0]
            parts.append(f"<p>Identified in a second run of {tries[-1]['duration_s']:g} s: the first, of "
                         f"{first['duration_s']:g} s, was not trusted ({html.escape('; '.join(first['reasons']))}; "
                         f"{first['lost_samples']} samples lost).</p>")
        parts.append("<h2>Frequency response</h2>" + _frf_svg(result, cfg))
    if result.get("design"):
        parts.append("<h2>Controller design</h2>" + table(["", "value"], [
            [html.escape(k), html.escape(fmt(v))] for k, v in result["design"].items()]))
    if result.get("verification"):
        v = result["verification"]
        keys = ("max_error_m", "rms_error_m", "overshoot_m", "settling_s")
        parts.append(f"<h2>Verification move ({v['move_m'] * 1e3:g} mm and back)</h2>" + table(
            ["", *keys], [["measured", *(fmt(v["measured"].get(k)) for k in keys)],
                          ["identified model", *(fmt(v["model"].get(k)) for k in keys)]]))
    if result.get("axis_toml"):
        parts.append("<h2>[axis] for run</h2><pre>" + html.escape(Path(result["axis_toml"]).read_text()) + "</pre>")
    if cfg.source and Path(cfg.source).is_file():
        parts.append("<h2>Config used</h2><pre>" + html.escape(Path(cfg.source).read_text()) + "</pre>")
    write_page(path, page(f"rt-ident commission: {verdict}", parts))
