"""Offline identification of a recording (``rt-ident identify FILE``).

Recordings made by ``rt-ident run`` carry their metadata (sample period,
excitation period and band, warm-up, method). For a streaming-capable method
the samples are replayed through exactly the code the loop ran, and the final
snapshot is fitted cold: the result equals the loop's final estimate.
Anything else (a CSV with ``t,theta1,theta2,torque`` and no metadata, another
method) goes through the batch estimator registry, which detects the
excitation period from the data when nobody says it.

``model``: ``two-inertia`` (default: everything above), ``two-inertia-friction`` or
``rigid-friction`` (:mod:`rt_ident.estimators.friction`, method ``svf-ls``). ``rigid-friction``
accepts a CSV with one position sensor ``t,theta1,torque`` in the file's own units.
:func:`validate_file` checks an identified model on another recording.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rt_ident.errors import DataError, EstimationError
from rt_ident.estimators.base import IdentData, Identification
from rt_ident.outputs.recording_reader import Recording, iter_parquet_blocks, parquet_metadata
from rt_ident.processes.recorder import read_recording

if TYPE_CHECKING:   # friction (numba, scipy.signal) is imported when a friction model is fitted
    from rt_ident.estimators.friction import FrictionIdentification
    from rt_ident.estimators.streaming import FrequencyStream, PaperStream

REPLAY_CHUNK = 4096


def identify_file(path: str | Path, method: str | None = None, *, period: int | None = None, model: str | None = None,
                  **options: Any) -> tuple[Identification | FrictionIdentification, dict[str, Any]]:
    """Identify the axis from a recording; returns (identification, info about how).

    A finished ``.parquet`` recording replayed through the loop's streaming estimator is read in
    record batches (memory independent of its length); everything else is read whole.
    ``model`` other than ``two-inertia`` (or ``method="svf-ls"``) goes to :func:`identify_model`."""
    if (model is not None and model.strip().lower() != "two-inertia") or (method or "").lower() == "svf-ls":
        return identify_model(path, model or "two-inertia", method, **options)
    meta = parquet_metadata(path)
    if meta is not None and _replayable(meta, method, period, options):
        est, n = _stream_replay(path, meta, method or meta["method"])
        info: dict[str, Any] = {"file": str(path), "source": "parquet", "samples": n, "metadata": True,
                "how": "replay of the loop's streaming estimator (streamed in record batches)"}
        return est, info
    rec = read_recording(path)
    meta = rec.metadata or {}
    method = method or meta.get("method") or _default_method()
    info = {"file": str(path), "source": rec.source, "samples": len(rec), "metadata": bool(meta)}
    ex = meta.get("excitation") or {}
    if (meta.get("sample_period") and ex.get("period_samples") and ex.get("band") and period is None
            and not options and method == meta.get("method")):
        from rt_ident.estimators.streaming import STREAMING_METHODS

        if method in STREAMING_METHODS and method != "paper":
            info["how"] = "replay of the loop's streaming estimator"
            return _replay(rec, meta, method), info
    info["how"] = "batch"
    from rt_ident.estimators.registry import identify

    data = _ident_data(rec, meta.get("sample_period"), period or ex.get("period_samples"))
    return identify(data, method, **options), info


def identify_model(path: str | Path, model: str, method: str | None = None,
                   **options: Any) -> tuple[Identification | FrictionIdentification, dict[str, Any]]:
    """Fit ``model`` (:data:`rt_ident.estimators.friction.MODELS`) to a recording by the batch
    method (default ``svf-ls``, the only one that accepts the friction models)."""
    from rt_ident.errors import ConfigError
    from rt_ident.estimators.base import uniform_dt
    from rt_ident.estimators.friction import NEEDS_THETA2, check_model, fit_friction
    from rt_ident.estimators.registry import METHODS, methods_for_model

    key = check_model(model)
    m = (method or "svf-ls").strip().lower()
    if m not in METHODS:
        raise ConfigError("method", f"unknown method {method!r}; valid: {', '.join(METHODS)}")
    if key not in METHODS[m].models:
        raise ConfigError("model", f"method {m!r} fits {', '.join(METHODS[m].models)} only; model {key!r} "
                          f"needs {' or '.join(methods_for_model(key))}")
    rec = read_recording(path, require_theta2=key in NEEDS_THETA2)
    dt = float((rec.metadata or {}).get("sample_period") or uniform_dt(rec.t))
    info: dict[str, Any] = {"file": str(path), "source": rec.source, "samples": len(rec),
                            "metadata": bool(rec.metadata), "how": f"batch ({m}, model {key})", "model": key}
    if m != "svf-ls":     # a linear-only method on the two-inertia model
        from rt_ident.estimators.registry import identify

        data = _ident_data(rec, (rec.metadata or {}).get("sample_period"))
        return identify(data, m, **options), info
    ident = fit_friction(rec.theta1, rec.torque, dt, model=key, theta2=rec.theta2, **options)
    return ident, info


def _ident_data(rec: Recording, dt: float | None, period: int | None = None) -> IdentData:
    if rec.theta2 is None:     # read with require_theta2: not met here
        raise DataError("theta2: required")
    return IdentData(t=rec.t, theta1=rec.theta1, theta2=rec.theta2, torque=rec.torque, omega1=rec.omega1,
                     omega2=rec.omega2, dt=dt, period=period)


def validate_file(ident: Any, path: str | Path) -> dict[str, Any]:
    """An identified model on *another* recording (``identify --validate OTHER``): the relative error
    of the torque it predicts from that recording's measured motion (and, for ``rigid-friction``,
    of the position an open-loop simulation from its torque gives, which drifts)."""
    from rt_ident.estimators.base import uniform_dt
    from rt_ident.estimators.friction import NEEDS_THETA2, FrictionIdentification, predict_torque, simulate_rigid

    if not isinstance(ident, FrictionIdentification):
        raise EstimationError("--validate needs a model fitted by svf-ls (give --model)")
    rec = read_recording(path, require_theta2=ident.model in NEEDS_THETA2)
    dt = float((rec.metadata or {}).get("sample_period") or uniform_dt(rec.t))
    out: dict[str, Any] = {"file": str(path), "samples": len(rec)}
    out.update(predict_torque(ident, rec.theta1, rec.torque, dt, theta2=rec.theta2))
    if ident.model == "rigid-friction":
        x = simulate_rigid(ident, rec.torque, dt)
        meas = rec.theta1 - rec.theta1[0]
        span = float(np.ptp(meas)) or 1.0
        out["open_loop_position_error_percent_of_span"] = float(100.0 * np.sqrt(np.mean((x - meas) ** 2)) / span)
    return out


def _replayable(meta: dict[str, Any], method: str | None, period: int | None, options: dict) -> bool:
    from rt_ident.estimators.streaming import STREAMING_METHODS

    ex = meta.get("excitation") or {}
    m = method or meta.get("method")
    return bool(meta.get("sample_period") and ex.get("period_samples") and ex.get("band") and period is None
                and not options and m == meta.get("method") and m in STREAMING_METHODS and m != "paper")


def _streaming_estimator(meta: dict[str, Any], method: str) -> FrequencyStream | PaperStream:
    from rt_ident.estimators.streaming import make_streaming

    ex = meta["excitation"]
    lead = float((meta.get("axis") or {}).get("lead", 7.96e-4))
    return make_streaming(method, dt=float(meta["sample_period"]), period=int(ex["period_samples"]),
                          band=tuple(ex["band"]), warmup_periods=int(meta.get("warmup_periods", 2)),
                          forgetting=float(meta.get("forgetting", 1.0)), lead=lead)


def _stream_replay(path: str | Path, meta: dict[str, Any], method: str) -> tuple[Identification, int]:
    est = _streaming_estimator(meta, method)
    n = 0
    for th1, th2, tq, seq in iter_parquet_blocks(path, REPLAY_CHUNK * 16):
        if seq is None:
            seq = np.arange(n, n + th1.shape[0])
        for i in range(0, th1.shape[0], REPLAY_CHUNK):
            s = slice(i, i + REPLAY_CHUNK)
            est.update_block(th1[s], th2[s], tq[s], seq[s])
        n += th1.shape[0]
    if n < 10:
        raise EstimationError(f"{path}: only {n} data rows")
    ident = est.final()
    if ident is None:
        raise EstimationError(f"{method}: the recording holds no complete excitation period after the warm-up")
    return ident, n


def _default_method() -> str:
    from rt_ident.estimators.registry import DEFAULT_METHOD

    return DEFAULT_METHOD


def _replay(rec: Recording, meta: dict[str, Any], method: str) -> Identification:
    if rec.theta2 is None:     # read with require_theta2: not met here
        raise DataError("theta2: required")
    est = _streaming_estimator(meta, method)
    seq = rec.seq if rec.seq is not None else np.arange(len(rec))
    for i in range(0, len(rec), REPLAY_CHUNK):
        s = slice(i, i + REPLAY_CHUNK)
        est.update_block(rec.theta1[s], rec.theta2[s], rec.torque[s], seq[s])
    ident = est.final()
    if ident is None:
        raise EstimationError(f"{method}: the recording holds no complete excitation period after the warm-up")
    return ident


__all__ = ["identify_file", "identify_model", "validate_file"]
