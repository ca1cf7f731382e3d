"""Compiled per-sample loops of the simulation layer.

Each kernel is written once as a plain Python function (the *reference path*,
run by the interpreter) and compiled with ``numba.njit(cache=True)`` (the fast
path). Both see exactly the same source, so they differ only by the
floating-point contraction numba may choose; tests check agreement to 1e-12.

No kernel allocates an output: callers pass every output array (trajectory_recursion
keeps two (nz,) scratch vectors for the state).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import numba
import numpy as np

from rt_ident.kernel_cache import cache_variant


def _linear_recursion_for(nz: int) -> Callable[..., None]:
    """The loop of :func:`linear_recursion_py` with the state size ``nz`` fixed (a closure constant).

    Compiled, a constant ``nz`` lets LLVM unroll the 4x4 / 6x6 products: 1.6x more steps/s for
    Newmark (nz = 6) than a run-time ``nz``, with bit-identical results.
    """
    def linear_recursion_fixed(S: np.ndarray, G0: np.ndarray, G1: np.ndarray, u: np.ndarray,
                               Z: np.ndarray, k0: int) -> None:
        n = u.shape[0]
        for k in range(k0, n - 1):
            uk = u[k]
            uk1 = u[k + 1]
            for i in range(nz):
                acc = G0[i] * uk + G1[i] * uk1
                for j in range(nz):
                    acc += S[i, j] * Z[k, j]
                Z[k + 1, i] = acc
    return linear_recursion_fixed


def linear_recursion_py(S: np.ndarray, G0: np.ndarray, G1: np.ndarray, u: np.ndarray,
                        Z: np.ndarray, k0: int) -> None:
    """Fill ``Z[k0+1:]`` with ``z[k+1] = S z[k] + G0 u[k] + G1 u[k+1]`` (``Z[k0]`` given).

    Every one-step integrator of :mod:`rt_ident.axis.integrators` applied to the
    linear model of Eq. (3) is such a recursion; the step matrices are built
    once in numpy and only this loop runs per sample.
    """
    _linear_recursion_for(S.shape[0])(S, G0, G1, u, Z, k0)


@functools.cache
def _linear_recursion_nb(nz: int) -> Callable[..., None]:
    """Compiled :func:`_linear_recursion_for` (memoised per nz; nz is part of numba's cache key)."""
    return numba.njit(cache=True)(cache_variant(_linear_recursion_for(nz), f"nz{nz}"))


def linear_recursion(S: np.ndarray, G0: np.ndarray, G1: np.ndarray, u: np.ndarray,
                     Z: np.ndarray, k0: int) -> None:
    """Compiled :func:`linear_recursion_py` (same source, state size specialised)."""
    _linear_recursion_nb(S.shape[0])(S, G0, G1, u, Z, k0)


def _trajectory_recursion_for(nz: int) -> Callable[..., int]:
    """The loop of :func:`trajectory_recursion_py` with the state size ``nz`` fixed (see above)."""
    def trajectory_recursion_fixed(S: np.ndarray, G0: np.ndarray, G1: np.ndarray, u: np.ndarray,
                                   z0: np.ndarray, k0: int, dt: float, par: np.ndarray, t: np.ndarray,
                                   theta: np.ndarray, omega: np.ndarray, alpha: np.ndarray,
                                   torque: np.ndarray) -> int:
        n = u.shape[0]
        B = par[0]
        K = par[1]
        I1 = par[2]
        I2 = par[3]
        zc = np.empty(nz)
        zn = np.empty(nz)
        for j in range(nz):
            zc[j] = z0[j]
        for k in range(k0, n - 1):
            uk = u[k]
            uk1 = u[k + 1]
            if not math.isfinite(uk1):
                return k + 1
            # same arithmetic, in the same order, as linear_recursion_py
            for i in range(nz):
                acc = G0[i] * uk + G1[i] * uk1
                for j in range(nz):
                    acc += S[i, j] * zc[j]
                zn[i] = acc
            r = k + 1
            th1 = zn[0]
            w1 = zn[1]
            th2 = zn[2]
            w2 = zn[3]
            theta[r, 0] = th1
            theta[r, 1] = th2
            omega[r, 0] = w1
            omega[r, 1] = w2
            # Eq. (6) solved for the accelerations, as rt_ident.axis.integrators.equilibrium_acceleration
            coupling = B * (w1 - w2) + K * (th1 - th2)
            alpha[r, 0] = (uk1 - coupling) / I1
            alpha[r, 1] = coupling / I2
            t[r] = r * dt
            torque[r] = uk1
            zc, zn = zn, zc
        return -1
    return trajectory_recursion_fixed


def trajectory_recursion_py(S: np.ndarray, G0: np.ndarray, G1: np.ndarray, u: np.ndarray,
                            z0: np.ndarray, k0: int, dt: float, par: np.ndarray, t: np.ndarray,
                            theta: np.ndarray, omega: np.ndarray, alpha: np.ndarray,
                            torque: np.ndarray) -> int:
    """:func:`linear_recursion_py` fused with the post-processing of a trajectory, in one pass.

    ``z0`` (nz,) is the extended state at sample ``k0``; rows ``k0+1 .. n-1`` of the outputs are
    filled: ``t[k] = k dt``, ``theta[k] = [z1, z3]``, ``omega[k] = [z2, z4]`` (Eq. 8 order),
    ``alpha[k]`` from the equilibrium Eq. (6) with ``u[k]`` (``par = [B, K, I1, I2]``) and
    ``torque[k] = u[k]``. No (n, nz) state history is kept: only the outputs are written.
    Stops at the first non-finite ``u[k]`` (``k > k0``) and returns ``k``; returns -1 when done.
    """
    return _trajectory_recursion_for(S.shape[0])(S, G0, G1, u, z0, k0, dt, par, t, theta, omega, alpha, torque)


@functools.cache
def _trajectory_recursion_nb(nz: int) -> Callable[..., int]:
    """Compiled :func:`_trajectory_recursion_for` (memoised per nz)."""
    return numba.njit(cache=True)(cache_variant(_trajectory_recursion_for(nz), f"nz{nz}"))


def trajectory_recursion(S: np.ndarray, G0: np.ndarray, G1: np.ndarray, u: np.ndarray,
                         z0: np.ndarray, k0: int, dt: float, par: np.ndarray, t: np.ndarray,
                         theta: np.ndarray, omega: np.ndarray, alpha: np.ndarray,
                         torque: np.ndarray) -> int:
    """Compiled :func:`trajectory_recursion_py` (same source, state size specialised)."""
    return _trajectory_recursion_nb(S.shape[0])(S, G0, G1, u, z0, k0, dt, par, t, theta, omega, alpha, torque)


def plant_block_py(Phi: np.ndarray, Gam: np.ndarray, x: np.ndarray, ctrl: np.ndarray,
                   cmd: np.ndarray, noise: np.ndarray, par: np.ndarray,
                   th1_out: np.ndarray, th2_out: np.ndarray, applied_out: np.ndarray,
                   meas_out: np.ndarray, states_out: np.ndarray) -> int:
    """Advance the sampled closed-loop plant by ``len(cmd)`` samples, in place.

    x     : (4,) true state [theta1, omega1, theta2, omega2] at the current sample (updated)
    ctrl  : (4,) carried controller state [previous measured theta1, filtered velocity,
            has-previous flag (0/1), travel-exceeded flag (0/1)] (updated)
    noise : (n, 4) unit normal draws [angle1, angle2, torque meas, torque process] or (0, 4)
    par   : (15,) [q1, res, lead, ctrl_on, kp, kd, ref, beta, limit,
                   s_angle, s_meas, s_proc, travel_lo, travel_hi, 1/dt]

    Per sample: measure (true -> noise -> quantize), PD on the measured motor
    angle (velocity from a first-order filtered backward difference), add the
    command, saturate, add process noise, hold over the sample (x <- Phi x + Gam T).
    Returns -1, or the index of the first non-finite command (nothing is advanced then).
    """
    n = cmd.shape[0]
    for k in range(n):
        if not math.isfinite(cmd[k]):
            return k
    q1 = par[0]
    res = par[1]
    lead = par[2]
    ctrl_on = par[3] != 0.0
    kp = par[4]
    kd = par[5]
    ref = par[6]
    beta = par[7]
    limit = par[8]
    s_ang = par[9]
    s_meas = par[10]
    s_proc = par[11]
    lo = par[12]
    hi = par[13]
    noisy = noise.shape[0] > 0
    inv_dt = par[14]
    for k in range(n):
        th1 = x[0]
        th2 = x[2]
        if noisy:
            th1 += s_ang * noise[k, 0]
            th2 += s_ang * noise[k, 1]
        if q1 > 0.0:
            th1 = math.floor(th1 / q1 + 0.5) * q1
        if res > 0.0:
            th2 = math.floor(lead * th2 / res + 0.5) * res / lead
        torque = cmd[k]
        if ctrl_on:
            if ctrl[2] == 0.0:
                ctrl[0] = th1
                ctrl[2] = 1.0
            # first-order low-pass of the backward difference: vf += beta ((th1 - prev)/dt - vf)
            vraw = (th1 - ctrl[0]) * inv_dt
            ctrl[1] += beta * (vraw - ctrl[1])
            ctrl[0] = th1
            torque += kp * (ref - th1) - kd * ctrl[1]
        if torque > limit:
            torque = limit
        elif torque < -limit:
            torque = -limit
        if noisy:
            torque += s_proc * noise[k, 3]
            meas = torque + s_meas * noise[k, 2]
        else:
            meas = torque
        xpos = lead * x[2]
        if xpos < lo or xpos > hi:
            ctrl[3] = 1.0
        th1_out[k] = th1
        th2_out[k] = th2
        applied_out[k] = torque
        meas_out[k] = meas
        for i in range(4):
            states_out[k, i] = x[i]
        x0 = x[0]
        x1 = x[1]
        x2 = x[2]
        x3 = x[3]
        for i in range(4):
            x[i] = Phi[i, 0] * x0 + Phi[i, 1] * x1 + Phi[i, 2] * x2 + Phi[i, 3] * x3 + Gam[i] * torque
    return -1


plant_block = numba.njit(cache=True)(plant_block_py)


def plant_block_friction_py(Phi: np.ndarray, Gam: np.ndarray, x: np.ndarray, ctrl: np.ndarray,
                            cmd: np.ndarray, noise: np.ndarray, par: np.ndarray, fpar: np.ndarray,
                            fstate: np.ndarray, th1_out: np.ndarray, th2_out: np.ndarray,
                            applied_out: np.ndarray, meas_out: np.ndarray, states_out: np.ndarray) -> int:
    """:func:`plant_block_py` with friction to ground and backlash (:mod:`rt_ident.axis.friction`).

    Phi (2, 4, 4), Gam (2, 4, 2): ZOH step matrices with two inputs (torque on body 1, on body 2),
    viscous friction included; index 0 in contact, 1 inside the backlash gap.
    fpar  : (10,) [Fc1, Fs1, vs1, Fc2, Fs2, vs2, backlash b, K, B, stick_window]
    fstate: (2,) stuck flags of body 1 and 2 (carried between blocks)

    Measurement, hold loop, saturation and noise are those of :func:`plant_block_py`. Physics per
    sample (Karnopp stick-slip, held over the sample like the torque): the coupling torque
    c = K dz(th1 - th2) + B (w1 - w2) (dead zone of width b; no coupling inside the gap); the
    non-friction torques N1 = T - c, N2 = c; a body that is stuck, or whose velocity is within the
    window, sticks when |N| <= Fs (friction = N, velocity 0, position pinned after the step) and
    else breaks away with friction Fs sign(N); a sliding body gets sign(v) (Fc + (Fs - Fc)
    exp(-(v/vs)^2)); a velocity that crosses zero within the sample is stopped there.
    """
    n = cmd.shape[0]
    for k in range(n):
        if not math.isfinite(cmd[k]):
            return k
    q1 = par[0]
    res = par[1]
    lead = par[2]
    ctrl_on = par[3] != 0.0
    kp = par[4]
    kd = par[5]
    ref = par[6]
    beta = par[7]
    limit = par[8]
    s_ang = par[9]
    s_meas = par[10]
    s_proc = par[11]
    lo = par[12]
    hi = par[13]
    noisy = noise.shape[0] > 0
    inv_dt = par[14]
    Fc1 = fpar[0]
    Fs1 = fpar[1]
    vs1 = fpar[2]
    Fc2 = fpar[3]
    Fs2 = fpar[4]
    vs2 = fpar[5]
    half = 0.5 * fpar[6]
    Kc = fpar[7]
    Bc = fpar[8]
    win = fpar[9]
    on1 = Fs1 > 0.0 or Fc1 > 0.0
    on2 = Fs2 > 0.0 or Fc2 > 0.0
    for k in range(n):
        th1 = x[0]
        th2 = x[2]
        if noisy:
            th1 += s_ang * noise[k, 0]
            th2 += s_ang * noise[k, 1]
        if q1 > 0.0:
            th1 = math.floor(th1 / q1 + 0.5) * q1
        if res > 0.0:
            th2 = math.floor(lead * th2 / res + 0.5) * res / lead
        torque = cmd[k]
        if ctrl_on:
            if ctrl[2] == 0.0:
                ctrl[0] = th1
                ctrl[2] = 1.0
            vraw = (th1 - ctrl[0]) * inv_dt
            ctrl[1] += beta * (vraw - ctrl[1])
            ctrl[0] = th1
            torque += kp * (ref - th1) - kd * ctrl[1]
        if torque > limit:
            torque = limit
        elif torque < -limit:
            torque = -limit
        if noisy:
            torque += s_proc * noise[k, 3]
            meas = torque + s_meas * noise[k, 2]
        else:
            meas = torque
        xpos = lead * x[2]
        if xpos < lo or xpos > hi:
            ctrl[3] = 1.0
        th1_out[k] = th1
        th2_out[k] = th2
        applied_out[k] = torque
        meas_out[k] = meas
        for i in range(4):
            states_out[k, i] = x[i]
        # ---- coupling, with the backlash dead zone
        d = x[0] - x[2]
        mode = 0
        e = 0.0                       # constant part of the contact torque on body 1: K s b/2
        if half > 0.0:
            if d > half:
                e = Kc * half
            elif d < -half:
                e = -Kc * half
            else:
                mode = 1
        if mode == 0:
            c = Kc * d - e + Bc * (x[1] - x[3])
        else:
            c = 0.0
        # ---- Karnopp stick-slip on each body
        stick1 = False
        f1 = 0.0
        if on1:
            n1 = torque - c
            w1 = x[1]
            if fstate[0] != 0.0 or abs(w1) <= win:
                if abs(n1) <= Fs1:
                    stick1 = True
                    f1 = n1
                    x[1] = 0.0
                else:
                    f1 = Fs1 if n1 > 0.0 else -Fs1
                    fstate[0] = 0.0
            else:
                m = Fc1
                if vs1 > 0.0 and abs(w1) < 6.0 * vs1:      # beyond 6 vs the Stribeck term is < 3e-16 Fs
                    r = w1 / vs1
                    m += (Fs1 - Fc1) * math.exp(-r * r)
                f1 = m if w1 > 0.0 else -m
        stick2 = False
        f2 = 0.0
        if on2:
            n2 = c
            w2 = x[3]
            if fstate[1] != 0.0 or abs(w2) <= win:
                if abs(n2) <= Fs2:
                    stick2 = True
                    f2 = n2
                    x[3] = 0.0
                else:
                    f2 = Fs2 if n2 > 0.0 else -Fs2
                    fstate[1] = 0.0
            else:
                m = Fc2
                if vs2 > 0.0 and abs(w2) < 6.0 * vs2:      # beyond 6 vs the Stribeck term is < 3e-16 Fs
                    r = w2 / vs2
                    m += (Fs2 - Fc2) * math.exp(-r * r)
                f2 = m if w2 > 0.0 else -m
        u1 = torque - f1 + e
        u2 = -f2 - e
        x0 = x[0]
        x1 = x[1]
        x2 = x[2]
        x3 = x[3]
        for i in range(4):
            x[i] = (Phi[mode, i, 0] * x0 + Phi[mode, i, 1] * x1 + Phi[mode, i, 2] * x2 + Phi[mode, i, 3] * x3
                    + Gam[mode, i, 0] * u1 + Gam[mode, i, 1] * u2)
        if on1:
            if stick1:
                x[0] = x0
                x[1] = 0.0
                fstate[0] = 1.0
            elif x1 * x[1] < 0.0:     # stopped within the sample
                x[1] = 0.0
                fstate[0] = 1.0
        if on2:
            if stick2:
                x[2] = x2
                x[3] = 0.0
                fstate[1] = 1.0
            elif x3 * x[3] < 0.0:
                x[3] = 0.0
                fstate[1] = 1.0
    return -1


plant_block_friction = numba.njit(cache=True)(plant_block_friction_py)


def first_non_finite3_py(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> int:
    """Index of the first sample where any of three equal-length arrays is NaN or infinite, else -1.

    The loop checks every block's angles and torque before they reach the estimators; three numpy
    sums and an isfinite each cost a few microseconds of the tick, this one pass under one.
    """
    for i in range(a.shape[0]):
        if not (math.isfinite(a[i]) and math.isfinite(b[i]) and math.isfinite(c[i])):
            return i
    return -1


first_non_finite3 = numba.njit(cache=True)(first_non_finite3_py)
