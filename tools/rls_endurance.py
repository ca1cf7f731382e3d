"""10^8 RLS updates with long zero-excitation stretches and non-finite samples: does P stay SPD?

    python tools/rls_endurance.py [--updates 1e8] [--variant directional]

Feeds blocks of 10^6 samples of the paper's 5-regressor, 4-output shape: excited stretches,
zero-regressor stretches (no excitation) and a sprinkling of NaN/inf samples. After each block it
checks that P is finite, symmetric and positive definite and prints the running tallies.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from rt_ident.estimators.rls import RecursiveLeastSquares


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--updates", type=float, default=1e8)
    ap.add_argument("--variant", default="directional", choices=("standard", "directional", "bounded-trace"))
    ap.add_argument("--forgetting", type=float, default=0.999)
    a = ap.parse_args()
    rng = np.random.default_rng(0)
    truth = rng.normal(size=(5, 4))
    rls = RecursiveLeastSquares(5, 4, p0=1e3, forgetting=a.forgetting, variant=a.variant)
    block = 1_000_000
    n_blocks = int(a.updates // block)
    t0 = time.perf_counter()
    worst_min_eig, worst_asym, max_trace = np.inf, 0.0, 0.0
    for b in range(n_blocks):
        Phi = rng.normal(size=(block, 5)) * np.array([1e-2, 3.0, 1e-2, 3.0, 0.3])
        if b % 3 == 1:
            Phi[: block // 2] = 0.0                     # half a block with no excitation at all
        Y = Phi @ truth + 1e-6 * rng.normal(size=(block, 4))
        bad = rng.choice(block, 20, replace=False)
        Phi[bad[:10], 0] = np.nan
        Y[bad[10:], 1] = np.inf
        rls.update_block(Phi, Y)
        P = rls.P
        if not np.all(np.isfinite(P)):
            raise SystemExit(f"block {b}: P has non-finite entries")
        worst_asym = max(worst_asym, float(np.max(np.abs(P - P.T))))
        worst_min_eig = min(worst_min_eig, float(np.linalg.eigvalsh(P).min()))
        max_trace = max(max_trace, float(np.trace(P)))
    dt = time.perf_counter() - t0
    err = float(np.max(np.abs(rls.theta - truth)))
    print(f"{rls.n_updates + rls.n_rejected:.3g} samples ({a.variant}, lambda={a.forgetting}) in {dt:.1f} s "
          f"({(rls.n_updates + rls.n_rejected) / dt / 1e6:.2f} M/s): rejected {rls.n_rejected}, "
          f"min eig(P) {worst_min_eig:.3g} > 0, max |P-P^T| {worst_asym:.3g}, max trace(P) {max_trace:.3g}, "
          f"max |theta - truth| {err:.3g}")


if __name__ == "__main__":
    main()
