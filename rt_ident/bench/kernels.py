"""``rt-ident bench``: our compiled kernels against peers, in one run, on the same data.

Every ``bench_*`` function is pure: it builds its data from a seed, times each contender
``repeats`` times after one warm-up call (numba compiles or loads its cache there, padasip and
filterpy import there) and returns a plain dict (medians of the repeats, rates, ratios, and the
answer's distance to a reference so that speed is never bought with wrong answers).

* :func:`bench_rls` - RLS, 5 regressors x 4 outputs (the paper's Eq. 9 shape): ours per sample
  (``update``) and per block (``update_block``, UD and covariance forms) against padasip
  ``FilterRLS`` (one filter per output, mu = 1), filterpy ``KalmanFilter`` as a parameter
  estimator (4 filters of 5 states, F = I, Q = 0, R = 1: the same recursion), a plain numpy RLS
  and numpy ``lstsq`` on the whole batch. Peers run on the first rows of the same data.
* :func:`bench_sim` - Newmark and ZOH simulation steps/s: ours (the whole ``simulate`` call a
  user makes, the same call writing into the arrays of an earlier result (``out=``), the compiled
  trajectory kernel alone and the bare recursion alone) against the interpreted reference loop
  and ``scipy.signal.lsim`` / ``dlsim`` on the same system and torque; also the sim backend's plant.
* :func:`bench_ls` - batch LS (Eq. 10) on the paper's Euler regressor: ours against numpy.
* :mod:`rt_ident.bench.loop` - the loop end to end (subprocesses), see there.

Timings are wall-clock medians on a possibly shared machine: compare ratios from the same
run, not absolute numbers across runs.
"""

from __future__ import annotations

import logging
import os
import platform
import sys
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from rich.progress import Progress

log = logging.getLogger(__name__)

__all__ = ["bench_ls", "bench_main", "bench_rls", "bench_sim", "machine_info"]

PAPER_DT = 2.9481e-5  # Table 2, N = 512, k = 10


# --------------------------------------------------------------------------- helpers
def _time(fn: Callable[[], Any], repeats: int) -> dict[str, float]:
    """One warm-up call, then ``repeats`` timed calls: median and min in seconds."""
    fn()
    runs = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        fn()
        runs.append(time.perf_counter() - t0)
    return {"median_s": float(np.median(runs)), "min_s": float(min(runs))}


def _rel_diff(a: np.ndarray, ref: np.ndarray) -> float:
    """max |a - ref| / max |ref|."""
    return float(np.max(np.abs(np.asarray(a) - ref)) / np.max(np.abs(ref)))


def _row(name: str, n: int, timing: dict[str, float], diff: float | None = None, **extra: Any) -> dict[str, Any]:
    t = timing["median_s"]
    return {"name": name, "n": int(n), "median_s": t, "min_s": timing["min_s"], "per_s": n / t,
            "ns_per_item": 1e9 * t / n, "rel_diff": diff, **extra}


def machine_info() -> dict[str, Any]:
    """CPU model, cores, load and library versions of this machine."""
    import numba
    import scipy

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    affinity: int | None
    try:
        affinity = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        affinity = os.cpu_count()
    return {"cpu": cpu, "cores": os.cpu_count(), "cores_usable": affinity,
            "load_avg_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
            "python": platform.python_version(), "numpy": np.__version__, "numba": numba.__version__,
            "scipy": scipy.__version__, "platform": platform.platform(),
            "blas_threads": os.environ.get("OPENBLAS_NUM_THREADS", "default")}


# --------------------------------------------------------------------------- RLS
def rls_data(m: int, n: int = 5, q: int = 4, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Regressor (m, n) with unequal column scales and targets (m, q) = Phi theta + noise."""
    rng = np.random.default_rng(seed)
    Phi = rng.standard_normal((m, n)) * np.linspace(0.5, 3.0, n)
    Y = Phi @ rng.standard_normal((n, q)) + 0.05 * rng.standard_normal((m, q))
    return Phi, Y


def numpy_rls(Phi: np.ndarray, Y: np.ndarray, p0: float) -> np.ndarray:
    """Plain numpy RLS (Eqs. 14-16, covariance form, one P for all outputs), one sample at a time."""
    n, q = Phi.shape[1], Y.shape[1]
    P = p0 * np.eye(n)
    theta = np.zeros((n, q))
    for phi, y in zip(Phi, Y):
        v = P @ phi
        k = v / (1.0 + phi @ v)                       # Eq. (15)
        theta += np.outer(k, y - phi @ theta)         # Eq. (14)
        P -= np.outer(k, v)                           # Eq. (16)
    return theta


def padasip_rls(Phi: np.ndarray, Y: np.ndarray, p0: float) -> np.ndarray:
    """padasip FilterRLS, one filter per output (mu = 1: no forgetting; R0 = p0 I)."""
    import padasip

    cols = []
    for c in range(Y.shape[1]):
        f = padasip.filters.FilterRLS(Phi.shape[1], mu=1.0, eps=1.0 / p0, w="zeros")
        f.run(Y[:, c], Phi)
        cols.append(f.w.copy())
    return np.column_stack(cols)


def filterpy_rls(Phi: np.ndarray, Y: np.ndarray, p0: float) -> np.ndarray:
    """filterpy KalmanFilter as a parameter estimator: 4 filters of 5 states, F = I, Q = 0, R = 1.

    With a constant state and unit measurement noise the Kalman update is exactly RLS (predict
    is the identity here, so it is not called: this favours the peer).
    """
    from filterpy.kalman import KalmanFilter

    n, q = Phi.shape[1], Y.shape[1]
    kfs = []
    for _ in range(q):
        kf = KalmanFilter(dim_x=n, dim_z=1)
        kf.x = np.zeros((n, 1))
        kf.P = p0 * np.eye(n)
        kf.R = np.eye(1)
        kf.Q = np.zeros((n, n))
        kfs.append(kf)
    for phi, y in zip(Phi, Y):
        H = phi.reshape(1, n)
        for c in range(q):
            kfs[c].update(np.array([[y[c]]]), H=H)
    return np.column_stack([kf.x[:, 0] for kf in kfs])


def _padasip_version() -> str | None:
    try:
        import padasip
    except ImportError:
        return None
    return str(getattr(padasip, "__version__", "installed"))


def bench_rls(m_block: int = 1_000_000, m_sample: int = 50_000, m_peer: int = 5_000, repeats: int = 5,
              p0: float = 1e6, seed: int = 0) -> dict[str, Any]:
    """RLS 5 x 4: samples/s of ours and of each peer, ratios, and max relative distance to batch LS."""
    from rt_ident.estimators.rls import RecursiveLeastSquares

    Phi, Y = rls_data(max(m_block, m_sample, m_peer), seed=seed)
    ls = {m: np.linalg.lstsq(Phi[:m], Y[:m], rcond=None)[0] for m in {m_block, m_sample, m_peer}}
    rows = []

    for form in ("ud", "covariance"):
        est = RecursiveLeastSquares(5, 4, p0=p0, form=form)

        def block(est: RecursiveLeastSquares = est) -> None:
            est.reset()
            est.update_block(Phi[:m_block], Y[:m_block])

        rows.append(_row(f"ours update_block ({form})", m_block, _time(block, repeats),
                         _rel_diff(est.theta, ls[m_block]), kind="ours", block=True))
    est = RecursiveLeastSquares(5, 4, p0=p0)
    pairs = list(zip(Phi[:m_sample], Y[:m_sample]))   # rows split once: the loop times update() itself

    def per_sample() -> None:
        est.reset()
        upd = est.update
        for phi, y in pairs:
            upd(phi, y)

    rows.append(_row("ours update, per sample (ud)", m_sample, _time(per_sample, repeats),
                     _rel_diff(est.theta, ls[m_sample]), kind="ours", block=False))
    peer_reps = max(1, min(repeats, 3))
    out: dict[str, Any] = {"shape": [5, 4], "p0": p0, "padasip": _padasip_version()}
    box: dict[str, np.ndarray] = {}
    peers: list[tuple[str, Callable[[], np.ndarray]]] = [
        ("numpy RLS, per sample", lambda: numpy_rls(Phi[:m_peer], Y[:m_peer], p0)),
        ("filterpy KalmanFilter x4, per sample", lambda: filterpy_rls(Phi[:m_peer], Y[:m_peer], p0)),
    ]
    if out["padasip"] is not None:
        peers.insert(0, ("padasip FilterRLS x4, per sample", lambda: padasip_rls(Phi[:m_peer], Y[:m_peer], p0)))
    else:
        log.warning("padasip is not installed (pip install -e '.[bench]'): that peer is skipped")
    for name, fn in peers:
        def store(fn: Callable[[], np.ndarray] = fn, name: str = name) -> None:
            box[name] = fn()
        timing = _time(store, peer_reps)
        rows.append(_row(name, m_peer, timing, _rel_diff(box[name], ls[m_peer]), kind="peer", block=False))
    timing = _time(lambda: box.__setitem__("lstsq", np.linalg.lstsq(Phi[:m_block], Y[:m_block], rcond=None)[0]),
                   repeats)
    rows.append(_row("numpy lstsq, whole batch", m_block, timing, 0.0, kind="peer", block=True))
    ours_block = rows[0]["per_s"]
    ours_sample = next(r for r in rows if r["name"].startswith("ours update,"))["per_s"]
    for r in rows:
        r["ours_block_x"] = ours_block / r["per_s"]
        r["ours_update_x"] = ours_sample / r["per_s"]
    out["rows"] = rows
    pad = next((r for r in rows if r["name"].startswith("padasip")), None)
    out["targets"] = {
        "block >= 20 M samples/s": ours_block >= 20e6,
        "block >= 150x padasip": None if pad is None else pad["ours_block_x"] >= 150.0,
        "update <= 2 us": 1.0 / ours_sample <= 2e-6,
        "all within 1e-6 of batch LS": all(r["rel_diff"] <= 1e-6 for r in rows),
    }
    return out


# --------------------------------------------------------------------------- simulation
def _time_interleaved(fns: dict[str, Callable[[], Any]], repeats: int) -> dict[str, dict[str, float]]:
    """:func:`_time` for several contenders run round-robin (one warm-up each), so that a noisy
    phase of a shared machine hits all of them alike and their ratios stay meaningful."""
    for fn in fns.values():
        fn()
    runs: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(max(1, repeats)):
        for k, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            runs[k].append(time.perf_counter() - t0)
    return {k: {"median_s": float(np.median(v)), "min_s": float(min(v))} for k, v in runs.items()}


def bench_sim(n_steps: int = 1_000_000, n_peer: int = 50_000, repeats: int = 5) -> dict[str, Any]:
    """Newmark and ZOH steps/s: ours vs the interpreted loop and scipy lsim/dlsim (same system, torque).

    For each of Newmark and ZOH, four rows of ours, from what a user gets to the bare loop:
    ``simulate()`` (the whole public call: validation, set-up, allocation of the result, the
    kernel), ``simulate(out=...)`` (the same call reusing an earlier result's arrays), the compiled
    trajectory kernel alone (recursion and every output in one pass, outputs preallocated) and the
    compiled recursion alone (the extended state only), timed round-robin. ``rates`` sums them up
    per integrator.
    """
    import scipy.signal

    from rt_ident.axis.integrators import Newmark, ZeroOrderHold, zoh_matrices
    from rt_ident.axis.kernels import linear_recursion, trajectory_recursion
    from rt_ident.axis.model import state_space
    from rt_ident.axis.params import thomson_x
    from rt_ident.axis.plant import HoldController, PlantSimulator

    p, dt = thomson_x(), PAPER_DT
    u = 0.3 * np.sin(2 * np.pi * np.arange(n_steps) / 512.0) * np.cos(2 * np.pi * np.arange(n_steps) / 97.0)
    A, b = state_space(p)
    Phi, Gam = zoh_matrices(p, dt)
    up = u[:n_peer]
    t_peer = np.arange(n_peer) * dt
    ref_dlsim = scipy.signal.dlsim((Phi, Gam[:, None], np.eye(4), np.zeros((4, 1)), dt), up)[1]
    peer_reps = max(1, min(repeats, 3))
    rows = []
    rates: dict[str, dict[str, float]] = {}
    for integ in (Newmark(), ZeroOrderHold()):
        name = integ.name
        box: dict[str, Any] = {"full": integ.simulate(p, u, dt)}
        out = integ.simulate(p, u, dt)
        S, G0, G1 = integ.recursion_matrices(p, dt)
        z0 = np.zeros(integ.nz)   # start at rest; u[0] = 0, so the Newmark start-up acceleration is 0 too
        par = np.array([p.B, p.K, p.I1, p.I2])
        Z = np.zeros((n_steps, integ.nz))
        tm = _time_interleaved({
            "full": lambda: box.__setitem__("full", integ.simulate(p, u, dt)),
            "reuse": lambda: integ.simulate(p, u, dt, out=out),
            "kernel": lambda: trajectory_recursion(S, G0, G1, u, z0, 0, dt, par, out.t, out.theta, out.omega,
                                                   out.alpha, out.torque),
            "recursion": lambda: linear_recursion(S, G0, G1, u, Z, 0)}, repeats)
        full = _row(f"ours {name} simulate()", n_steps, tm["full"], None, kind="ours", integrator=name)
        diff = _rel_diff(out.states(), box["full"].states())
        reuse = _row(f"ours {name} simulate(out=...)", n_steps, tm["reuse"], diff, kind="ours", integrator=name)
        kernel = _row(f"ours {name} trajectory kernel (outputs preallocated)", n_steps, tm["kernel"], diff,
                      kind="ours", integrator=name)
        recursion = _row(f"ours {name} compiled recursion", n_steps, tm["recursion"], None, kind="ours",
                         integrator=name)
        rows += [full, reuse, kernel, recursion]
        ours = box["full"].states()[:n_peer]
        rows.append(_row(f"{name} interpreted loop (compiled=False)", n_peer,
                         _time(lambda: box.__setitem__("py", integ.simulate(p, up, dt, compiled=False)), peer_reps),
                         _rel_diff(box["py"].states(), ours), kind="peer", integrator=name))
        rates[name] = {"simulate_steps_per_s": full["per_s"], "simulate_out_steps_per_s": reuse["per_s"],
                       "kernel_steps_per_s": kernel["per_s"], "recursion_steps_per_s": recursion["per_s"],
                       "simulate_over_kernel": full["per_s"] / kernel["per_s"]}
    xs = ZeroOrderHold().simulate(p, up, dt).states()
    box2: dict[str, Any] = {}
    rows.append(_row("scipy.signal.dlsim (ZOH model)", n_peer,
                     _time(lambda: box2.__setitem__("d", scipy.signal.dlsim(
                         (Phi, Gam[:, None], np.eye(4), np.zeros((4, 1)), dt), up)[1]), peer_reps),
                     _rel_diff(xs, ref_dlsim), kind="peer", integrator="zoh"))
    rows.append(_row("scipy.signal.lsim (interp=False)", n_peer,
                     _time(lambda: box2.__setitem__("c", scipy.signal.lsim(
                         (A, b[:, None], np.eye(4), np.zeros((4, 1))), up, t_peer, interp=False)[2]), peer_reps),
                     _rel_diff(xs, box2["c"]), kind="peer", integrator="zoh"))
    plant = PlantSimulator(p, dt, controller=HoldController(), torque_limit=1.0)
    rows.append(_row("sim backend plant step_block (ZOH, sensors, hold loop)", n_steps,
                     _time(lambda: plant.step_block(u), repeats), None, kind="ours", integrator="zoh"))
    from rt_ident.axis.friction import thomson_friction

    plant_f = PlantSimulator(p, dt, controller=HoldController(), torque_limit=1.0, friction=thomson_friction())
    rows.append(_row("the same with THOMSON friction (Karnopp stick-slip, Stribeck)", n_steps,
                     _time(lambda: plant_f.step_block(u), repeats), None, kind="friction", integrator="zoh"))
    best = {name: max(r["per_s"] for r in rows if r["kind"] == "ours" and r["integrator"] == name)
            for name in ("newmark", "zoh")}
    for r in rows:   # how many times faster our best Newmark / ZOH path is than this row
        r["newmark_x"] = best["newmark"] / r["per_s"]
        r["zoh_x"] = best["zoh"] / r["per_s"]
    return {"dt": dt, "rows": rows, "rates": rates,
            "targets": {"newmark kernel >= 20 M steps/s": rates["newmark"]["recursion_steps_per_s"] >= 20e6,
                        "zoh kernel >= 20 M steps/s": rates["zoh"]["recursion_steps_per_s"] >= 20e6,
                        "newmark simulate() >= 20 M steps/s": rates["newmark"]["simulate_steps_per_s"] >= 20e6,
                        "zoh simulate() >= 20 M steps/s": rates["zoh"]["simulate_steps_per_s"] >= 20e6}}


# --------------------------------------------------------------------------- batch LS
def bench_ls(periods: int = 40, repeats: int = 7) -> dict[str, Any]:
    """Eq. (10) on the paper's Euler regressor (Newmark response to a Schroeder multisine)."""
    from rt_ident.axis.excitation import schroeder_multisine
    from rt_ident.axis.integrators import Newmark
    from rt_ident.axis.params import thomson_x
    from rt_ident.estimators.ls import lstsq
    from rt_ident.estimators.paper import euler_regression

    torque = schroeder_multisine(512, (1, 20), peak=0.3).at(np.arange(512 * periods))
    A, b = euler_regression(Newmark().simulate(thomson_x(), torque, PAPER_DT).states(), torque)
    box: dict[str, Any] = {}
    t_ours = _time(lambda: box.__setitem__("ours", lstsq(A, b)), repeats)
    t_np = _time(lambda: box.__setitem__("np", np.linalg.lstsq(A, b, rcond=None)[0]), repeats)
    ratio = t_ours["median_s"] / t_np["median_s"]
    diff = _rel_diff(box["ours"].theta, box["np"])
    return {"rows": [_row("ours lstsq (scaled pivoted QR)", A.shape[0], t_ours, diff),
                     _row("numpy lstsq (SVD, gelsd)", A.shape[0], t_np, 0.0)],
            "shape": list(A.shape), "cond_scaled": box["ours"].cond, "time_ratio_ours_over_numpy": ratio,
            "targets": {"ours <= 2x numpy lstsq": ratio <= 2.0}}


# --------------------------------------------------------------------------- main
def bench_main(json_out: bool, quick: bool, loop_seconds: float, repeats: int,
               loop_rates: tuple[int, ...] | None = None) -> dict[str, Any]:
    """Run every benchmark, print a rich table (or JSON with ``json_out``) on stdout, return the dict.

    ``quick``: a smoke run of every table: small data, 2 repeats, one loop trial of at most 2 s at
    34 k samples/s with .rrd streaming (the figures are indicative only). ``loop_seconds`` <= 0 skips
    the end-to-end loop search; ``loop_rates`` replaces the rates it tries (samples/s, ascending).
    Progress goes to stderr.
    """
    from rt_ident.bench.loop import bench_loop
    from rt_ident.bench.report import print_report, to_json

    sizes = (dict(m_block=200_000, m_sample=10_000, m_peer=1_000) if quick
             else dict(m_block=1_000_000, m_sample=50_000, m_peer=5_000))
    steps = (dict(n_steps=200_000, n_peer=10_000) if quick else dict(n_steps=1_000_000, n_peer=50_000))
    trial = min(loop_seconds, 2.0) if quick else loop_seconds
    loop_kw: dict[str, Any] = {"rates": tuple(loop_rates)} if loop_rates else {}
    if quick:
        repeats = min(repeats, 2)
        loop_kw = {"rates": tuple(loop_rates) if loop_rates else (34_000,), "sinks": ("rrd",), "retries": 0}
    out: dict[str, Any] = {"machine": machine_info(), "quick": quick, "repeats": repeats,
                           "command": " ".join([os.path.basename(sys.argv[0] or "python"), *sys.argv[1:]])}
    with _progress() as prog:
        plain = not prog.console.is_terminal   # no live bar (stderr redirected): one line per stage

        def stage(desc: str, completed: float) -> None:
            prog.update(task, description=desc, completed=completed)
            if plain:
                prog.console.print(f"[{time.strftime('%H:%M:%S')}] {desc}", highlight=False)

        task = prog.add_task("", total=4 if trial > 0 else 3)
        stage("RLS 5x4 vs peers", 0)
        out["rls"] = bench_rls(repeats=repeats, **sizes)
        stage("simulation vs peers", 1)
        out["sim"] = bench_sim(repeats=repeats, **steps)
        stage("batch LS vs numpy", 2)
        out["ls"] = bench_ls(repeats=max(repeats, 5))
        if trial > 0:
            out["loop"] = bench_loop(trial, **loop_kw, progress=lambda desc, frac: stage(desc, 3 + frac))
        else:
            out["loop"] = {"skipped": True}
    if json_out:
        sys.stdout.write(to_json(out) + "\n")
    else:
        print_report(out)
    return out


def _progress() -> Progress:
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(),
                    console=Console(stderr=True), transient=True)
