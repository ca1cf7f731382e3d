"""PNG figures of ``rt-ident reproduce --figures DIR`` (the paper's Figs. 4, 7-8, 9-12)."""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np
from matplotlib.figure import Figure

from rt_ident.reports.reproduce import CaseResult, ReproduceResult

_RLS_FIGS = (("fig09_rls_K.png", "K", "Stiffness K [N m/rad]"),
             ("fig10_rls_B.png", "B", "Damping B [N m s/rad]"),
             ("fig11_rls_I2.png", "I2", "Table inertia I2 [kg m²]"),
             ("fig12_rls_I1.png", "I1", "Motor inertia I1 [kg m²]"))


class _Arrays(NamedTuple):
    """The arrays a case keeps for the figures (``keep_arrays=True``)."""

    t: np.ndarray
    torque: np.ndarray
    torque_hat_ls: np.ndarray
    torque_hat_rls: np.ndarray
    rls_history_t: np.ndarray
    rls_history: dict[str, np.ndarray]


def _arrays(c: CaseResult) -> _Arrays:
    if (c.t is None or c.torque is None or c.torque_hat_ls is None or c.torque_hat_rls is None
            or c.rls_history_t is None or c.rls_history is None):
        raise ValueError(f"case N={c.N} k={c.k}: run with keep_arrays=True for the figures")
    return _Arrays(c.t, c.torque, c.torque_hat_ls, c.torque_hat_rls, c.rls_history_t, c.rls_history)


def write_figures(result: ReproduceResult, out_dir: str | Path) -> list[Path]:
    """Write the figures; every case must have been run with ``keep_arrays=True``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    c0 = result.cases[0]
    kept = [_arrays(c) for c in result.cases]

    # Fig. 4: the Schroeder excitation (first case, two periods)
    fig = Figure(figsize=(8, 3.2))
    ax = fig.subplots()
    a0 = kept[0]
    n = min(len(a0.t), 2 * c0.N)
    ax.plot(a0.t[:n] * 1e3, a0.torque[:n], lw=0.9)
    ax.set(xlabel="t [ms]", ylabel="T [N m]",
           title=f"Fig. 4 - Schroeder excitation (N={c0.N}, harmonics {c0.band[0]}..{c0.band[1]})")
    ax.grid(alpha=0.3)
    written.append(_save(fig, out / "fig04_excitation.png"))

    # Figs. 7-8: identified vs true excitation, Eq. (18). Two periods of three overlapping traces are
    # unreadable at N = 2048 (440 ms of dense multisine): the top panel zooms into a window of
    # ~60 samples where the traces can be told apart, the bottom one shows the errors over two periods.
    for num, c, a in zip((7, 8), result.cases, kept):
        fig = Figure(figsize=(8, 5.4))
        ax, ax_e = fig.subplots(2, 1, gridspec_kw={"height_ratios": [1.2, 1]})
        n = min(len(a.t), 2 * c.N)
        w0 = c.N // 2
        w = slice(w0, min(n, w0 + max(40, c.N // 32)))
        ax.plot(a.t[w] * 1e3, a.torque[w], "k", lw=1.6, label="true")
        ax.plot(a.t[w] * 1e3, a.torque_hat_ls[w], "--", lw=1.2, label=f"LS (NRMSE {c.ls_fit_nrmse:.3g})")
        ax.plot(a.t[w] * 1e3, a.torque_hat_rls[w], ":", lw=1.6, label=f"RLS (NRMSE {c.rls_fit_nrmse:.3g})")
        ax.set(xlabel="t [ms]", ylabel="T [N m]",
               title=f"Fig. {num} - identified excitation, N={c.N} k={c.k}: a zoom of {w.stop - w.start} samples")
        ax.legend(loc="upper right", fontsize=8)
        ax.grid(alpha=0.3)
        ax_e.plot(a.t[:n] * 1e3, a.torque_hat_ls[:n] - a.torque[:n], lw=0.8, label="LS - true")
        ax_e.plot(a.t[:n] * 1e3, a.torque_hat_rls[:n] - a.torque[:n], lw=0.8, alpha=0.8, label="RLS - true")
        ax_e.axvspan(a.t[w.start] * 1e3, a.t[w.stop - 1] * 1e3, color="0.85", zorder=0, label="zoom above")
        ax_e.set(xlabel="t [ms]", ylabel="error [N m]", title="reconstruction error over two periods")
        ax_e.legend(loc="upper right", fontsize=8)
        ax_e.grid(alpha=0.3)
        written.append(_save(fig, out / f"fig{num:02d}_identified_excitation_N{c.N}.png"))

    # Figs. 9-12: recursive estimates over time, both cases, with the true value. The y range holds
    # the true value and the estimate after its first 10 % (the start-up transient may leave it).
    for fname, key, label in _RLS_FIGS:
        fig = Figure(figsize=(10, 3.2))
        axes = fig.subplots(1, len(result.cases))
        for ax, c, a in zip(axes, result.cases, kept):
            h = a.rls_history[key]
            ax.plot(a.rls_history_t * 1e3, h, lw=1.0, label="RLS")
            ax.axhline(result.truth[key], color="k", ls="--", lw=0.8, label="true")
            ax.set(xlabel="t [ms]", ylabel=label, title=f"N={c.N} k={c.k}")
            tail = h[len(h) // 10:]
            tail = tail[np.isfinite(tail)]
            vals = np.concatenate([tail, [result.truth[key], 0.0]])
            lo, hi = float(vals.min()), float(vals.max())
            pad = 0.12 * (hi - lo or abs(hi) or 1.0)
            ax.set_ylim(lo - (pad if lo < 0 else 0.0), hi + pad)
            ax.grid(alpha=0.3)
        axes[0].legend(fontsize=8)
        fig.suptitle(f"Recursive estimation of {key}")
        written.append(_save(fig, out / fname))
    return written


def _save(fig: Figure, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    return path
