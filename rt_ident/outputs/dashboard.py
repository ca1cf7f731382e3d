"""The rerun dashboard: entity paths (all in one place), how the FRF views are drawn, the blueprint.

Time series (``time`` timeline, duration in seconds). An entity with several series holds one
row per time with one scalar per series: signals sampled together share their row id and time
column, which is most of a small row's bytes (sharing them makes a 10-s run's .rrd 1.9 MB, not 2.9).

==========================================  ===============================================  ============
entity                                      block keys (see :mod:`rt_ident.processes.telemetry`)  unit
==========================================  ===============================================  ============
``angles``                                  ``theta1``, ``theta2``                           rad
``torque/drive``                            ``torque_meas``, ``torque_cmd``                  N m
                                            (measured, commanded)
``torque/estimate``                         ``torque_filt``, ``torque_hat``                  N m
                                            (measured through the SVF, its Eq. 18 reconstruction)
``torque/nrmse_percent``                    (the telemetry process: the two above, 1 s)      %
``torque/control``                          ``u_control`` (the host's control torque)        N m
``params/{I1,I2,B,K}/estimate``             ``I1`` ... ``K``                                 SI
``params/{I1,I2,B,K}/ci95``                 ``lo_I1``, ``hi_I1`` ... (95 % interval)         SI
``params/{I1,I2,B,K}/true``                 ``set_truth({...})``                             SI
``params/{I1,I2,B,K}/per_sample``           ``svf_I1`` ... (the per-sample estimate)         SI
``modal/{wn,wd,zeta}/estimate|ci95|true``   ``wn``, ``wd``, ``zeta``, ``lo_wn`` ...          rad/s, -
``loop/lateness_us``                        ``lateness_us``                                  us
``loop/events/{overruns,stalls}``           ``overruns``, ``stalls`` (past max_stall_s)      count
``control/position``                        ``x_ref``, ``x_table``                           m
``control/error``                           ``error_m`` (table minus reference)              m
``control/gains/{theta2,omega1}``           ``gain_theta2``, ``gain_omega1``                 N m/rad, N m s/rad
``control/margins/{pm_deg,gm_db}``          ``pm_deg``, ``gm_db`` (nominal loop)             deg, dB
``control/redesigns``                       ``n_accepted``, ``n_rejected``, ``fallbacks``    count
==========================================  ===============================================  ============

Frequency responses (logged at each fit / redesign on the ``time`` timeline, so scrubbing the
time shows the FRF as it was then), under ``frf/``:

* ``frf/theta1/{magnitude,phase}``, ``frf/theta2/{magnitude,phase}``: the measured FRF
  (``Points2D`` at the excited lines) with the identified model's (``LineStrips2D``) and its 95 %
  band; the resonance and the anti-resonance marked;
* ``frf/loop/{magnitude,phase}``: the active controller's loop gain on the identified model,
  with the crossover and the margins.

Why ``LineStrips2D`` in a 2-D view and not time series over a frequency timeline: a time series
holds every value ever logged at an index, so the FRFs of successive fits would pile up; a strip
logged at time t is *replaced* by the next fit, and the view shows the one valid at the selected
time. The 2-D view has no log axis, so the drawing space is ``x = 100 log10(f / Hz)`` (one decade
= 100 units) and ``y = -2 dB`` (or ``-phase / 2``: the y axis of a 2-D view points down), with
its own labelled grid lines.

``rerun`` is imported only inside the functions that draw, so the real-time process can import
the path constants without loading rerun.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

import numpy as np

PARAM_NAMES: tuple[str, ...] = ("I1", "I2", "B", "K")
MODAL_NAMES: tuple[str, ...] = ("wn", "wd", "zeta")
ESTIMATE_KEYS: tuple[str, ...] = PARAM_NAMES + MODAL_NAMES

ANGLES = "angles"
TORQUE_DRIVE = "torque/drive"
TORQUE_ESTIMATE = "torque/estimate"
TORQUE_NRMSE = "torque/nrmse_percent"
TORQUE_CONTROL = "torque/control"
LATENESS = "loop/lateness_us"
LOOP_EVENTS = "loop/events"
OVERRUNS = f"{LOOP_EVENTS}/overruns"
STALLS = f"{LOOP_EVENTS}/stalls"
FRF = "frf"


def _group(key: str) -> str:
    return "params" if key in PARAM_NAMES else "modal"


def estimate_path(key: str) -> str:
    """Entity of the running estimate of ``key`` (one of :data:`ESTIMATE_KEYS`)."""
    return f"{_group(key)}/{key}/estimate"


def truth_path(key: str) -> str:
    """Entity of the true value of ``key``, drawn next to its estimate."""
    return f"{_group(key)}/{key}/true"


def interval_path(key: str) -> str:
    """Entity of the 95 % interval of ``key`` (two series: lower, upper)."""
    return f"{_group(key)}/{key}/ci95"


#: Per-tick control signals -> entity paths (sent on the tick timeline like the estimates).
CONTROL_ENTITIES: Mapping[str, str] = MappingProxyType(
    {
        "x_ref": "control/position",
        "x_table": "control/position",
        "error_m": "control/error",
        "u_control": TORQUE_CONTROL,
        "gain_theta2": "control/gains/theta2",
        "gain_omega1": "control/gains/omega1",
        "pm_deg": "control/margins/pm_deg",
        "gm_db": "control/margins/gm_db",
        "n_accepted": "control/redesigns",
        "n_rejected": "control/redesigns",
        "fallbacks": "control/redesigns",
        **{f"svf_{k}": f"params/{k}/per_sample" for k in PARAM_NAMES},
    }
)

#: Entity path -> the block keys it holds, one series each, in this order.
ENTITY_SERIES: Mapping[str, tuple[str, ...]] = MappingProxyType(
    {
        ANGLES: ("theta1", "theta2"),
        TORQUE_DRIVE: ("torque_meas", "torque_cmd"),
        TORQUE_ESTIMATE: ("torque_filt", "torque_hat"),
        **{estimate_path(k): (k,) for k in ESTIMATE_KEYS},
        **{interval_path(k): (f"lo_{k}", f"hi_{k}") for k in ESTIMATE_KEYS},
        LATENESS: ("lateness_us",),
        OVERRUNS: ("overruns",),
        STALLS: ("stalls",),
        "control/position": ("x_ref", "x_table"),
        "control/error": ("error_m",),
        TORQUE_CONTROL: ("u_control",),
        "control/gains/theta2": ("gain_theta2",),
        "control/gains/omega1": ("gain_omega1",),
        "control/margins/pm_deg": ("pm_deg",),
        "control/margins/gm_db": ("gm_db",),
        "control/redesigns": ("n_accepted", "n_rejected", "fallbacks"),
        **{f"params/{k}/per_sample": (f"svf_{k}",) for k in PARAM_NAMES},
    }
)

#: Block key -> entity path of every signal the loop publishes.
BLOCK_ENTITIES: Mapping[str, str] = MappingProxyType({k: path for path, keys in ENTITY_SERIES.items() for k in keys})

_UNITS = MappingProxyType({"I1": "kg m²", "I2": "kg m²", "B": "N m s/rad", "K": "N m/rad",
                           "wn": "rad/s", "wd": "rad/s", "zeta": "-"})
_EST_COLOR = (31, 119, 180)
_CI_COLOR = (158, 202, 225)
_TRUE_COLOR = (150, 150, 150)
_RED, _GREEN, _ORANGE, _PURPLE, _GREY = (214, 39, 40), (44, 160, 44), (255, 127, 14), (148, 103, 189), (127, 127, 127)

#: Entity path -> (legend names, RGB colours) per series, logged once as static ``rr.SeriesLines``.
SERIES_STYLES: Mapping[str, tuple[tuple[str, ...], tuple[tuple[int, int, int], ...]]] = MappingProxyType(
    {
        **{estimate_path(k): ((f"{k} estimate [{_UNITS[k]}]",), (_EST_COLOR,)) for k in ESTIMATE_KEYS},
        **{interval_path(k): ((f"{k} 95 % lower", f"{k} 95 % upper"), (_CI_COLOR, _CI_COLOR)) for k in ESTIMATE_KEYS},
        **{truth_path(k): ((f"{k} true [{_UNITS[k]}]",), (_TRUE_COLOR,)) for k in ESTIMATE_KEYS},
        **{f"params/{k}/per_sample": ((f"{k} per-sample (svf) [{_UNITS[k]}]",), (_ORANGE,)) for k in PARAM_NAMES},
        ANGLES: (("theta1 motor [rad]", "theta2 table x/l [rad]"), (_EST_COLOR, _ORANGE)),
        TORQUE_DRIVE: (("measured [N m]", "commanded [N m]"), (_RED, _GREY)),
        TORQUE_ESTIMATE: (("measured, filtered [N m]", "reconstructed, Eq. 18 on filtered derivatives [N m]"),
                          (_RED, _GREEN)),
        TORQUE_NRMSE: (("Eq. 18 vs measured (both filtered), NRMSE over 1 s [%]",), (_GREEN,)),
        TORQUE_CONTROL: (("control torque [N m]",), (_ORANGE,)),
        LATENESS: (("tick lateness [us] (max per 10 ticks)",), (_PURPLE,)),
        OVERRUNS: (("overruns [count]",), (_RED,)),
        STALLS: (("loop stalls [count]",), (_PURPLE,)),
        "control/position": (("reference [m]", "table [m]"), (_GREY, _EST_COLOR)),
        "control/error": (("tracking error [m]",), (_RED,)),
        "control/gains/theta2": (("gain on theta2 [N m/rad]",), (_EST_COLOR,)),
        "control/gains/omega1": (("gain on omega1 [N m s/rad]",), (_ORANGE,)),
        "control/margins/pm_deg": (("phase margin [deg]",), (_GREEN,)),
        "control/margins/gm_db": (("gain margin [dB]",), (_PURPLE,)),
        "control/redesigns": (("redesigns accepted", "redesigns rejected", "fallbacks to the conservative controller"),
                              (_GREEN, _RED, _GREY)),
    }
)

# ------------------------------------------------------------------ frequency-response drawing
_X_PER_DECADE = 100.0
_Y_PER_DB = 2.0
_Y_PER_DEG = 0.5


def _x(f_hz: np.ndarray) -> np.ndarray:
    return _X_PER_DECADE * np.log10(np.asarray(f_hz, dtype=float))


def _strip(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    ok = np.isfinite(x) & np.isfinite(y)
    return np.column_stack([x[ok], y[ok]])


def _grid(lo_hz: float, hi_hz: float, y_lo: float, y_hi: float, y_step: float, y_scale: float, unit: str
          ) -> tuple[list[np.ndarray], list[str], np.ndarray, list[str]]:
    """Grid lines and their labels: a vertical line at each 1-2-5 frequency, a horizontal one every
    ``y_step`` units of the quantity (dB or deg)."""
    strips, labels, pts, pt_labels = [], [], [], []
    y0, y1 = -y_scale * y_hi, -y_scale * y_lo
    for dec in range(int(math.floor(math.log10(lo_hz))), int(math.ceil(math.log10(hi_hz))) + 1):
        for m in (1, 2, 5):
            f = m * 10.0 ** dec
            if lo_hz <= f <= hi_hz:
                x = float(_x(np.array([f]))[0])
                strips.append(np.array([[x, y0], [x, y1]]))
                labels.append("")
                if m == 1:
                    pts.append([x, y1 + 6.0])
                    pt_labels.append(f"{f / 1000:g} kHz" if f >= 1000 else f"{f:g} Hz")
    x0, x1 = float(_x(np.array([lo_hz]))[0]), float(_x(np.array([hi_hz]))[0])
    v = math.floor(y_lo / y_step) * y_step
    while v <= y_hi + 1e-9:
        y = -y_scale * v
        strips.append(np.array([[x0, y], [x1, y]]))
        labels.append("")
        pts.append([x0 - 4.0, y])
        pt_labels.append(f"{v:g} {unit}")
        v += y_step
    return strips, labels, np.array(pts, dtype=float).reshape(-1, 2), pt_labels


def _strips(rec: Any, rr: Any, path: str, t: float, strips: list[np.ndarray], color: tuple[int, int, int],
            width: float, labels: list[str] | None = None) -> None:
    """One row of ``LineStrips2D`` at time ``t``, sent columnar like the time series: ``rec.log``
    of these views makes the telemetry process grow with every draw; ``send_columns`` does not."""
    n = len(strips)
    cols = rr.LineStrips2D.columns(strips=strips, colors=[color] * n, radii=[-width] * n,   # < 0: UI points
                                   labels=labels if labels is not None else [""] * n,
                                   show_labels=[labels is not None] * n).partition([n])
    rec.send_columns(path, indexes=[rr.TimeColumn("time", duration=[t])], columns=cols)


def _points(rec: Any, rr: Any, path: str, t: float, pts: np.ndarray, color: tuple[int, int, int], size: float,
            labels: list[str] | None = None) -> None:
    n = len(pts)
    cols = rr.Points2D.columns(positions=pts, colors=[color] * n, radii=[-size] * n,
                               labels=labels if labels is not None else [""] * n,
                               show_labels=[labels is not None] * n).partition([n])
    rec.send_columns(path, indexes=[rr.TimeColumn("time", duration=[t])], columns=cols)


def _bode_pair(rec: Any, rr: Any, t: float, base: str, f_model: np.ndarray,
               curves: list[tuple[str, np.ndarray, np.ndarray, tuple[int, int, int]]], f_meas: np.ndarray | None,
               meas: tuple[np.ndarray, np.ndarray] | None, marks: list[tuple[float, str]],
               mag_floor: float | None = None) -> None:
    """Draw one magnitude and one phase panel under ``base`` at time ``t`` (see the module docstring)."""
    lo_hz, hi_hz = float(np.min(f_model)), float(np.max(f_model))
    for part, k, step, scale, unit in (("magnitude", 0, 20.0, _Y_PER_DB, "dB"), ("phase", 1, 90.0, _Y_PER_DEG, "deg")):
        ys = [c[1 + k] for c in curves]
        if meas is not None:
            ys.append(meas[k])
        allv = np.concatenate([np.ravel(y) for y in ys])
        allv = allv[np.isfinite(allv)]
        if allv.size == 0:
            continue
        y_lo, y_hi = float(allv.min()), float(allv.max())
        if k == 0 and mag_floor is not None:
            y_lo = max(y_lo, mag_floor)
        y_lo, y_hi = math.floor(y_lo / step) * step, math.ceil(y_hi / step) * step
        path = f"{base}/{part}"
        strips, _, pts, pt_labels = _grid(lo_hz, hi_hz, y_lo, y_hi, step, scale, unit)
        _strips(rec, rr, f"{path}/grid", t, strips, (90, 90, 90), 0.5)
        _points(rec, rr, f"{path}/grid_labels", t, pts, (170, 170, 170), 0.1, pt_labels)
        for name, *vals, color in curves:
            if not np.any(np.isfinite(vals[k])):
                continue
            y = -scale * np.clip(vals[k], y_lo - step, y_hi + step)
            _strips(rec, rr, f"{path}/{name}", t, [_strip(_x(f_model), y)], color, 0.8 if "band" in name else 1.5)
        if meas is not None and f_meas is not None:
            y = -scale * np.asarray(meas[k], dtype=float)
            _points(rec, rr, f"{path}/measured", t, _strip(_x(f_meas), y), _RED, 3.0)
        y0, y1 = -scale * y_hi, -scale * y_lo
        mk = [(f, text) for f, text in marks if math.isfinite(f) and lo_hz <= f <= hi_hz]
        if mk:
            xs = [float(_x(np.array([f]))[0]) for f, _ in mk]
            _strips(rec, rr, f"{path}/marks", t, [np.array([[x, y0], [x, y1]]) for x in xs], _PURPLE, 1.0,
                    [text for _, text in mk])


def draw_fit_frf(rec: Any, rr: Any, t: float, view: Mapping[str, np.ndarray]) -> None:
    """The measured FRFs of theta1 and theta2 with the model and its 95 % band (one fit, at time t)."""
    f_res, f_anti = (float(v) for v in view["marks_hz"][:2])
    for j, name in ((1, "theta1"), (2, "theta2")):
        g = f"g{j}"
        curves = [("model", view[f"{g}_db"], view[f"{g}_deg"], _EST_COLOR),
                  ("band_low", view[f"{g}_lo"], view[f"{g}_deg"] * np.nan, _CI_COLOR),
                  ("band_high", view[f"{g}_hi"], view[f"{g}_deg"] * np.nan, _CI_COLOR)]
        marks = [(f_res, f"resonance {f_res:.0f} Hz")]
        if j == 1:
            marks.append((f_anti, f"anti-resonance {f_anti:.0f} Hz"))
        _bode_pair(rec, rr, t, f"{FRF}/{name}", view["f_model"], curves, view["f_meas"],
                   (view[f"m{j}_db"], view[f"p{j}_deg"]), marks)


def draw_loop_gain(rec: Any, rr: Any, t: float, view: Mapping[str, np.ndarray], margins: Mapping[str, float]) -> None:
    """The active controller's loop gain, 0 dB and -180 deg lines, crossover and margins (at time t)."""
    f, mag, ph = (np.asarray(view[k], dtype=float) for k in ("f_hz", "mag_db", "phase_deg"))
    zero = np.zeros_like(f)
    curves = [("loop_gain", mag, ph, _EST_COLOR), ("reference_0db_m180", zero, zero - 180.0, _GREY)]
    cross = np.flatnonzero(np.diff(np.sign(mag)) != 0)
    pm, gm = margins.get("pm_deg"), margins.get("gm_db")
    text = f"crossover, PM {pm:.0f} deg" if pm is not None and math.isfinite(pm) else "crossover"
    if gm is not None and math.isfinite(gm):
        text += f", GM {gm:.1f} dB"
    marks = [(float(f[cross[0]]), text)] if cross.size else []
    _bode_pair(rec, rr, t, f"{FRF}/loop", f, curves, None, None, marks, mag_floor=-80.0)


def default_blueprint() -> Any:
    """One grid: FRFs (measured vs model, loop gain), the estimates with their 95 % bands and true
    values, the torque, its Eq. 18 reconstruction and NRMSE, tracking, margins, the loop's timing."""
    import rerun.blueprint as rrb

    def frf(origin: str, name: str) -> Any:
        return rrb.Spatial2DView(origin=origin, name=name)

    views = [
        frf(f"{FRF}/theta1/magnitude", "FRF theta1/T: measured (dots) vs model, 95 % band [dB]"),
        frf(f"{FRF}/theta2/magnitude", "FRF theta2/T: measured (dots) vs model, 95 % band [dB]"),
        frf(f"{FRF}/theta1/phase", "FRF theta1/T phase [deg]"),
        frf(f"{FRF}/loop/magnitude", "loop gain of the active controller [dB]"),
        frf(f"{FRF}/loop/phase", "loop gain phase [deg]"),
    ]
    views += [rrb.TimeSeriesView(origin=f"params/{k}", name=f"{k} [{_UNITS[k]}]") for k in PARAM_NAMES]
    views += [rrb.TimeSeriesView(origin=f"modal/{k}", name=f"{k} [{_UNITS[k]}]") for k in MODAL_NAMES]
    views += [
        rrb.TimeSeriesView(origin=TORQUE_ESTIMATE, name="torque through the SVF: measured vs Eq. 18 [N m]"),
        rrb.TimeSeriesView(origin=TORQUE_NRMSE, name="Eq. 18 reconstruction NRMSE [%]"),
        rrb.TimeSeriesView(origin="control/position", name="table position: reference vs actual [m]"),
        rrb.TimeSeriesView(origin="control/error", name="tracking error [m]"),
        rrb.TimeSeriesView(origin="torque", contents=[f"+ /{TORQUE_DRIVE}", f"+ /{TORQUE_CONTROL}"],
                           name="torque: measured, commanded, control [N m]"),
        rrb.TimeSeriesView(origin="control/margins", name="margins of the active controller"),
        rrb.TimeSeriesView(origin="control/gains", name="controller gains"),
        rrb.TimeSeriesView(origin="control/redesigns", name="redesigns accepted / rejected, fallbacks"),
        rrb.TimeSeriesView(origin=ANGLES, name="encoder angles [rad]"),
        rrb.TimeSeriesView(origin=LATENESS, name="loop lateness [us]"),
        rrb.TimeSeriesView(origin=LOOP_EVENTS, name="loop overruns and stalls"),
        frf(f"{FRF}/theta2/phase", "FRF theta2/T phase [deg]"),
    ]
    # "following": the time cursor stays at the newest data (live and when a finished .rrd opens), so
    # the FRF and loop-gain views show the latest fit rather than the first one
    return rrb.Blueprint(rrb.Grid(*views, grid_columns=6),
                         rrb.TimePanel(timeline="time", state="collapsed", play_state="following"),
                         collapse_panels=True)


# ----- the XY circular test: one recording for both axes --------------------------------------------
CONTOUR_XY = "contour/xy"                  # the table's path and the reference circle [mm]
CONTOUR_BALLBAR = "contour/ballbar"        # each direction's radial deviation, magnified, around the circle
CONTOUR_RADIAL = "contour/radial_error"    # radial deviation [um] against the angle on the circle
CONTOUR_FIGURES = "contour/figures"        # G, F, H as text
_DIR_COLOR = {"ccw": (31, 119, 180), "cw": (214, 39, 40)}


def write_contour_rrd(path: str | None, reference: tuple[np.ndarray, np.ndarray],
                      paths: dict[str, tuple[np.ndarray, np.ndarray]], radius: float,
                      centre: tuple[float, float], figures: Mapping[str, Any], *,
                      connect_url: str | None = None) -> str:
    """The circular test's dashboard, both axes in one recording: the XY path of the table against the
    reference (``reference``: the commanded X and Y over the whole run, ``paths``: the measured table
    per direction over its measured turn, all in m), the ballbar trace (radial deviation magnified as
    in :func:`rt_ident.control.contour.polar_plot`), the deviation against the angle on the timeline
    ``angle`` (tenths of a degree, counter-clockwise from +X about the nominal centre) and the figures.
    Written after the run (the loop's samples of both axes are in hand then) to ``path``, or sent to
    the viewer at ``connect_url`` (a live run: beside the axes' recordings); returns where it went."""
    import os

    import rerun as rr
    import rerun.blueprint as rrb

    os.environ.setdefault("CI", "1")        # rerun: no analytics config written under HOME
    rec = rr.RecordingStream("rt_ident-xy-contour")
    bp = rrb.Blueprint(rrb.Horizontal(
        rrb.Spatial2DView(origin=CONTOUR_XY, name="XY path: reference vs table [mm]"),
        rrb.Spatial2DView(origin=CONTOUR_BALLBAR, name="ballbar: radial deviation, magnified"),
        rrb.Vertical(rrb.TimeSeriesView(origin=CONTOUR_RADIAL, name="radial deviation [um] along the circle"),
                     rrb.TextDocumentView(origin=CONTOUR_FIGURES, name="ISO 230-4 figures"))),
        rrb.TimePanel(timeline="angle", state="collapsed"))
    if connect_url is not None:
        rec.connect_grpc(connect_url, default_blueprint=bp)
        where = connect_url
    elif path is not None:
        rec.save(path, default_blueprint=bp)
        where = path
    else:
        raise ValueError("the contour dashboard needs a path or a connect_url")
    try:
        cx, cy = centre
        xr, yr = reference
        ok = np.isfinite(xr) & np.isfinite(yr)
        rec.log(f"{CONTOUR_XY}/reference", rr.LineStrips2D([np.column_stack([xr[ok], -yr[ok]]) * 1e3],
                                                           colors=[(128, 128, 128)], radii=[0.01]), static=True)
        devs = {d: np.hypot(x - cx, y - cy) - radius for d, (x, y) in paths.items()}
        span = max((float(np.max(np.abs(v))) for v in devs.values() if v.size), default=1e-6) or 1e-6
        scale = 10 ** math.ceil(math.log10(span * 1e6))       # um per half ring, as the PNG
        ring = np.linspace(0.0, 2 * math.pi, 361)
        rec.log(f"{CONTOUR_BALLBAR}/nominal", rr.LineStrips2D(
            [np.column_stack([np.cos(ring), -np.sin(ring)]) * r for r in (0.5, 1.0, 1.5)],
            colors=[(200, 200, 200), (128, 128, 128), (200, 200, 200)], radii=[0.004]), static=True)
        for d, (x, y) in paths.items():
            color = _DIR_COLOR.get(d, (0, 0, 0))
            rec.log(f"{CONTOUR_XY}/table_{d}", rr.LineStrips2D([np.column_stack([x, -y]) * 1e3], colors=[color],
                                                               radii=[0.01]), static=True)
            ang = np.arctan2(y - cy, x - cx)
            rho = 1.0 + devs[d] * 1e6 / scale
            strip = np.column_stack([rho * np.cos(ang), -rho * np.sin(ang)])
            rec.log(f"{CONTOUR_BALLBAR}/{d}", rr.LineStrips2D([strip], colors=[color], radii=[0.006]), static=True)
            tenth = np.round(np.degrees(np.mod(ang, 2 * math.pi)) * 10).astype(np.int64)
            order = np.argsort(tenth, kind="stable")
            rec.send_columns(f"{CONTOUR_RADIAL}/{d}", indexes=[rr.TimeColumn("angle", sequence=tenth[order])],
                             columns=rr.Scalars.columns(scalars=1e6 * devs[d][order]))
        lines = [f"circle R {1e3 * radius:g} mm; ballbar rings: -{scale / 2:g}, 0, +{scale / 2:g} um"]
        for d in ("ccw", "cw"):
            f = figures.get(d)
            if f:
                lines.append(f"{d.upper()}: G {f['G_um']:.2f} um, F {f['F_min_um']:+.2f} .. {f['F_max_um']:+.2f} um")
        if figures.get("H_um") is not None:
            lines.append(f"H {figures['H_um']:.2f} um")
        rec.log(CONTOUR_FIGURES, rr.TextDocument("\n\n".join(lines)), static=True)
    finally:
        rec.flush()
        rec.disconnect()
    return where
