"""``rt-ident reproduce``: the paper's two Table 2 cases, end to end.

For each case (N, k): Dt from Table 2's criterion, a Schroeder multisine
periodic over N samples, Newmark (average acceleration) simulation of the
Table 1 axis from rest, then the paper's Euler-form LS (Eq. 10) and RLS
(Eqs. 14-16), recovery of (I1, I2, B, K), modal parameters of the estimated
state matrix, and the excitation identified by Eq. (18).

The paper does not state the multisine's harmonic band or its amplitude. We
excite harmonics 1..``band_factor``*k: Table 2's criterion puts harmonic k
exactly at wn (w0 = wn/k), so the default band_factor = 2 covers the
resonance and an octave above it. Amplitude cannot change noise-free linear
LS results (every signal scales with it); :func:`sensitivity` shows both.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from rt_ident.axis.excitation import schroeder_multisine
from rt_ident.axis.integrators import Trajectory, get_integrator
from rt_ident.axis.modal import modal_parameters
from rt_ident.axis.params import AxisParams, thomson_x
from rt_ident.axis.timestep import table2_cases
from rt_ident.estimators.excitation_id import nrmse, reconstruct_torque
from rt_ident.estimators.paper import fit_paper_ls, fit_paper_rls

if TYPE_CHECKING:
    from rt_ident.estimators.registry import LinearMethod
from rt_ident.reports import paper_tables

PARAM_KEYS = ("I1", "I2", "B", "K")
MODAL_KEYS = ("wn", "wd", "zeta")
ALL_KEYS = PARAM_KEYS + MODAL_KEYS

Progress = Callable[[str, float], None]  # (description, fraction done 0..1)


def _summary(p: AxisParams) -> dict[str, float]:
    out = {k: getattr(p, k) for k in PARAM_KEYS}
    out.update(modal_parameters(p))
    return out


@dataclass
class CaseResult:
    N: int
    k: int
    dt: float
    w0: float
    wn: float
    band: tuple[int, int]
    periods: int
    ls: dict[str, float]
    rls: dict[str, float]
    ls_fit_nrmse: float
    rls_fit_nrmse: float
    beyond: dict[str, dict[str, float]] = field(default_factory=dict)
    # arrays kept for figures
    t: np.ndarray | None = None
    torque: np.ndarray | None = None
    torque_hat_ls: np.ndarray | None = None
    torque_hat_rls: np.ndarray | None = None
    rls_history_t: np.ndarray | None = None
    rls_history: dict[str, np.ndarray] | None = None


@dataclass
class ReproduceResult:
    truth: dict[str, float]
    table2: list[dict[str, float]]
    cases: list[CaseResult]
    band_factor: float
    periods: int
    peak_torque: float

    def as_json(self) -> dict:
        return {
            "truth": self.truth,
            "table2": self.table2,
            "settings": {"band": "harmonics 1..band_factor*k", "band_factor": self.band_factor,
                         "periods": self.periods, "peak_torque_Nm": self.peak_torque,
                         "integrator": "newmark(alpha=1/4, delta=1/2)"},
            "cases": [
                {"N": c.N, "k": c.k, "dt": c.dt, "band": list(c.band),
                 "ls": c.ls, "rls": c.rls,
                 "excitation_fit_nrmse": {"ls": c.ls_fit_nrmse, "rls": c.rls_fit_nrmse},
                 **({"beyond": c.beyond} if c.beyond else {})}
                for c in self.cases
            ],
            "paper": {
                "ls": [paper_tables.LS[(c.N, c.k)] for c in self.cases],
                "rls": [paper_tables.RLS[(c.N, c.k)] for c in self.cases],
            },
        }


def simulate_case(p: AxisParams, N: int, k: int, dt: float, *, band_factor: float, periods: int,
                  peak_torque: float) -> tuple[tuple[int, int], Trajectory]:
    """Schroeder excitation (harmonics 1..band_factor*k) and the Newmark response from rest."""
    hi = int(min(max(1, round(band_factor * k)), N // 2 - 1))
    ms = schroeder_multisine(N, (1, hi), peak=peak_torque)
    torque = ms.periodic(periods)
    traj = get_integrator("newmark").simulate(p, torque, dt)
    return (1, hi), traj


def run_case(p: AxisParams, N: int, k: int, dt: float, w0: float, wn: float, *, band_factor: float = 2.0,
             periods: int = 4, peak_torque: float = 0.3, beyond: Iterable[str] = (),
             keep_arrays: bool = False, progress: Progress | None = None) -> CaseResult:
    band, traj = simulate_case(p, N, k, dt, band_factor=band_factor, periods=periods, peak_torque=peak_torque)
    states = traj.states()
    if progress:
        progress(f"N={N} k={k}: LS", 0.3)
    ls = fit_paper_ls(states, traj.torque, dt)
    if progress:
        progress(f"N={N} k={k}: RLS", 0.5)
    rls = fit_paper_rls(states, traj.torque, dt, history=-1 if keep_arrays else 0)
    # Eq. (18): identified excitation from the estimated matrices and the simulated response
    hat_ls = reconstruct_torque(ls.params, traj.theta, traj.omega, traj.alpha)[:, 0]
    hat_rls = reconstruct_torque(rls.params, traj.theta, traj.omega, traj.alpha)[:, 0]
    res = CaseResult(
        N=N, k=k, dt=dt, w0=w0, wn=wn, band=band, periods=periods,
        ls=_summary(ls.params), rls=_summary(rls.params),
        ls_fit_nrmse=float(nrmse(hat_ls, traj.torque)), rls_fit_nrmse=float(nrmse(hat_rls, traj.torque)),
    )
    for i, name in enumerate(beyond):
        if progress:
            progress(f"N={N} k={k}: {name}", 0.6 + 0.4 * i / max(1, len(tuple(beyond))))
        res.beyond[name] = _beyond(name, traj, dt, N)
    if keep_arrays:
        res.t, res.torque = traj.t, traj.torque
        res.torque_hat_ls, res.torque_hat_rls = hat_ls, hat_rls
        res.rls_history_t, res.rls_history = rls.history_t, rls.history
    return res


#: "beyond the paper" rows: label -> (registry method, options). The data are Newmark (trapezoidal),
#: so "zoh" is shown as the consistent model of the *other* hold, for contrast.
BEYOND: dict[str, tuple[LinearMethod, dict[str, Any]]] = {
    "tustin (states)": ("tustin", {"use_states": True}),
    "tustin (angles only)": ("tustin", {"use_states": False}),
    "frequency (Newmark model, angles only)": ("frequency", {"hold": "tustin"}),
    "zoh (wrong hold for these data)": ("zoh", {}),
}


def _beyond(label: str, traj: Trajectory, dt: float, N: int) -> dict[str, float]:
    from rt_ident.estimators.registry import IdentData, identify

    method, options = BEYOND[label]
    data = IdentData(t=traj.t, theta1=traj.theta[:, 0], theta2=traj.theta[:, 1], torque=traj.torque,
                     omega1=traj.omega[:, 0], omega2=traj.omega[:, 1], dt=dt, period=N)
    ident = identify(data, method, **options)
    return _summary(ident.params)


def run_reproduce(*, band_factor: float = 2.0, periods: int = 4, peak_torque: float = 0.3,
                  beyond: Iterable[str] = (), keep_arrays: bool = False,
                  progress: Progress | None = None) -> ReproduceResult:
    p = thomson_x()
    truth = _summary(p)
    cases = table2_cases(truth["wn"])
    out = []
    for i, c in enumerate(cases):
        def sub(desc: str, frac: float, i: int = i) -> None:
            if progress:
                progress(desc, (i + frac) / len(cases))
        out.append(run_case(p, c.N, int(c.k), c.dt, c.w0, c.wn, band_factor=band_factor, periods=periods,
                            peak_torque=peak_torque, beyond=tuple(beyond), keep_arrays=keep_arrays,
                            progress=sub))
    if progress:
        progress("done", 1.0)
    table2 = [{"N": c.N, "k": int(c.k), "wn": c.wn, "w0": c.w0, "dt": c.dt} for c in cases]
    return ReproduceResult(truth, table2, out, band_factor, periods, peak_torque)


def error_pct(estimate: float, truth: float) -> float:
    return 100.0 * abs(estimate - truth) / abs(truth)


def _raw_ls_summary(traj: Trajectory, dt: float) -> dict[str, float]:
    """Euler LS values even when they come out non-physical (then modal values are NaN)."""
    from rt_ident.errors import RtIdentError
    from rt_ident.estimators.ls import lstsq
    from rt_ident.estimators.paper import euler_regression, recover_values

    A, b = euler_regression(traj.states(), traj.torque)
    vals = dict(zip(PARAM_KEYS, (float(v) for v in recover_values(lstsq(A, b).theta, dt))))
    try:
        vals.update(modal_parameters(AxisParams(**vals)))
    except RtIdentError:
        vals.update({k: math.nan for k in MODAL_KEYS})
    return vals


def sensitivity(band_factors: Iterable[float] = (0.5, 1.0, 2.0, 4.0, math.inf),
                peaks: Iterable[float] = (0.3, 3.0), periods: int = 4) -> list[dict]:
    """LS error % of every parameter, per case, per band and amplitude (the paper leaves both unstated)."""
    p = thomson_x()
    truth = _summary(p)
    rows = []
    for c in table2_cases(truth["wn"]):
        for bf in band_factors:
            for peak in peaks:
                band, traj = simulate_case(p, c.N, int(c.k), c.dt, band_factor=bf if math.isfinite(bf) else 1e9,
                                           periods=periods, peak_torque=peak)
                est = _raw_ls_summary(traj, c.dt)
                rows.append({"N": c.N, "k": int(c.k), "band": list(band), "peak": peak,
                             "error_pct": {key: 100.0 * (est[key] - truth[key]) / truth[key] for key in ALL_KEYS}})
    return rows
