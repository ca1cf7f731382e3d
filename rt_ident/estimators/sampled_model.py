"""Exact sampled models of the axis in the frequency domain, with derivatives (for the frequency fit).

Every way the data can be made is written ``M(z) X(z) = N(z) T(z) + z c`` for the DFT
X of the Eq. (8) state over one window and the DFT T of the torque samples:

* ``"zoh"``: torque held over [t_k, t_k+1) (a real drive): M = zI - Ad, N = bd,
  [Ad, bd] from expm([[A, b], [0, 0]] dt);
* ``"tustin"``: trapezoidal rule = Newmark average acceleration (Eqs. 4-6) with the load
  at both ends (the paper's simulations): M = (z-1)I - (dt/2)(z+1)A, N = (dt/2)(z+1)b;
* ``"tustin_held"``: Newmark with the torque held over the step
  (rt_ident.axis.plant ``integrator="newmark"``): N = dt b.

``c`` (real 4-vector) is the exact leakage of a window that is not periodic: the DFT
of x_k+1 over a window of N samples is z (X + x_N - x_0).
Derivatives are w.r.t. the log-parameters ``theta = log [I1, I2, B, K]``.
"""

from __future__ import annotations

import math

import numpy as np

from rt_ident.errors import ConfigError

HOLDS: tuple[str, ...] = ("zoh", "tustin", "tustin_held")
POS = [0, 2]                      # theta1, theta2 inside an Eq. (8) state
_TAYLOR_TERMS = 18                # with ||X / 2^s|| <= 1/2: truncation ~ 0.5^19 / 19! ~ 1e-23


def check_hold(hold: str) -> str:
    """Canonical hold name ("newmark" is an alias of "tustin"); ConfigError otherwise."""
    key = str(hold).strip().lower()
    if key == "newmark":
        key = "tustin"
    if key not in HOLDS:
        raise ConfigError("hold", f"unknown hold {hold!r}; valid: {', '.join(HOLDS)}")
    return key


def state_matrices(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A, b of Eq. (8) (input +1/I1) for p = [I1, I2, B, K], and dA (4,4,4), db (4,4) w.r.t. log p."""
    I1, I2, B, K = p
    k1, b1, k2, b2 = K / I1, B / I1, K / I2, B / I2
    A = np.array([[0, 1, 0, 0], [-k1, -b1, k1, b1], [0, 0, 0, 1], [k2, b2, -k2, -b2]], float)
    b = np.array([0.0, 1.0 / I1, 0.0, 0.0])
    dA = np.zeros((4, 4, 4))
    db = np.zeros((4, 4))
    dA[0, 1] = -A[1]                  # row omega1 scales as 1/I1
    db[0, 1] = -b[1]
    dA[1, 3] = -A[3]                  # row omega2 scales as 1/I2
    dA[2, 1] = [0, -b1, 0, b1]        # B terms
    dA[2, 3] = [0, b2, 0, -b2]
    dA[3, 1] = [-k1, 0, k1, 0]        # K terms
    dA[3, 3] = [k2, 0, -k2, 0]
    return A, b, dA, db


def expm_frechet_small(X: np.ndarray, Es: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
    """expm(X) and its Frechet derivatives L(X, E_i) for a small, balanced matrix.

    Scaling and squaring with a Taylor polynomial: T_k = T_k-1 Y / k, dT_k = (dT_k-1 Y + T_k-1 F)/k
    for Y = X/2^s, F = E/2^s, then s squarings exp(2Y) = exp(Y)^2, L <- L exp(Y) + exp(Y) L.
    Written out (instead of scipy.linalg.expm on a block matrix) because it stays in tiny
    matmuls: scipy's LU solve on a 25x25 block goes multi-threaded and is 20x slower on a
    busy 2-core machine. Agrees with scipy.linalg.expm / expm_frechet to ~1e-14 (tests).
    """
    norm = float(np.max(np.sum(np.abs(X), axis=0)))
    s = max(0, int(math.ceil(math.log2(norm / 0.5)))) if norm > 0.5 else 0
    Y = X / 2.0**s
    P = np.eye(X.shape[0]) + Y
    T = Y.copy()
    dP = dT = None
    if Es is not None:
        F = Es / 2.0**s
        dT = F.copy()
        dP = F.copy()
    for k in range(2, _TAYLOR_TERMS + 1):
        if dT is not None and dP is not None:
            dT = (dT @ Y + T @ F) / k
            dP = dP + dT
        T = T @ Y / k
        P = P + T
    for _ in range(s):
        if dP is not None:
            dP = dP @ P + P @ dP
        P = P @ P
    return P, dP


def hold_model(theta: np.ndarray, z: np.ndarray, dt: float, hold: str, derivs: bool = True
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """M (H,4,4), N (H,4) of ``M X = N T + z c`` and dM (4,H,4,4), dN (4,H,4) w.r.t. log p."""
    A, b, dA, db = state_matrices(np.exp(theta))
    H = z.size
    eye = np.eye(4)
    if hold == "zoh":
        # balance: angles, velocities * dt and torque * b1 dt^2 all O(1)
        D = np.array([1.0, dt, 1.0, dt, b[1] * dt * dt])
        X = np.zeros((5, 5))
        X[:4, :4], X[:4, 4] = A * dt, b * dt
        Es = None
        if derivs:
            Es = np.zeros((4, 5, 5))
            Es[:, :4, :4], Es[:, :4, 4] = dA * dt, db * dt
            Es = Es * D[:, None] / D[None, :]
        E, dE = expm_frechet_small(X * D[:, None] / D[None, :], Es)
        E = E * D[None, :] / D[:, None]
        M = z[:, None, None] * eye - E[:4, :4]
        N = np.broadcast_to(E[:4, 4], (H, 4))
        if dE is None:
            return M, N, None, None
        dE = dE * D[None, None, :] / D[None, :, None]
        return (M, N, np.broadcast_to(-dE[:, None, :4, :4], (4, H, 4, 4)),
                np.broadcast_to(dE[:, None, :4, 4], (4, H, 4)))
    h = 0.5 * dt
    zp = (z + 1.0)[:, None]
    M = (z - 1.0)[:, None, None] * eye - h * zp[:, :, None] * A
    dM = -h * zp[None, :, :, None] * dA[:, None] if derivs else None
    if hold == "tustin":
        N, dN = h * zp * b, (h * zp[None] * db[:, None] if derivs else None)
    else:  # tustin_held: the torque held over the step enters as dt b T_k
        N = np.broadcast_to(dt * b, (H, 4))
        dN = np.broadcast_to(dt * db[:, None], (4, H, 4)) if derivs else None
    return M, N, dM, dN


def frequency_response(theta: np.ndarray, z: np.ndarray, dt: float, hold: str) -> np.ndarray:
    """(H, 2) exact sampled frequency responses T -> (theta1, theta2) at the points z."""
    M, N, _, _ = hold_model(theta, z, dt, hold, derivs=False)
    return np.linalg.solve(M, N[..., None])[:, POS, 0]
