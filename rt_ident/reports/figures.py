"""PNG figures of ``rt-ident reproduce --figures DIR`` (the paper's Figs. 4, 7-8, 9-12)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from rt_ident.reports.reproduce import ReproduceResult  # noqa: E402

_RLS_FIGS = (("fig09_rls_K.png", "K", "Stiffness K [N m/rad]"),
             ("fig10_rls_B.png", "B", "Damping B [N m s/rad]"),
             ("fig11_rls_I2.png", "I2", "Table inertia I2 [kg m²]"),
             ("fig12_rls_I1.png", "I1", "Motor inertia I1 [kg m²]"))


def write_figures(result: ReproduceResult, out_dir: str | Path) -> list[Path]:
    """Write the figures; every case must have been run with ``keep_arrays=True``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    c0 = result.cases[0]

    # Fig. 4: the Schroeder excitation (first case, two periods)
    fig, ax = plt.subplots(figsize=(8, 3.2))
    n = min(len(c0.t), 2 * c0.N)
    ax.plot(c0.t[:n] * 1e3, c0.torque[:n], lw=0.9)
    ax.set(xlabel="t [ms]", ylabel="T [N m]",
           title=f"Fig. 4 - Schroeder excitation (N={c0.N}, harmonics {c0.band[0]}..{c0.band[1]})")
    ax.grid(alpha=0.3)
    written.append(_save(fig, out / "fig04_excitation.png"))

    # Figs. 7-8: identified vs true excitation, Eq. (18)
    for num, c in zip((7, 8), result.cases):
        fig, ax = plt.subplots(figsize=(8, 3.2))
        n = min(len(c.t), 2 * c.N)
        ax.plot(c.t[:n] * 1e3, c.torque[:n], "k", lw=1.2, label="true")
        ax.plot(c.t[:n] * 1e3, c.torque_hat_ls[:n], "--", lw=0.9, label=f"LS, NRMSE {c.ls_fit_nrmse:.3g}")
        ax.plot(c.t[:n] * 1e3, c.torque_hat_rls[:n], ":", lw=0.9, label=f"RLS, NRMSE {c.rls_fit_nrmse:.3g}")
        ax.set(xlabel="t [ms]", ylabel="T [N m]", title=f"Fig. {num} - identified excitation, N={c.N} k={c.k}")
        ax.legend(loc="upper right", fontsize=8)
        ax.grid(alpha=0.3)
        written.append(_save(fig, out / f"fig{num:02d}_identified_excitation_N{c.N}.png"))

    # Figs. 9-12: recursive estimates over time, both cases, with the true value
    for fname, key, label in _RLS_FIGS:
        fig, axes = plt.subplots(1, len(result.cases), figsize=(10, 3.2))
        for ax, c in zip(axes, result.cases):
            ax.plot(c.rls_history_t * 1e3, c.rls_history[key], lw=1.0, label="RLS")
            ax.axhline(result.truth[key], color="k", ls="--", lw=0.8, label="true")
            ax.set(xlabel="t [ms]", ylabel=label, title=f"N={c.N} k={c.k}")
            lo, hi = sorted((0.0, 2.5 * result.truth[key]))
            ax.set_ylim(lo, hi)
            ax.grid(alpha=0.3)
        axes[0].legend(fontsize=8)
        fig.suptitle(f"Recursive estimation of {key}")
        written.append(_save(fig, out / fname))
    return written


def _save(fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
