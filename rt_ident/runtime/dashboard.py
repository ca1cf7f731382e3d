"""The rerun dashboard: entity paths (all in one place) and the default blueprint.

Entity paths (time series on the ``time`` timeline, duration in seconds):

====================================  ==========================================  =========
entity                                block key (see :mod:`rt_ident.runtime.telemetry`)   unit
====================================  ==========================================  =========
``params/{I1,I2,B,K}/estimate``       ``"I1"``, ``"I2"``, ``"B"``, ``"K"``        SI
``params/{I1,I2,B,K}/true``           ``set_truth({...})``                        SI
``modal/{wn,zeta}/estimate``          ``"wn"``, ``"zeta"``                        rad/s, -
``modal/{wn,zeta}/true``              ``set_truth({...})``                        rad/s, -
``torque/measured``                   ``"torque_meas"``                           N m
``torque/commanded``                  ``"torque_cmd"``                            N m
``torque/reconstructed``              ``"torque_hat"`` (Eq. 18)                   N m
``angles/theta1``, ``angles/theta2``  ``"theta1"``, ``"theta2"``                  rad
``loop/lateness_us``                  ``"lateness_us"``                           us
``loop/overruns``                     ``"overruns"``                              count
``control/position/{reference,actual}`` ``"x_ref"``, ``"x_table"``               m
``control/error``                     ``"error_m"`` (table minus reference)       m
``torque/control``                    ``"u_control"`` (the host's control torque) N m
``control/gains/{theta2,omega1}``     ``"gain_theta2"``, ``"gain_omega1"``        N m/rad, N m s/rad
``control/margins/{pm_deg,gm_db}``    ``"pm_deg"``, ``"gm_db"`` (nominal loop)    deg, dB
``control/redesigns/{accepted,rejected}`` ``"n_accepted"``, ``"n_rejected"``           count
``control/redesigns/fallbacks``       ``"fallbacks"``                             count
``params/{I1,I2,B,K}/per_sample``     ``"svf_I1"`` ... (the per-sample estimate)   SI
====================================  ==========================================  =========

``rerun`` is imported only inside :func:`default_blueprint`, so the real-time process can import
the path constants without loading rerun.
"""

from __future__ import annotations

from types import MappingProxyType
from typing import Any, Mapping

PARAM_NAMES: tuple[str, ...] = ("I1", "I2", "B", "K")
MODAL_NAMES: tuple[str, ...] = ("wn", "zeta")
ESTIMATE_KEYS: tuple[str, ...] = PARAM_NAMES + MODAL_NAMES

TORQUE_MEASURED = "torque/measured"
TORQUE_COMMANDED = "torque/commanded"
TORQUE_RECONSTRUCTED = "torque/reconstructed"
THETA1 = "angles/theta1"
THETA2 = "angles/theta2"
LATENESS = "loop/lateness_us"
OVERRUNS = "loop/overruns"
TORQUE_CONTROL = "torque/control"

#: Per-tick control signals -> entity paths (sent on the tick timeline like the estimates).
CONTROL_ENTITIES: Mapping[str, str] = MappingProxyType(
    {
        "x_ref": "control/position/reference",
        "x_table": "control/position/actual",
        "error_m": "control/error",
        "u_control": TORQUE_CONTROL,
        "gain_theta2": "control/gains/theta2",
        "gain_omega1": "control/gains/omega1",
        "pm_deg": "control/margins/pm_deg",
        "gm_db": "control/margins/gm_db",
        "n_accepted": "control/redesigns/accepted",
        "n_rejected": "control/redesigns/rejected",
        "fallbacks": "control/redesigns/fallbacks",
        **{f"svf_{k}": f"params/{k}/per_sample" for k in PARAM_NAMES},
    }
)


def estimate_path(key: str) -> str:
    """Entity of the running estimate of ``key`` (one of :data:`ESTIMATE_KEYS`)."""
    return f"{'params' if key in PARAM_NAMES else 'modal'}/{key}/estimate"


def truth_path(key: str) -> str:
    """Entity of the true value of ``key``, drawn next to its estimate."""
    return f"{'params' if key in PARAM_NAMES else 'modal'}/{key}/true"


#: Block key -> entity path for every signal the telemetry process draws.
BLOCK_ENTITIES: Mapping[str, str] = MappingProxyType(
    {
        "theta1": THETA1,
        "theta2": THETA2,
        "torque_meas": TORQUE_MEASURED,
        "torque_cmd": TORQUE_COMMANDED,
        "torque_hat": TORQUE_RECONSTRUCTED,
        **{k: estimate_path(k) for k in ESTIMATE_KEYS},
        "lateness_us": LATENESS,
        "overruns": OVERRUNS,
        **CONTROL_ENTITIES,
    }
)

_UNITS = MappingProxyType({"I1": "kg m²", "I2": "kg m²", "B": "N m s/rad", "K": "N m/rad",
                           "wn": "rad/s", "zeta": "-"})
_EST_COLOR = (31, 119, 180)
_TRUE_COLOR = (150, 150, 150)

#: Entity path -> (legend name, RGB colour), logged once as static ``rr.SeriesLines``.
SERIES_STYLES: Mapping[str, tuple[str, tuple[int, int, int]]] = MappingProxyType(
    {
        **{estimate_path(k): (f"{k} estimate [{_UNITS[k]}]", _EST_COLOR) for k in ESTIMATE_KEYS},
        **{truth_path(k): (f"{k} true [{_UNITS[k]}]", _TRUE_COLOR) for k in ESTIMATE_KEYS},
        **{f"params/{k}/per_sample": (f"{k} per-sample (svf) [{_UNITS[k]}]", (255, 127, 14)) for k in PARAM_NAMES},
        TORQUE_MEASURED: ("measured [N m]", (214, 39, 40)),
        TORQUE_COMMANDED: ("commanded [N m]", (127, 127, 127)),
        TORQUE_RECONSTRUCTED: ("reconstructed, Eq. 18 [N m]", (44, 160, 44)),
        THETA1: ("theta1 motor [rad]", (31, 119, 180)),
        THETA2: ("theta2 table x/l [rad]", (255, 127, 14)),
        LATENESS: ("tick lateness [us]", (148, 103, 189)),
        OVERRUNS: ("overruns [count]", (214, 39, 40)),
        "control/position/reference": ("reference [m]", (127, 127, 127)),
        "control/position/actual": ("table [m]", (31, 119, 180)),
        "control/error": ("tracking error [m]", (214, 39, 40)),
        TORQUE_CONTROL: ("control torque [N m]", (255, 127, 14)),
        "control/gains/theta2": ("gain on theta2 [N m/rad]", (31, 119, 180)),
        "control/gains/omega1": ("gain on omega1 [N m s/rad]", (255, 127, 14)),
        "control/margins/pm_deg": ("phase margin [deg]", (44, 160, 44)),
        "control/margins/gm_db": ("gain margin [dB]", (148, 103, 189)),
        "control/redesigns/accepted": ("redesigns accepted", (44, 160, 44)),
        "control/redesigns/rejected": ("redesigns rejected", (214, 39, 40)),
        "control/redesigns/fallbacks": ("fallbacks to the conservative controller", (127, 127, 127)),
    }
)


def default_blueprint() -> Any:
    """A grid of time-series views: I1, I2, B, K (each with its true value), wn, zeta,
    measured vs reconstructed torque, encoder angles, loop lateness, overruns."""
    import rerun.blueprint as rrb

    views = [
        rrb.TimeSeriesView(origin=f"params/{k}", name=f"{k} [{_UNITS[k]}]") for k in PARAM_NAMES
    ]
    views += [rrb.TimeSeriesView(origin=f"modal/{k}", name=f"{k} [{_UNITS[k]}]") for k in MODAL_NAMES]
    views += [
        rrb.TimeSeriesView(origin="torque", name="torque: measured vs reconstructed (Eq. 18)"),
        rrb.TimeSeriesView(origin="angles", name="encoder angles [rad]"),
        rrb.TimeSeriesView(origin=LATENESS, name="loop lateness [us]"),
        rrb.TimeSeriesView(origin=OVERRUNS, name="loop overruns"),
        rrb.TimeSeriesView(origin="control/position", name="table position: reference vs actual [m]"),
        rrb.TimeSeriesView(origin="control/error", name="tracking error [m]"),
        rrb.TimeSeriesView(origin="control/gains", name="controller gains"),
        rrb.TimeSeriesView(origin="control/margins", name="margins of the active controller"),
        rrb.TimeSeriesView(origin="control/redesigns", name="redesigns accepted / rejected, fallbacks"),
    ]
    return rrb.Blueprint(rrb.Grid(*views, grid_columns=4), collapse_panels=True)
