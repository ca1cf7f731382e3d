"""Kernels of :mod:`rt_ident.estimators.rls`: one RLS sample in UD form or in covariance form.

Packed state
------------
Each estimator keeps its whole state in one contiguous float64 vector ``S`` (see
:func:`layout`): a header ``[lambda, variant, max_trace, 0]``, the n x n matrix (U of
``P = U D U^T``, or P itself), d = diag(D) (UD form only), theta (n x q) and the kernels'
scratch space. The per-sample entry point therefore takes three arrays, ``(S, phi, y)``:
numba's dispatcher costs ~80 ns per array argument, which dominated a 13-argument call.
The public attributes of the estimator are numpy views into ``S``.

Compiled kernels are specialised per shape: one loop per form (``core``) in which n and q are
compile-time constants (closure constants), so LLVM fully unrolls the 5 x 4 loops, compiled
once and then loaded from numba's on-disk cache. :func:`block_kernel` runs it on the rows of a
block and :func:`update_kernel` on one sample: one sample through either gives bit-identical
results, whether the kernels were just compiled or loaded from the cache. No fast-math flag:
``contract`` (fused multiply-adds) is a little faster, but kernels loaded from the cache then round
differently from those just compiled and from each other; no reassociation (sums keep their order),
and no ``nnan``/``ninf``, which would break the NaN propagation used to reject bad samples.
The plain-numpy references in :mod:`._rls_reference` (``compiled=False``) agree with them to
1e-12 relative (tested).

UD form (Bierman's measurement update). With f = U^T phi, g = D f, a_0 = 1,
a_j = a_{j-1} + f_j g_j (so a_n = 1 + phi^T P phi): ``D - g g^T / a_n = Ut D' Ut^T`` with
``d_j' = d_j a_{j-1}/a_j`` and ``Ut_ij = g_i p_j`` (i < j), ``p_j = -f_j/a_{j-1}``; the new U
is ``U Ut``, i.e. column j gains ``p_j sum_{i<j} g_i U[:, i]``; the gain is ``K = U g / a_n``
(= P phi / (1 + phi^T P phi)). The a_j are formed first so that the n divisions are
independent (they pipeline instead of forming one serial latency chain).

Agee-Turner positive rank-one update (directional forgetting), P + c v v^T with v = P phi,
so U^-1 v = g: ``D + c g g^T = Ut D' Ut^T`` with, for j = n..1, ``d_j' = d_j + c_j g_j^2``,
``Ut_ij = c_j g_j g_i / d_j'``, ``c_{j-1} = c_j d_j / d_j'`` (c_n = c).

Covariance form: every variant is one symmetric rank-one update ``P <- a P - b v v^T`` with
``v = P phi``, ``K = c v`` (the forgetting folded into a, b, c, see :func:`_cov_coeffs`); only
the upper triangle is computed and mirrored, so P is exactly symmetric.

Non-finite samples: the a-priori error ``e = y - theta^T phi`` is non-finite whenever phi or
y holds a NaN/inf (theta is always finite), so testing e and ``phi^T P phi`` suffices.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import numba

from rt_ident.kernel_cache import cache_variant

STANDARD = 0
DIRECTIONAL = 1
BOUNDED_TRACE = 2
VARIANTS: dict[str, int] = {"standard": STANDARD, "directional": DIRECTIONAL, "bounded-trace": BOUNDED_TRACE}
HEADER = 4  # [lambda, variant, max_trace, unused]


def layout(n: int, q: int) -> dict[str, tuple[int, int]]:
    """Offsets ``name -> (start, stop)`` of the packed state vector (see the module docstring)."""
    sizes = (("M", n * n), ("d", n), ("theta", n * q), ("f", n), ("g", n), ("k", n), ("am", n), ("inv", n),
             ("e", q), ("W", n * n))
    out, pos = {}, HEADER
    for name, size in sizes:
        out[name] = (pos, pos + size)
        pos += size
    out["size"] = (0, pos)
    return out


def _offsets(n: int, q: int) -> tuple[int, ...]:
    """Start offsets in S of M (U or P), d, theta, f (v), g, k, am, inv, e, W (see :func:`layout`).

    The kernels index S directly (``U[i, j]`` is ``S[oM + i*n + j]``) rather than through views:
    in numba every view is reference counted, which costs ~0.3 us per single-sample call.
    """
    lay = layout(n, q)
    return tuple(lay[name][0] for name in ("M", "d", "theta", "f", "g", "k", "am", "inv", "e", "W"))


def _fixed_identity(dispatcher: Callable, name: str) -> None:
    """Name the dispatcher the same in every process.

    numba keys a cached closure by its pickled cells (with the dispatchers they call), and a dispatcher
    pickles with a random uuid: the closures over ``core`` (``block``, ``update``) would miss the cache in
    every new process, compile again and add files to it. numba has no public way to set it; where this
    private one is gone, only the cache misses come back.
    """
    try:
        dispatcher._set_uuid(name)  # type: ignore[attr-defined]
    except (AttributeError, AssertionError):
        pass


@numba.njit(inline="always")
def _cov_coeffs(r, trace, lam, variant, max_trace):  # noqa: ANN001, ANN202
    """(a, b, c) of ``P <- a P - b v v^T``, ``K = c v`` for r = phi^T P phi, v = P phi.

    standard / bounded-trace: P_f = s P (s = 1/lam, or smaller so trace(P_f) <= max_trace), then
    Eqs. (15)-(16): K = s v / (1 + s r), P <- s P - s^2 v v^T / (1 + s r).
    directional: P_f = P + c' v v^T, c' = (1-lam)/(lam r), so P_f phi = v/lam, phi^T P_f phi = r/lam;
    then K = v/(lam + r) and P <- P - b v v^T with b = 1/(lam (lam + r)) - c' = (r - (1-lam))/(r (lam + r)).
    """
    if variant == DIRECTIONAL:
        if lam < 1.0 and r > 0.0:
            return 1.0, (r - (1.0 - lam)) / (r * (lam + r)), 1.0 / (lam + r)
        c = 1.0 / (1.0 + r)
        return 1.0, c, c
    s = 1.0 / lam
    if variant == BOUNDED_TRACE and trace * s > max_trace:
        s = max_trace / trace
    c = s / (1.0 + s * r)
    return s, s * c, c


_fixed_identity(_cov_coeffs, "rt_ident.rls.cov_coeffs")


# --------------------------------------------------------------------------- shape-specialised kernels
# Each form has one ``core`` loop on flat arrays (row t of Phi at Phi[t*n:(t+1)*n]); ``block`` (2-D
# inputs) and ``update`` (one sample) both call it. Notation: U[i, j] (or P[i, j]) is S[oM + i*n + j],
# d[j] is S[oD + j], theta[i, c] is S[oT + i*q + c], and f (v in the covariance form), g, k, am
# (a_{j-1}), inv (1/a_j), e, W likewise (scratch). The loop body is written out in ``core`` on
# purpose: passing arrays to a helper per sample (even an inlined one) costs NRT reference
# counting, which doubles the time per sample; reshaping inside ``update`` costs ~0.4 us per call.
def _make_ud(n: int, q: int) -> Callable:
    nq = n * q
    oM, oD, oT, oF, oG, oK, oA, oI, oE, oW = _offsets(n, q)

    @numba.njit(cache=True)
    @functools.partial(cache_variant, tag=f"{n}x{q}")
    def core(S, Phi, Y, m, hist, hpos, record):  # noqa: ANN001, ANN202
        lam = S[0]
        variant = int(S[1])
        max_trace = S[2]
        acc = 0
        H = hist.shape[0] // nq
        for t in range(m):
            x = t * n                          # row t of Phi
            ok = True                          # Eq. (14) bracket: e = y - theta^T phi (non-finite
            for c in range(q):                 # if phi or y is)
                s = Y[t * q + c]
                for i in range(n):
                    s -= S[oT + i * q + c] * Phi[x + i]
                S[oE + c] = s
                ok &= math.isfinite(s)
            if not ok:
                continue
            r = 0.0                            # f = U^T phi, g = D f, r = phi^T P phi
            for j in range(n):
                s = Phi[x + j]
                for i in range(j):
                    s += S[oM + i * n + j] * Phi[x + i]
                S[oF + j] = s
                S[oG + j] = S[oD + j] * s
                r += s * S[oG + j]
            if not math.isfinite(r):
                continue
            # ---- forgetting (time update of P)
            if variant == DIRECTIONAL:
                if lam < 1.0 and r > 0.0:
                    # R <- R - (1-lam) phi phi^T / r  <=>  P <- P + cd (P phi)(P phi)^T, cd = (1-lam)/(lam r):
                    # Agee-Turner; W[:, j] = sum_{i<j} g_i U[:, i] (prefix sums with the old columns)
                    for i in range(n):
                        S[oW + i * n] = 0.0
                    for j in range(1, n):
                        gj = S[oG + j - 1]
                        for i in range(n):
                            S[oW + i * n + j] = S[oW + i * n + j - 1] + gj * S[oM + i * n + j - 1]
                    cj = (1.0 - lam) / (lam * r)
                    for j in range(n - 1, -1, -1):
                        gj = S[oG + j]
                        dn = S[oD + j] + cj * gj * gj
                        coef = cj * gj / dn
                        for i in range(j):
                            S[oM + i * n + j] += coef * S[oW + i * n + j]
                        cj = cj * S[oD + j] / dn
                        S[oD + j] = dn
                    for j in range(n):         # f, g again with the new factors
                        s = Phi[x + j]
                        for i in range(j):
                            s += S[oM + i * n + j] * Phi[x + i]
                        S[oF + j] = s
                        S[oG + j] = S[oD + j] * s
            elif lam < 1.0 or variant == BOUNDED_TRACE:
                sc = 1.0 / lam                 # P <- P / lambda
                if variant == BOUNDED_TRACE:
                    tr = 0.0
                    for j in range(n):
                        s = 1.0
                        for i in range(j):
                            s += S[oM + i * n + j] * S[oM + i * n + j]
                        tr += S[oD + j] * s
                    if tr * sc > max_trace:
                        sc = max_trace / tr
                for j in range(n):
                    S[oD + j] *= sc
                    S[oG + j] *= sc
            # ---- Eqs. (15)-(16), Bierman. a_j first (serial adds), then independent divisions.
            a = 1.0
            for j in range(n):
                S[oA + j] = a                      # a_{j-1}
                a += S[oF + j] * S[oG + j]
                S[oI + j] = a                     # a_j (inverted below)
            for j in range(n):
                S[oI + j] = 1.0 / S[oI + j]
            for i in range(n):
                S[oK + i] = 0.0
            for j in range(n):                 # k accumulates sum_{i<j} g_i U_old[:, i]
                gj = S[oG + j]
                p = -S[oF + j] if j == 0 else -S[oF + j] * S[oI + j - 1]
                S[oD + j] = S[oD + j] * (S[oA + j] * S[oI + j])
                for i in range(j):
                    uij = S[oM + i * n + j]
                    S[oM + i * n + j] = uij + p * S[oK + i]
                    S[oK + i] += gj * uij
                S[oK + j] += gj
            inv_n = S[oI + n - 1]                 # Eq. (15): K = P phi / (1 + phi^T P phi)
            for i in range(n):                 # Eq. (14): theta += K e^T
                ki = S[oK + i] * inv_n
                for c in range(q):
                    S[oT + i * q + c] += ki * S[oE + c]
            acc += 1
            if record:
                h = (hpos % H) * nq
                for i in range(nq):
                    hist[h + i] = S[oT + i]
                hpos += 1
        return acc, hpos

    return core


def _make_cov(n: int, q: int) -> Callable:
    nq = n * q
    oM, oD, oT, oF, oG, oK, oA, oI, oE, oW = _offsets(n, q)

    @numba.njit(cache=True)
    @functools.partial(cache_variant, tag=f"{n}x{q}")
    def core(S, Phi, Y, m, hist, hpos, record):  # noqa: ANN001, ANN202
        lam = S[0]
        variant = int(S[1])
        max_trace = S[2]
        acc = 0
        H = hist.shape[0] // nq
        for t in range(m):
            x = t * n
            ok = True                          # Eq. (14) bracket: e = y - theta^T phi
            for c in range(q):
                s = Y[t * q + c]
                for i in range(n):
                    s -= S[oT + i * q + c] * Phi[x + i]
                S[oE + c] = s
                ok &= math.isfinite(s)
            if not ok:
                continue
            r = 0.0
            for i in range(n):                 # v = P phi, r = phi^T P phi
                s = 0.0
                for j in range(n):
                    s += S[oM + i * n + j] * Phi[x + j]
                S[oF + i] = s
                r += Phi[x + i] * s
            if not math.isfinite(r):
                continue
            trace = 0.0
            if variant == BOUNDED_TRACE:
                for i in range(n):
                    trace += S[oM + i * n + i]
            a, b, cg = _cov_coeffs(r, trace, lam, variant, max_trace)
            for i in range(n):                 # Eq. (14): theta += K e^T with Eq. (15) K = cg P phi
                ki = cg * S[oF + i]
                for c in range(q):
                    S[oT + i * q + c] += ki * S[oE + c]
            if a == 1.0:                       # Eq. (16), symmetric rank-one (upper triangle, mirrored)
                for i in range(n):
                    bvi = b * S[oF + i]
                    for j in range(i, n):
                        pij = S[oM + i * n + j] - bvi * S[oF + j]
                        S[oM + i * n + j] = pij
                        S[oM + j * n + i] = pij
            else:
                for i in range(n):
                    bvi = b * S[oF + i]
                    for j in range(i, n):
                        pij = a * S[oM + i * n + j] - bvi * S[oF + j]
                        S[oM + i * n + j] = pij
                        S[oM + j * n + i] = pij
            acc += 1
            if record:
                h = (hpos % H) * nq
                for i in range(nq):
                    hist[h + i] = S[oT + i]
                hpos += 1
        return acc, hpos

    return core


@functools.cache
def _core(form: str, n: int, q: int) -> Callable:
    core = _make_ud(n, q) if form == "ud" else _make_cov(n, q)
    _fixed_identity(core, f"rt_ident.rls.{form}.{n}x{q}")
    return core


@functools.cache
def block_kernel(form: str, n: int, q: int) -> Callable:
    """``block(S, Phi, Y, hist, hpos, record) -> (accepted, hpos)`` for this form and shape.

    Compiled on first call (or loaded from numba's on-disk cache). Memoised per (form, n, q), a
    compile cache like numba's own; n and q are closure constants and part of numba's cache key.
    """
    core = _core(form, int(n), int(q))

    @numba.njit(cache=True)
    @functools.partial(cache_variant, tag=f"{form}_{n}x{q}")
    def block(S, Phi, Y, hist, hpos, record):  # noqa: ANN001, ANN202
        return core(S, Phi.ravel(), Y.ravel(), Phi.shape[0], hist.ravel(), hpos, record)

    return block


@functools.cache
def update_kernel(form: str, n: int, q: int) -> Callable:
    """``update(S, phi, y) -> bool`` for this form and shape, compiled now for exactly one signature.

    Only C-contiguous writeable float64 vectors are accepted (anything else raises TypeError, and
    the caller converts), so the dispatcher never compiles a new variant inside a real-time loop.
    """
    core = _core(form, int(n), int(q))

    @numba.njit("boolean(float64[::1], float64[::1], float64[::1])", cache=True)
    @functools.partial(cache_variant, tag=f"{form}_{n}x{q}")
    def update(S, phi, y):  # noqa: ANN001, ANN202
        return core(S, phi, y, 1, S[:1], 0, False)[0] == 1   # S[:1]: a history never written

    return update
