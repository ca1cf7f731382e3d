"""Telemetry: a separate process that streams decimated blocks to rerun.

The real-time loop calls :meth:`TelemetryProcess.publish` with a dict of arrays. ``publish``
decimates it and copies it into a bounded shared-memory ring (:mod:`rt_ident.runtime.shm_ring`: no
feeder thread, no pickling, no system call in the loop's process). It never waits: on a full
ring the block is dropped and counted. A spawned child process owns an
``rr.RecordingStream`` (no global rerun state), coalesces whatever is queued and logs it with
columnar ``send_columns`` only (~70 ns/sample, vs ~30 us per ``rr.log``). Whatever the sink does
(``connect_grpc`` to a missing viewer blocks the logging call), only the child can stall.

Block contract (keys and entity paths: :mod:`rt_ident.runtime.dashboard`)::

    {"t": sample times [s],                      # required
     "theta1", "theta2", "torque_meas", "torque_cmd", "torque_hat": arrays like t,
     "t_tick": tick times [s] (optional),
     "I1", "I2", "B", "K", "wn", "zeta", "lateness_us", "overruns": arrays like t_tick
                                                 # (like t when there is no t_tick)}

Decimation keeps every ``decimation``-th sample of the arrays that follow ``t``, continuous
across blocks; tick-rate arrays that follow ``t_tick`` are sent whole. True values, given once
with :meth:`TelemetryProcess.set_truth`, are drawn as a second series beside each estimate: the
child sends the true value at the first and last time of every batch that holds that estimate
(a horizontal line over the estimate's time span).

Sinks: ``"rrd"`` file (complete after ``close()``, which disconnects the stream); ``"spawn"``
starts ``rerun --bind <bind_ip> --port <port>`` (never 0.0.0.0 unless configured) and connects;
``"connect"`` connects to ``connect_url``; ``"serve"`` hosts a gRPC server with
``GrpcServerSink(bind_ip=bind_ip)``; ``"off"`` starts nothing. The child sets ``CI=1`` (rerun
writes no analytics config) unless ``CI`` is already set.
"""

from __future__ import annotations

import ipaddress
import logging
import math
import multiprocessing as mp
import os
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from rt_ident.errors import ConfigError, DataError
from rt_ident.runtime.dashboard import BLOCK_ENTITIES, CONTROL_ENTITIES, ESTIMATE_KEYS, SERIES_STYLES, truth_path
from rt_ident.runtime.helper_guard import become_helper, start_ignoring_signals
from rt_ident.runtime.shm_ring import MessageRing

log = logging.getLogger(__name__)

SINKS: tuple[str, ...] = ("rrd", "spawn", "connect", "serve", "off")
TICK_KEYS: frozenset[str] = frozenset(ESTIMATE_KEYS + ("lateness_us", "overruns") + tuple(CONTROL_ENTITIES))
_MAX_COALESCE = 256  # blocks merged into one send_columns per entity in the child
_TRUTH = "truth:"    # key prefix of a truth message in the ring
_POLL_S = 0.01       # child: sleep between polls of an empty ring


def default_sink(env: Mapping[str, str] | None = None) -> str:
    """``"spawn"`` when a display is available, else ``"rrd"``."""
    env = os.environ if env is None else env
    return "spawn" if env.get("DISPLAY") or env.get("WAYLAND_DISPLAY") else "rrd"


@dataclass(frozen=True)
class TelemetryConfig:
    """Where telemetry goes and how much of it. Validated on construction (no I/O)."""

    sink: str = "rrd"
    rrd_path: str | None = None
    connect_url: str | None = None
    bind_ip: str = "127.0.0.1"
    decimation: int = 1
    application_id: str = "rt_ident"
    port: int = 9876  # viewer port for "spawn", server port for "serve"
    queue_size: int = 64  # blocks buffered between the loop and the child
    ring_bytes: int = 8 << 20  # and at most this many bytes of them
    flush_timeout: float = 2.0  # child: max wait for rerun to flush at close

    def __post_init__(self) -> None:
        if self.sink not in SINKS:
            raise ConfigError("sink", f"must be one of {', '.join(SINKS)}, got {self.sink!r}")
        if self.sink == "rrd" and not self.rrd_path:
            raise ConfigError("rrd_path", 'required when sink == "rrd"')
        if self.sink == "connect":
            url = self.connect_url or ""
            if not url.startswith(("rerun://", "rerun+http://", "rerun+https://")) or not url.endswith("/proxy"):
                raise ConfigError("connect_url", f"must look like rerun+http://HOST:PORT/proxy, got {url!r}")
        try:
            ipaddress.ip_address(self.bind_ip)
        except ValueError as e:
            raise ConfigError("bind_ip", f"not an IP address: {self.bind_ip!r}") from e
        if isinstance(self.decimation, bool) or not isinstance(self.decimation, int) or self.decimation < 1:
            raise ConfigError("decimation", f"must be an integer >= 1, got {self.decimation!r}")
        if not isinstance(self.port, int) or not 1 <= self.port <= 65535:
            raise ConfigError("port", f"must be in 1..65535, got {self.port!r}")
        if not isinstance(self.queue_size, int) or self.queue_size < 1:
            raise ConfigError("queue_size", f"must be an integer >= 1, got {self.queue_size!r}")
        if isinstance(self.ring_bytes, bool) or not isinstance(self.ring_bytes, int) or self.ring_bytes < 1 << 16:
            raise ConfigError("ring_bytes", f"must be an integer >= 65536, got {self.ring_bytes!r}")
        if not self.application_id:
            raise ConfigError("application_id", "must not be empty")
        if not (math.isfinite(self.flush_timeout) and self.flush_timeout > 0):
            raise ConfigError("flush_timeout", f"must be > 0 s, got {self.flush_timeout!r}")


def viewer_command(cfg: TelemetryConfig) -> list[str]:
    """The command that starts a local viewer bound to ``cfg.bind_ip:cfg.port`` (sink "spawn")."""
    return [sys.executable, "-m", "rerun_cli", "--bind", cfg.bind_ip, "--port", str(cfg.port),
            "--memory-limit", "25%", "--hide-welcome-screen"]


def _local_host(bind_ip: str) -> str:
    return "127.0.0.1" if ipaddress.ip_address(bind_ip).is_unspecified else bind_ip


DEFAULT_PORT = 9876


def serve_port(bind_ip: str, configured: int | None) -> int:
    """The port to serve on: the configured one (refused in one line when taken), else 9876, or a
    free port the system picks when 9876 is taken (a second run beside the first)."""
    def free(port: int) -> bool:
        with socket.socket(socket.AF_INET6 if ":" in bind_ip else socket.AF_INET) as s:
            try:
                s.bind((bind_ip, port))
            except OSError:
                return False
            return True

    if configured is not None:
        if not free(configured):
            raise ConfigError("telemetry.port", f"{bind_ip}:{configured} is in use (another run serving?); "
                                                "choose another port or leave it unset for a free one")
        return configured
    if free(DEFAULT_PORT):
        return DEFAULT_PORT
    with socket.socket(socket.AF_INET6 if ":" in bind_ip else socket.AF_INET) as s:
        s.bind((bind_ip, 0))
        port = int(s.getsockname()[1])
    log.warning("telemetry: port %d is in use; serving on %d instead", DEFAULT_PORT, port)
    return port


def _port_open(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=0.2):
            return True
    except OSError:
        return False


def _open_sink(rec: Any, cfg: TelemetryConfig, rr: Any) -> None:
    """Attach the configured sink to ``rec`` (child process only; may block there)."""
    from rt_ident.runtime.dashboard import default_blueprint

    bp = default_blueprint()
    if cfg.sink == "rrd":
        assert cfg.rrd_path is not None
        Path(cfg.rrd_path).parent.mkdir(parents=True, exist_ok=True)
        rec.save(cfg.rrd_path, default_blueprint=bp)
    elif cfg.sink == "connect":
        rec.connect_grpc(cfg.connect_url, default_blueprint=bp)
    elif cfg.sink == "serve":
        sink = rr.GrpcServerSink(bind_ip=cfg.bind_ip, port=cfg.port)
        rec.set_sinks(sink, default_blueprint=bp)
        log.info("telemetry served at %s", sink.uri)
    elif cfg.sink == "spawn":
        host = _local_host(cfg.bind_ip)
        if not _port_open(host, cfg.port):
            env = dict(os.environ, CI=os.environ.get("CI", "1"))
            subprocess.Popen(viewer_command(cfg), env=env, start_new_session=True, stdin=subprocess.DEVNULL,
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            deadline = time.monotonic() + 15.0
            while not _port_open(host, cfg.port) and time.monotonic() < deadline:
                time.sleep(0.1)
        rec.connect_grpc(f"rerun+http://{host}:{cfg.port}/proxy", default_blueprint=bp)


def _send(rec: Any, rr: Any, blocks: list[dict[str, np.ndarray]], truth: dict[str, float]) -> None:
    """One ``send_columns`` per entity for a list of blocks (and the truth line segments)."""
    keys = [k for k in BLOCK_ENTITIES if any(k in b for b in blocks)]
    for key in keys:
        tcol = [b["t_tick"] if key in TICK_KEYS and "t_tick" in b else b["t"] for b in blocks if key in b]
        t = np.concatenate(tcol)
        if t.size == 0:
            continue
        v = np.concatenate([b[key] for b in blocks if key in b])
        rec.send_columns(BLOCK_ENTITIES[key], indexes=[rr.TimeColumn("time", duration=t)],
                         columns=rr.Scalars.columns(scalars=v))
        if key in truth:
            span = np.array([t.min(), t.max()])
            rec.send_columns(truth_path(key), indexes=[rr.TimeColumn("time", duration=span)],
                             columns=rr.Scalars.columns(scalars=np.full(2, truth[key])))


def _telemetry_main(cfg: TelemetryConfig, ring: MessageRing, sent: Any, ready: Any, truth: dict[str, float]) -> None:
    """Body of the telemetry process: poll the ring, send what is there, stop when the writer closes
    (or the run's main process dies: the .rrd is then finished with what arrived)."""
    watch = become_helper()
    os.environ.setdefault("CI", "1")  # rerun: no analytics config written under HOME
    import rerun as rr

    rec = rr.RecordingStream(cfg.application_id)
    _open_sink(rec, cfg, rr)
    for path, (name, color) in SERIES_STYLES.items():
        rec.log(path, rr.SeriesLines(names=name, colors=[color]), static=True)
    ready.set()
    truth = dict(truth)
    while True:
        closed = ring.writer_closed or watch.gone   # read before draining: nothing can follow a close
        msgs = ring.get(_MAX_COALESCE)
        blocks = []
        for m in msgs:
            if any(k.startswith(_TRUTH) for k in m):
                truth.update({k[len(_TRUTH):]: float(v[0]) for k, v in m.items()})
            else:
                blocks.append(m)
        if blocks:
            _send(rec, rr, blocks, truth)
            sent.value += len(blocks)
        if not msgs:
            if closed:
                break
            time.sleep(_POLL_S)
    try:
        rec.flush(timeout_sec=cfg.flush_timeout)
    except Exception as e:  # noqa: BLE001 - rerun raises RuntimeError on flush timeout
        log.warning("telemetry flush incomplete: %s", e)
    rec.disconnect()  # finalizes the .rrd (footer) / closes connections and servers


class TelemetryProcess:
    """Stream blocks to rerun from a spawned child process; the caller never blocks.

    ``start()`` spawns the child (``__enter__`` does too); ``publish(block)`` returns False and
    counts a drop when the ring is full (or not started); ``close(timeout)`` asks the child to
    flush and disconnect, and terminates it if it has not finished in ``timeout`` seconds.
    ``sent`` counts blocks the child handed to rerun, ``dropped`` blocks refused by ``publish``.
    """

    def __init__(self, config: TelemetryConfig) -> None:
        self.config = config
        self._ctx = mp.get_context("spawn")
        self._ring: MessageRing | None = None
        self._proc: Any = None
        self._sent: Any = None  # mp.Value, created by start() (the constructor does no I/O)
        self._dropped = 0
        self._published = 0
        self._n_seen = 0  # samples seen, for decimation phase across blocks
        self._ready: Any = None
        self._truth: dict[str, float] = {}
        self._truth_pending = False
        self._closed = False
        self.earlier_rrd: list[str] = []   # files of telemetry processes that died (see restart)
        self._sent_before = 0

    @property
    def sent(self) -> int:
        return self._sent_before + (0 if self._sent is None else int(self._sent.value))

    @property
    def dropped(self) -> int:
        return self._dropped

    @property
    def published(self) -> int:
        return self._published

    @property
    def pid(self) -> int | None:
        return None if self._proc is None else self._proc.pid

    def start(self) -> "TelemetryProcess":
        if self._proc is not None or self.config.sink == "off":
            return self
        self._ring = MessageRing(self.config.ring_bytes, max_messages=self.config.queue_size, ctx=self._ctx)
        # Lock-free, one writer (the child). A child terminated while holding a lock would
        # otherwise hang every later read.
        self._sent = self._ctx.Value("q", 0, lock=False)
        self._ready = self._ctx.Event()
        self._proc = self._ctx.Process(target=_telemetry_main, name="rt_ident-telemetry", daemon=True,
                                       args=(self.config, self._ring, self._sent, self._ready, dict(self._truth)))
        start_ignoring_signals(self._proc)
        self._truth_pending = False
        return self

    @property
    def alive(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    @property
    def exitcode(self) -> int | None:
        return None if self._proc is None else self._proc.exitcode

    def restart(self) -> "TelemetryProcess":
        """A new telemetry process in place of a dead one. An .rrd sink continues in a new file
        (``<name>-2.rrd``: the dead child's file keeps what it wrote, never overwritten)."""
        old = self._proc
        if old is not None and old.is_alive():
            old.terminate()
            old.join(1.0)
        self._sent_before = self.sent
        self._sent = None
        if self.config.sink == "rrd" and self.config.rrd_path:
            import dataclasses

            p = Path(self.config.rrd_path)
            self.earlier_rrd.append(str(p))
            self.config = dataclasses.replace(self.config, rrd_path=str(p.with_name(f"{p.stem}-2{p.suffix}")))
        self._proc = None
        return self.start()

    def wait_ready(self, timeout: float) -> bool:
        """Wait (outside the real-time loop!) until the child has opened its sink. True if ready.

        Blocks published before that only fill the ring; with a short ring they are dropped.
        """
        if self._ready is None:
            return self.config.sink == "off"
        return bool(self._ready.wait(timeout))

    def set_truth(self, truth: Mapping[str, float]) -> bool:
        """True values drawn next to the estimates (keys from ``ESTIMATE_KEYS``). Never blocks."""
        for k, v in truth.items():
            if k not in ESTIMATE_KEYS:
                raise DataError(f"set_truth(): unknown key {k!r} (known: {', '.join(ESTIMATE_KEYS)})")
            if not math.isfinite(float(v)):
                raise DataError(f"set_truth(): {k} = {v!r} is not finite")
        self._truth.update({k: float(v) for k, v in truth.items()})
        self._truth_pending = True
        return self._push_truth()

    def _push_truth(self) -> bool:
        if self._ring is None:  # not started: handed to the child at start()
            return self.config.sink != "off"
        if self._closed or not self._ring.put({_TRUTH + k: np.array([v]) for k, v in self._truth.items()}):
            return False
        self._truth_pending = False
        return True

    def _prepare(self, block: Mapping[str, Any]) -> dict[str, np.ndarray]:
        """Validate and decimate a block (``publish`` copies it into the ring: the caller may reuse its arrays)."""
        if "t" not in block:
            raise DataError("publish(): block has no 't'")
        t = np.asarray(block["t"], dtype=np.float64)
        n, dec = t.shape[0], self.config.decimation
        start = (-self._n_seen) % dec
        self._n_seen += n
        out = {"t": t[start::dec] if dec > 1 else t}
        tt = block.get("t_tick")
        if tt is not None:
            out["t_tick"] = np.array(tt, dtype=np.float64, ndmin=1)
        for key, value in block.items():
            if key in ("t", "t_tick"):
                continue
            if key not in BLOCK_ENTITIES:
                raise DataError(f"publish(): unknown block key {key!r} (known: {', '.join(BLOCK_ENTITIES)})")
            a = np.asarray(value, dtype=np.float64)
            if key in TICK_KEYS and tt is not None:
                if a.shape != out["t_tick"].shape:
                    raise DataError(f"publish(): {key!r} has shape {a.shape}, 't_tick' {out['t_tick'].shape}")
                out[key] = a
            else:
                if a.shape != t.shape:
                    raise DataError(f"publish(): {key!r} has shape {a.shape}, 't' {t.shape}")
                out[key] = a[start::dec] if dec > 1 else a
        return out

    def publish(self, block: Mapping[str, Any]) -> bool:
        """Queue one block without waiting. False (and ``dropped`` += 1) if it could not be queued.

        With ``sink == "off"`` the block is accepted and discarded (True, no counters change).
        """
        if self.config.sink == "off":
            return True
        msg = self._prepare(block)
        if self._ring is None or self._closed:
            self._dropped += 1
            return False
        if self._truth_pending:
            self._push_truth()
        if not self._ring.put(msg):
            self._dropped += 1
            return False
        self._published += 1
        return True

    def close(self, timeout: float = 5.0) -> dict[str, Any]:
        """Flush and stop the child; returns within ~``timeout`` s whatever the sink does."""
        t0 = time.monotonic()
        deadline = t0 + max(0.0, timeout - 0.5)  # keep 0.5 s for terminate/kill
        terminated = False
        if self._proc is not None and not self._closed:
            self._closed = True
            self._ring.close_writer()
            self._proc.join(max(0.0, deadline - time.monotonic()))
            if self._proc.is_alive():
                log.warning("telemetry process did not finish within %.1f s; terminating", timeout)
                terminated = True
                self._proc.terminate()
                self._proc.join(0.4)
                if self._proc.is_alive():
                    self._proc.kill()
                    self._proc.join(0.1)
        self._closed = True
        return {
            "sink": self.config.sink,
            "rrd_path": self.config.rrd_path if self.config.sink == "rrd" else None,
            "earlier_rrd": list(self.earlier_rrd),
            "published": self._published,
            "sent": self.sent,
            "dropped": self.dropped,
            "exitcode": None if self._proc is None else self._proc.exitcode,
            "terminated": terminated,
            "seconds": time.monotonic() - t0,
        }

    def __enter__(self) -> "TelemetryProcess":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
