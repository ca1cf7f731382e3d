"""The frequency-response view of a fit: measured FRF at the excited lines, the model's over it.

Built in the fit process (never in the tick) from the streaming DFT sums of the ``frequency``
method (:class:`~rt_ident.estimators.spectra.Spectra`) and the Gauss-Newton fit, and sent to
the dashboard once per fit:

* measured ``H1 = Theta1 / T`` and ``H2 = Theta2 / T`` at each excited harmonic: the ratio of the
  period-averaged spectra (the same ``mean`` the fit uses), magnitude in dB re 1 rad/(N m) and
  phase in degrees;
* the identified model's exact sampled response (:func:`~rt_ident.estimators.sampled_model.frequency_response`,
  the same hold as the fit) on a log grid, and its 95 % band: the 2.5 and 97.5 percentiles of the
  response over parameter draws from the fit's log-parameter covariance (a Monte-Carlo band: the
  magnitude near the resonance is far from linear in the parameters, so a first-order band
  would be too narrow there);
* the resonance (the flexible mode's wd of the model) and the anti-resonance of the motor
  side, the zero of ``I2 s^2 + B s + K`` (Eq. 3's motor row over the table row), ``sqrt(K / I2)``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from rt_ident.estimators.sampled_model import frequency_response

#: keys of the dict :func:`frf_view` returns (each a 1-D float array); the dashboard draws them
FRF_KEYS: tuple[str, ...] = ("f_meas", "m1_db", "p1_deg", "m2_db", "p2_deg", "f_model", "g1_db", "g1_lo", "g1_hi",
                             "g1_deg", "g2_db", "g2_lo", "g2_hi", "g2_deg", "marks_hz")


def _db(h: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore"):
        return 20.0 * np.log10(np.abs(h))


def _deg(h: np.ndarray) -> np.ndarray:
    """Unwrapped phase in degrees, shifted so its first point lies in (-360, 0]: a double
    integrator starts near -180 deg and stays below, as a Bode plot shows it."""
    ph = np.degrees(np.unwrap(np.angle(h)))
    if ph.size:
        ph -= 360.0 * math.ceil(ph[0] / 360.0)
    return ph


def frf_view(sp: Any, x_log: np.ndarray, cov_log: np.ndarray | None, hold: str, *, n_grid: int = 200,
             draws: int = 64, seed: int = 0) -> dict[str, np.ndarray]:
    """Measured and model FRFs of one fit (see the module docstring). ``x_log`` = log [I1, I2, B, K]."""
    f_meas = sp.omega / (2.0 * math.pi)
    Y1, Y2, T = sp.mean
    ok = np.abs(T) > 0.0
    H1 = np.where(ok, Y1 / np.where(ok, T, 1.0), np.nan)
    H2 = np.where(ok, Y2 / np.where(ok, T, 1.0), np.nan)
    nyq = 0.5 / sp.dt
    lo = max(float(f_meas.min()) / 2.0, 1e-3) if f_meas.size else 1.0
    hi = min(nyq * 0.98, float(f_meas.max()) * 2.0) if f_meas.size else nyq * 0.98
    f_model = np.geomspace(lo, max(hi, lo * 10.0), n_grid)
    z = np.exp(2j * math.pi * f_model * sp.dt)
    theta = np.asarray(x_log, dtype=float)[:4]
    G = frequency_response(theta, z, sp.dt, hold)            # (n_grid, 2): T -> theta1, theta2
    out = {"f_meas": f_meas, "m1_db": _db(H1), "p1_deg": _deg(H1), "m2_db": _db(H2), "p2_deg": _deg(H2),
           "f_model": f_model, "g1_db": _db(G[:, 0]), "g1_deg": _deg(G[:, 0]),
           "g2_db": _db(G[:, 1]), "g2_deg": _deg(G[:, 1])}
    band = None
    if cov_log is not None and np.all(np.isfinite(cov_log)) and draws > 1:
        rng = np.random.default_rng(seed)
        try:
            L = np.linalg.cholesky(np.asarray(cov_log, dtype=float)[:4, :4] + 1e-18 * np.eye(4))
            mags = []
            for _ in range(draws):
                x = theta + L @ rng.standard_normal(4)
                if not np.all(np.abs(x - theta) < 20.0):        # a draw e^20 away: no model to draw
                    continue
                try:
                    mags.append(_db(frequency_response(x, z, sp.dt, hold)).T)
                except (ArithmeticError, np.linalg.LinAlgError):
                    continue
            if len(mags) >= 8:
                band = np.percentile(np.array(mags), [2.5, 97.5], axis=0)      # (2, 2, n_grid)
        except np.linalg.LinAlgError:
            band = None
    for j, key in ((0, "g1"), (1, "g2")):
        if band is None:
            out[f"{key}_lo"] = out[f"{key}_db"].copy()
            out[f"{key}_hi"] = out[f"{key}_db"].copy()
        else:
            out[f"{key}_lo"], out[f"{key}_hi"] = band[0, j], band[1, j]
    I1, I2, B, K = np.exp(theta)
    g = 1.0 / I1 + 1.0 / I2
    wn = math.sqrt(K * g)
    zeta = 0.5 * B * g / wn
    wd = wn * math.sqrt(max(1.0 - zeta * zeta, 0.0))
    out["marks_hz"] = np.array([wd / (2.0 * math.pi), math.sqrt(K / I2) / (2.0 * math.pi)])
    return {k: np.asarray(out[k], dtype=np.float64) for k in FRF_KEYS}
