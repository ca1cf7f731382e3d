"""Noise study: how each estimator's error moves with encoder quantization and torque noise.

Closed-loop bench data from :class:`rt_ident.axis.plant.PlantSimulator` (the Table 1 axis at the paper's
Dt, position hold closed, Schroeder period 512 samples, harmonics 1..20, peak 0.3 N m, 20 periods):
angles only, quantized to a motor encoder of ``cpr`` counts/rev and a linear scale of matching
resolution, torque measured with Gaussian noise of the given % of its rms. Methods:

- "frequency": the default; exact sampled (ZOH) model on period-averaged spectra;
- "tustin": the exact time-domain regression for trapezoidal data, angles only (3-point relation);
- "paper": the paper's Euler LS on Kalman-filtered velocities (what Eq. 9 gets on a bench).

The figure of merit is the largest |error| over I1, I2, B, K in %; an estimator that fails or gives
a non-physical value is reported as NaN (drawn at the top of the plot).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from rt_ident.axis.excitation import schroeder_multisine
from rt_ident.axis.params import AxisParams, thomson_x
from rt_ident.axis.plant import HoldController, PlantBlock, PlantSimulator, SensorConfig
from rt_ident.errors import RtIdentError

if TYPE_CHECKING:
    from rt_ident.estimators.registry import LinearMethod

QUANTIZATION = ((0, 0.0), (2**20, 1.25e-8), (2**17, 1e-7), (2**14, 8e-7))   # (counts/rev, scale m); 0 = ideal
TORQUE_NOISE_PCT = (0.0, 0.5, 2.0)
METHODS: tuple[LinearMethod, ...] = ("frequency", "tustin", "paper")
DT, N, PERIODS = 2.9481e-5, 512, 20


def _data(cpr: int, res: float, noise_pct: float, seed: int = 5) -> tuple[AxisParams, PlantBlock]:
    p = thomson_x()
    ms = schroeder_multisine(N, (1, 20), peak=0.3)
    u = ms.periodic(PERIODS)
    sensors = SensorConfig(counts_per_rev=cpr, scale_resolution=res,
                           torque_meas_noise=noise_pct / 100.0 * ms.rms)
    blk = PlantSimulator(p, DT, sensors=sensors, controller=HoldController(), torque_limit=1.0,
                         seed=seed).step_block(u)
    return p, blk


def _fit(method: LinearMethod, blk: PlantBlock, cpr: int, res: float) -> dict[str, float]:
    from rt_ident.estimators.registry import IdentData, identify

    if method == "paper":
        from rt_ident.estimators.paper import fit_paper_ls
        from rt_ident.estimators.state_estimation import AxisStateEstimator, encoder_quanta

        q1, q2 = encoder_quanta(cpr or 2**24, res or 1e-9, thomson_x().lead)
        st = AxisStateEstimator(DT, q1, q2, 1e9).filter_block(blk.theta1, blk.theta2)
        states = np.column_stack([st.theta[:, 0], st.omega[:, 0], st.theta[:, 1], st.omega[:, 1]])
        return fit_paper_ls(states, blk.torque_meas, DT).params.as_dict()
    data = IdentData(t=None, theta1=blk.theta1, theta2=blk.theta2, torque=blk.torque_meas, dt=DT,
                     period=N if method == "frequency" else None)
    opts = {"use_states": False} if method == "tustin" else {}
    return identify(data, method, **opts).params.as_dict()


def run_study(progress: Callable[[str, float], None] | None = None) -> list[dict]:
    rows = []
    total = len(QUANTIZATION) * len(TORQUE_NOISE_PCT) * len(METHODS)
    i = 0
    for cpr, res in QUANTIZATION:
        for noise in TORQUE_NOISE_PCT:
            p, blk = _data(cpr, res, noise)
            for m in METHODS:
                i += 1
                if progress:
                    progress(f"noise study: cpr={cpr or 'ideal'} noise={noise}% {m}", i / total)
                try:
                    est = _fit(m, blk, cpr, res)
                    err = max(abs(est[k] / getattr(p, k) - 1) * 100 for k in ("I1", "I2", "B", "K"))
                except RtIdentError:
                    err = math.nan
                rows.append({"counts_per_rev": cpr, "scale_m": res, "torque_noise_pct": noise, "method": m,
                             "max_error_pct": err})
    return rows


def write_png(rows: list[dict], path: str | Path) -> Path:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 3.6))
    axes = fig.subplots(1, len(TORQUE_NOISE_PCT), sharey=True)
    labels = ["ideal" if c == 0 else f"2^{int(math.log2(c))}" for c, _ in QUANTIZATION]
    for ax, noise in zip(axes, TORQUE_NOISE_PCT):
        for m, marker in zip(METHODS, "os^"):
            ys = [next(r["max_error_pct"] for r in rows if r["counts_per_rev"] == c and r["method"] == m
                       and r["torque_noise_pct"] == noise) for c, _ in QUANTIZATION]
            ys = [1e3 if not math.isfinite(y) else max(y, 1e-12) for y in ys]
            ax.semilogy(labels, ys, marker=marker, label=m)
        ax.axhline(1.0, color="k", ls=":", lw=0.8)
        ax.set(title=f"torque noise {noise:g} %", xlabel="motor encoder counts/rev")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("max |error| over I1, I2, B, K [%]")
    axes[0].legend(fontsize=8)
    fig.suptitle("Noise study: closed loop, angles only, 34 kHz (failures drawn at 1e3 %)")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    return path
