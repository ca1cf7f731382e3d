"""Telemetry: a separate process that streams decimated blocks to rerun.

The real-time loop calls :meth:`TelemetryProcess.publish` with a dict of arrays. ``publish``
decimates it and copies it into a bounded shared-memory ring (:mod:`rt_ident.processes.shm_ring`: no
feeder thread, no pickling, no system call in the loop's process). It never waits: on a full
ring the block is dropped and counted. A child process owns an
``rr.RecordingStream`` (no global rerun state), coalesces whatever is queued and logs it with
columnar ``send_columns`` only (~70 ns/sample, vs ~30 us per ``rr.log``). Whatever the sink does
(``connect_grpc`` to a missing viewer blocks the logging call), only the child can stall.

Block contract (keys and entity paths: :mod:`rt_ident.outputs.dashboard`)::

    {"t": sample times [s],                      # required
     "theta1", "theta2", "torque_meas", "torque_cmd", "torque_filt", "torque_hat": arrays like t,
     "t_tick": tick times [s] (optional),
     "I1", "I2", "B", "K", "wn", "zeta", "lateness_us", "overruns": arrays like t_tick
                                                 # (like t when there is no t_tick)}

Decimation keeps every ``decimation``-th sample of the arrays that follow ``t``, continuous
across blocks; tick-rate arrays that follow ``t_tick`` are sent whole. True values, given once
with :meth:`TelemetryProcess.set_truth`, are drawn as a second series beside each estimate: the
child sends the true value at the first and last time of every batch that holds that estimate
(a horizontal line over the estimate's time span).

Sinks and their settings (:class:`TelemetryConfig`), the viewer and the .rrd's footer:
:mod:`rt_ident.outputs.sinks`. The child sets ``CI=1`` (rerun writes no analytics config) unless
``CI`` is already set.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections.abc import Callable, Collection, Mapping
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import numpy as np

from rt_ident.errors import DataError
from rt_ident.outputs.dashboard import (
    BLOCK_ENTITIES,
    CONTROL_ENTITIES,
    ENTITY_SERIES,
    ESTIMATE_KEYS,
    SERIES_STYLES,
    TORQUE_NRMSE,
    draw_fit_frf,
    draw_loop_gain,
    truth_path,
)
from rt_ident.outputs.sinks import (
    CLIENT_SINKS,
    TelemetryConfig,
    disk_full,
    ensure_viewer,
    finish_rrd,
    port_open,
    viewer_address,
)
from rt_ident.processes.context import beside_the_loop, helper_context
from rt_ident.processes.guard import (
    PLACEMENT_ATTR,
    become_helper,
    end_helper,
    quick_exit,
    start_ignoring_signals,
    take_placement,
)
from rt_ident.processes.shm_ring import MessageRing, RingReused, key_words, put_rows

log = logging.getLogger(__name__)

_CI_KEYS = tuple(f"{side}_{k}" for k in ESTIMATE_KEYS for side in ("lo", "hi"))
TICK_KEYS: frozenset[str] = frozenset(ESTIMATE_KEYS + _CI_KEYS + ("lateness_us", "overruns", "stalls")
                                      + tuple(CONTROL_ENTITIES))
#: Tick-rate signals drawn at a tenth of the tick rate (the lateness as its envelope: every late
#: tick stays visible); the per-sample estimates settle over ~100 ms, 100 points/s draw them whole.
THIN_KEYS: Mapping[str, int] = {"lateness_us": 10, **{f"svf_{k}": 10 for k in ("I1", "I2", "B", "K")}}
#: Tick-rate signals that change only now and then (a fit, a redesign, an overrun): sent as steps.
STEP_KEYS: frozenset[str] = frozenset(ESTIMATE_KEYS + _CI_KEYS + ("overruns", "stalls", "gain_theta2", "gain_omega1",
                                                                   "pm_deg", "gm_db", "n_accepted", "n_rejected",
                                                                   "fallbacks"))
_MAX_COALESCE = 256  # blocks taken from the ring per poll
_MAX_PENDING = 2048  # blocks held in the child before a send even if batch_seconds has not passed
_TRUTH = "truth:"    # key prefix of a truth message in the ring
_WINDOW = "window"           # the window values of a tick block (publish(window=...)), one vector
_WINDOW_ID = "window_id"     # ... and the id of their names, sent before as {_WINDOW_SCHEMA: (id, names)}
_WINDOW_SCHEMA = "window_schema"
_WINDOW_WORDS = np.concatenate([key_words(_WINDOW_ID), key_words(_WINDOW)])   # publish_rows' tail
_NO_VALUES = np.zeros(0)
_VIEWS = ("frf:", "lg:")  # key prefixes of a fit's FRF view and of a controller's loop-gain view
_NRMSE_WINDOW_S = 1.0  # the torque estimate's running NRMSE over the last second of samples
# Every send_columns is a chunk of its own (~1-2 kB of overhead in the .rrd). A step signal that did
# not change is therefore extended (its last value re-sent) only this often, and the FRF views are
# drawn at most this often (the newest one wins; the last one is always drawn at close).
_EXTEND_S = 5.0
_VIEW_EVERY_S = 2.0        # ... while the model moves (its resonance by > _VIEW_MOVED since the last draw)
_VIEW_STEADY_S = 10.0      # ... once it has settled. (A draw is 24 chunks, ~0.05 MB of .rrd.)
_VIEW_MOVED = 0.005        # a resonance that moved by more than this fraction: the model still moves
_POLL_S = 0.01       # child: sleep between polls of an empty ring


#: ``failed`` codes the child leaves for the parent (0: none)
FAIL_DISK_FULL, FAIL_NO_VIEWER, FAIL_FLUSH, FAIL_CONNECT = 1, 2, 3, 4


def _open_sink(rec: Any, cfg: TelemetryConfig, rr: Any) -> None:
    """Attach the configured sink to ``rec`` (child process only; may block there)."""
    from rt_ident.outputs.dashboard import default_blueprint

    bp = default_blueprint()
    if cfg.sink == "rrd":
        assert cfg.rrd_path is not None
        Path(cfg.rrd_path).parent.mkdir(parents=True, exist_ok=True)
        # No footer: to write one, the file sink keeps a manifest entry per chunk until the stream
        # closes, and the child would grow for the whole run. close() adds it (finish_rrd).
        rec.save(cfg.rrd_path, default_blueprint=bp, write_footer=False)
    elif cfg.sink == "connect":
        rec.connect_grpc(cfg.connect_url, default_blueprint=bp)
    elif cfg.sink == "serve":
        sink = rr.GrpcServerSink(bind_ip=cfg.bind_ip, port=cfg.port)
        rec.set_sinks(sink, default_blueprint=bp)
        log.info("telemetry served at %s", sink.uri)
    elif cfg.sink == "spawn":
        rec.connect_grpc(ensure_viewer(cfg), default_blueprint=bp)


def _connect(rec: Any, cfg: TelemetryConfig, rr: Any, failed: Any) -> None:
    """The ``connect`` sink, opened beside the child's loop; a failure leaves ``FAIL_CONNECT``."""
    try:
        _open_sink(rec, cfg, rr)
    except Exception as exc:  # noqa: BLE001 - rerun's errors vary by version; each is reported the same
        log.error("telemetry: connecting to %s failed: %s", cfg.connect_url, exc)
        failed.value = FAIL_CONNECT


def _connected(connecting: threading.Thread, timeout: float) -> bool:
    """Whether the connect thread ended within ``timeout`` (it sets ``failed`` itself if its connect failed)."""
    connecting.join(timeout)
    return not connecting.is_alive()


def _step_points(v: np.ndarray, last: np.ndarray | None, extend: bool) -> np.ndarray:
    """Row indices of a piecewise-constant signal worth sending (``v``: rows x series): each row
    where any series changes, with the row just before it (so the viewer draws a step, not a ramp),
    and, when ``extend``, the batch's last row (so the line reaches the present). ``last`` is the
    row sent at the end of the previous batch."""
    n = v.shape[0]
    prev = np.empty_like(v)
    prev[0] = np.nan if last is None else last
    prev[1:] = v[:-1]
    same = np.all((v == prev) | (np.isnan(v) & np.isnan(prev)), axis=1)
    change = np.flatnonzero(~same)
    keep = np.zeros(n, dtype=bool)
    keep[change] = True
    keep[change[change > 0] - 1] = True
    keep[-1] |= extend
    return np.flatnonzero(keep)


def _thin(t: np.ndarray, v: np.ndarray, every: int, envelope: bool) -> tuple[np.ndarray, np.ndarray]:
    """Every ``every``-th row, or (``envelope``) the row with the largest first series of each run
    of ``every`` rows, so a single late tick still shows as a spike."""
    if every <= 1 or v.shape[0] <= every:
        return t, v
    if not envelope:
        return t[every - 1::every], v[every - 1::every]
    m = v.shape[0] // every * every
    w = v[:m, 0].reshape(-1, every)
    arg = np.argmax(np.where(np.isnan(w), -np.inf, w), axis=1) + np.arange(0, m, every)
    tail = np.arange(m, v.shape[0])[-1:] if m < v.shape[0] else np.empty(0, dtype=int)
    idx = np.concatenate([arg, tail])
    return t[idx], v[idx]


def _view_moved(marks: np.ndarray | None, last: np.ndarray | None) -> bool:
    """Whether a fit's resonance moved by more than :data:`_VIEW_MOVED` since the FRF last drawn.
    Any mark (a wild fit's 0 Hz or NaN, an empty array) is an answer, never an exception: an
    exception here would end the telemetry process."""
    if marks is None or last is None or len(marks) == 0 or len(last) == 0:
        return True
    a, b = float(marks[0]), float(last[0])
    if not (math.isfinite(a) and math.isfinite(b)) or b == 0.0:
        return a != b
    return abs(a / b - 1.0) > _VIEW_MOVED


class _Sender:
    """Sends coalesced blocks with one ``send_columns`` per entity per batch.

    An entity's series share one row per time (:data:`~rt_ident.outputs.dashboard.ENTITY_SERIES`;
    a series missing from a block, like the reconstruction before the first fit, is NaN there).
    Signals that change only at a fit or a redesign (estimates, intervals, gains, margins,
    counters) are sent as their change points (:func:`_step_points`): repeating one value per
    tick was most of the .rrd's bytes for none of its information. The running NRMSE of the Eq. 18
    reconstruction against the filtered measured torque is computed here, over the last second,
    once per batch."""

    def __init__(self, rec: Any, rr: Any) -> None:
        self.rec, self.rr = rec, rr
        self.last: dict[str, np.ndarray] = {}
        self.extended: dict[str, float] = {}      # entity -> when its line was last extended
        self.truth_sent: dict[str, float] = {}    # truth entity -> last time its line was extended to
        self.tail: dict[str, tuple[float, np.ndarray, bool]] = {}  # step entity -> (last t, row, was sent)
        self.views: dict[str, dict[str, np.ndarray]] = {}   # newest undrawn view per kind
        self.view_drawn: dict[str, float] = {}
        self.view_marks: np.ndarray | None = None   # resonance/anti-resonance of the last FRF drawn
        self._torque: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []   # (t, filtered, reconstructed)

    def send(self, blocks: list[dict[str, np.ndarray]], truth: dict[str, float], final: bool = False) -> None:
        rec, rr = self.rec, self.rr
        now = time.monotonic()
        for path, keys in ENTITY_SERIES.items():
            have = [b for b in blocks if any(k in b for k in keys)]
            if not have:
                continue
            tick = keys[0] in TICK_KEYS
            t = np.concatenate([b["t_tick"] if tick and "t_tick" in b else b["t"] for b in have])
            if t.size == 0:
                continue
            cols = []
            for k in keys:
                parts = []
                for b in have:
                    n = (b["t_tick"] if tick and "t_tick" in b else b["t"]).size
                    parts.append(b[k] if k in b else np.full(n, np.nan))
                cols.append(np.concatenate(parts))
            v = np.column_stack(cols)
            if all(k in STEP_KEYS for k in keys):
                extend = final or now - self.extended.get(path, -math.inf) >= _EXTEND_S
                idx = _step_points(v, self.last.get(path), extend)
                self.last[path] = v[-1].copy()
                self.tail[path] = (float(t[-1]), v[-1].copy(), idx.size > 0 and idx[-1] == v.shape[0] - 1)
                if extend:
                    self.extended[path] = now
                if idx.size == 0:
                    continue
                t, v = t[idx], v[idx]
            elif keys[0] in THIN_KEYS:
                t, v = _thin(t, v, THIN_KEYS[keys[0]], envelope=keys[0] == "lateness_us")
            rec.send_columns(path, indexes=[rr.TimeColumn("time", duration=t)],
                             columns=rr.Scalars.columns(scalars=v if v.shape[1] > 1 else v[:, 0]))
            for k in keys:
                if k in truth and (final or truth_path(k) not in self.truth_sent
                                   or now - self.extended.get(truth_path(k), -math.inf) >= _EXTEND_S):
                    start = self.truth_sent.get(truth_path(k), float(t.min()))
                    span = np.array([start, max(start, float(t.max()))])
                    self.truth_sent[truth_path(k)] = float(span[1])
                    self.extended[truth_path(k)] = now
                    rec.send_columns(truth_path(k), indexes=[rr.TimeColumn("time", duration=span)],
                                     columns=rr.Scalars.columns(scalars=np.full(2, truth[k])))
        self._nrmse(blocks)

    def finish(self, truth: dict[str, float]) -> None:
        """At close: every step line and true-value line reaches the last time seen."""
        rr = self.rr
        t_end = -math.inf
        for path, (t, row, sent) in self.tail.items():
            t_end = max(t_end, t)
            if not sent:
                self.rec.send_columns(path, indexes=[rr.TimeColumn("time", duration=np.array([t]))],
                                      columns=rr.Scalars.columns(scalars=row[None, :] if row.size > 1 else row))
        for key, value in truth.items():
            start = self.truth_sent.get(truth_path(key))
            if start is not None and t_end > start:
                span = rr.TimeColumn("time", duration=np.array([start, t_end]))
                self.rec.send_columns(truth_path(key), indexes=[span],
                                      columns=rr.Scalars.columns(scalars=np.full(2, value)))

    def _nrmse(self, blocks: list[dict[str, np.ndarray]]) -> None:
        """NRMSE [%] of the Eq. 18 reconstruction against the measured torque, both through the SVF,
        over the last second: 100 rms(F T_hat - F T) / std(F T), the fit measure of
        rt_ident.estimators.excitation_id."""
        for b in blocks:
            if "torque_filt" in b and "torque_hat" in b:
                self._torque.append((b["t"], b["torque_filt"], b["torque_hat"]))
        if not self._torque:
            return
        t_end = float(self._torque[-1][0][-1])
        while self._torque and float(self._torque[0][0][-1]) < t_end - _NRMSE_WINDOW_S:
            self._torque.pop(0)
        if not self._torque:
            return
        meas = np.concatenate([x[1] for x in self._torque])
        hat = np.concatenate([x[2] for x in self._torque])
        ok = np.isfinite(meas) & np.isfinite(hat)
        if ok.sum() < 10:
            return
        sd = float(np.std(meas[ok]))
        if sd <= 0.0:
            return
        value = 100.0 * float(np.sqrt(np.mean((hat[ok] - meas[ok]) ** 2))) / sd
        self.rec.send_columns(TORQUE_NRMSE, indexes=[self.rr.TimeColumn("time", duration=np.array([t_end]))],
                              columns=self.rr.Scalars.columns(scalars=np.array([value])))

    def offer_view(self, msg: dict[str, np.ndarray], final: bool = False) -> None:
        """Keep the newest view of its kind; draw it when the last one of that kind is old enough."""
        kind = "frf:" if any(k.startswith("frf:") for k in msg) else "lg:"
        self.views[kind] = msg
        self.draw_views(final)

    def draw_views(self, final: bool = False) -> None:
        now = time.monotonic()
        for kind in list(self.views):
            # a new controller's loop gain is drawn at once (rare); fit FRFs are rate-limited
            age = now - self.view_drawn.get(kind, -math.inf)
            if kind == "frf:" and not final:
                moved = _view_moved(self.views[kind].get("frf:marks_hz"), self.view_marks)
                if age < (_VIEW_EVERY_S if moved else _VIEW_STEADY_S):
                    continue
            elif not (final or kind == "lg:" or age >= _VIEW_EVERY_S):
                continue
            msg = self.views.pop(kind)
            self.view_drawn[kind] = now
            if kind == "frf:":
                self.view_marks = msg.get("frf:marks_hz")
            try:
                self._draw_view(kind, msg)
            except (ValueError, KeyError, TypeError) as e:   # a view that cannot be drawn is skipped
                log.warning("telemetry: view not drawn: %s", e)

    def _draw_view(self, kind: str, msg: dict[str, np.ndarray]) -> None:
        """A fit's FRF view or a controller's loop gain, logged at its time (see rt_ident.outputs.dashboard)."""
        rec, rr = self.rec, self.rr
        view = {k[len(kind):]: v for k, v in msg.items() if k.startswith(kind)}
        t = float(view.pop("t")[0])
        if kind == "frf:":
            draw_fit_frf(rec, rr, t, view)
        else:
            margins = {"pm_deg": float(view.pop("pm_deg")[0]), "gm_db": float(view.pop("gm_db")[0])}
            draw_loop_gain(rec, rr, t, view, margins)


def _expand_window(m: dict[str, np.ndarray], schemas: Mapping[int, tuple[str, ...]]) -> None:
    """A tick block's window vector back into one array per name, its value at every tick."""
    values = m.pop(_WINDOW)
    names = schemas.get(int(m.pop(_WINDOW_ID)[0]))
    if names is None:                                  # cannot happen: the names go first, in order
        log.warning("telemetry: window values without their names; dropped")
        return
    n = m["t_tick"].shape[0]
    for name, v in zip(names, values):
        m[name] = np.full(n, v)


def _telemetry_main(cfg: TelemetryConfig, ring: MessageRing, sent: Any, ready: Any, truth: dict[str, float],
                    failed: Any = None) -> None:
    """Body of the telemetry process: poll the ring, send what is there, stop when the writer closes
    (or the run's main process dies: the .rrd is then finished with what arrived)."""
    watch = become_helper(defer_placement=True)      # rerun imported and the sink opened first
    if failed is None:
        from types import SimpleNamespace

        failed = SimpleNamespace(value=0)
    os.environ.setdefault("CI", "1")  # rerun: no analytics config written under HOME
    # warnings only (an INFO line reached the terminal), and not the missing-footer one (_open_sink)
    if cfg.sink == "rrd":
        os.environ.setdefault("RUST_LOG", "warn,re_log_encoding::rrd::file_sink=error")
    elif cfg.sink in CLIENT_SINKS:   # not rerun's retry lines: an undelivered dashboard is reported in the summary
        os.environ.setdefault("RUST_LOG", "warn,re_grpc_client=off,re_sdk::recording_stream=off")
    import rerun as rr

    rec = rr.RecordingStream(cfg.application_id)
    connecting = None
    if cfg.sink == "connect":
        # connect_grpc blocks 5 s when nothing listens: the run goes on meanwhile, rerun buffering what is
        # logged until the sink is set (and a viewer started later still gets it)
        host, port = viewer_address(cfg)
        if not port_open(host, port):
            log.warning("telemetry: nothing listens at %s:%d yet; the dashboard goes there if a viewer starts",
                        host, port)
        connecting = threading.Thread(target=_connect, args=(rec, cfg, rr, failed), name="telemetry connect",
                                      daemon=True)
        connecting.start()
    else:
        _open_sink(rec, cfg, rr)
    for path, (names, colors) in SERIES_STYLES.items():
        rec.log(path, rr.SeriesLines(names=list(names), colors=list(colors)), static=True)
    ready.set()
    take_placement()
    truth = dict(truth)
    sender = _Sender(rec, rr)
    pending: list[dict[str, np.ndarray]] = []
    schemas: dict[int, tuple[str, ...]] = {}      # window id -> its names (publish(window=...))
    last_send = time.monotonic()
    while True:
        closed = ring.writer_closed or watch.gone   # read before draining: nothing can follow a close
        try:
            msgs = ring.get(_MAX_COALESCE)
        except RingReused as exc:                   # its parent let go of the ring: finish with what came
            log.warning("telemetry: %s", exc)
            msgs, closed = [], True
        for m in msgs:
            if MessageRing.is_object(m):
                obj = MessageRing.unpickle(m)
                if isinstance(obj, dict) and _WINDOW_SCHEMA in obj:
                    wid, names = obj[_WINDOW_SCHEMA]
                    schemas[int(wid)] = tuple(names)
                continue
            if _WINDOW in m:
                _expand_window(m, schemas)
            if any(k.startswith(_TRUTH) for k in m):
                truth.update({k[len(_TRUTH):]: float(v[0]) for k, v in m.items()})
            elif any(k.startswith(_VIEWS) for k in m):
                sender.offer_view(m)              # logged at its own time: order against the samples is moot
            else:
                pending.append(m)
        now = time.monotonic()
        final = closed and not msgs
        if pending and (now - last_send >= cfg.batch_seconds or len(pending) >= _MAX_PENDING or final):
            full = disk_full(cfg.rrd_path, cfg.min_free_bytes) if cfg.sink == "rrd" else None
            if full:                              # stop writing; the parent reports it (never "sent")
                if not failed.value:
                    failed.value = FAIL_DISK_FULL
                    log.error("telemetry: %s; the dashboard stops here", full)
            else:
                sender.send(pending, truth, final=final)
                sent.value += len(pending)
            pending = []
            last_send = now
        if sender.views:
            sender.draw_views(final)
        if not msgs:
            if closed and not pending:
                sender.finish(truth)
                break
            time.sleep(_POLL_S)
    client = cfg.sink in CLIENT_SINKS
    if client and not port_open(*viewer_address(cfg)):
        failed.value = FAIL_NO_VIEWER
    elif connecting is not None and not _connected(connecting, cfg.flush_timeout):
        failed.value = FAIL_FLUSH                 # still connecting: a flush would only empty rerun's buffer
    else:
        try:
            rec.flush(timeout_sec=cfg.flush_timeout)
        except Exception as e:  # noqa: BLE001 - rerun raises RuntimeError on flush timeout
            if client:
                failed.value = FAIL_FLUSH
            else:
                log.warning("telemetry flush incomplete: %s", e)
    if client and failed.value:
        # nothing more can reach the viewer; rerun would spend 5 s at exit on a last connection attempt
        os._exit(0)
    rec.disconnect()  # finalizes the .rrd (footer) / closes connections and servers
    if cfg.sink == "rrd":
        quick_exit()  # the file is closed: nothing is left to hand over


class TelemetryProcess:
    """Stream blocks to rerun from a child process; the caller never blocks.

    ``start()`` starts the child (``__enter__`` does too); ``publish(block)`` returns False and
    counts a drop when the ring is full (or not started); ``close(timeout)`` asks the child to
    flush and disconnect, and terminates it if it has not finished in ``timeout`` seconds.
    ``sent`` counts blocks the child handed to rerun, ``dropped`` blocks refused by ``publish``.
    """

    def __init__(self, config: TelemetryConfig) -> None:
        self.config = config
        self._ctx: Any = None        # helper_context(), at start(): the constructor starts no process
        self._ring: MessageRing | None = None
        self._proc: Any = None
        self._sent: Any = None  # mp.Value, created by start() (the constructor does no I/O)
        self._failed: Any = None
        self._dropped = 0
        self._published = 0
        self._n_seen = 0  # samples seen, for decimation phase across blocks
        self._ready: Any = None
        self._truth: dict[str, float] = {}
        self._truth_pending = False
        self._schemas: dict[tuple[str, ...], int] = {}   # window names sent to the child -> their id
        self._row_keys: dict[tuple[str, ...], np.ndarray] = {}   # publish_rows: checked keys -> their words
        self._closed = False
        self._room_s = 0.0                     # wait_for_room(): how long full rings may still be waited on
        self._footer: dict[str, Any] = {}   # close(): whether the .rrd got its footer (_finish)
        self.earlier_rrd: list[str] = []   # files of telemetry processes that died (see restart)
        self.placement: dict[str, Any] | None = None    # how the run placed the child: a replacement takes the same
        self._sent_before = 0
        self._replacing: Future[tuple[Any, ...]] | None = None    # restart() under way

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
        """The child's pid (the dead one's while a restart is under way)."""
        self._current()
        return None if self._proc is None else self._proc.pid

    def start(self) -> TelemetryProcess:
        if self._proc is not None or self.config.sink == "off":
            return self
        self._take(self._parts(self.config, dict(self._truth)))
        self._truth_pending = False
        return self

    @staticmethod
    def _parts(config: TelemetryConfig, truth: dict[str, float],
               placement: dict[str, Any] | None = None) -> tuple[Any, ...]:
        """A started child with its ring, counters and ready event (context, ring, sent, failed, ready, process);
        ``placement``: how the run placed the child it replaces (:data:`~rt_ident.processes.guard.PLACEMENT_ATTR`)."""
        ctx = helper_context()
        ring = MessageRing(config.ring_bytes, max_messages=config.queue_size, ctx=ctx)
        # Lock-free, one writer (the child). A child terminated while holding a lock would
        # otherwise hang every later read.
        sent = ctx.Value("q", 0, lock=False)
        failed = ctx.Value("b", 0, lock=False)   # FAIL_*: a full disk, an undelivered dashboard
        ready = ctx.Event()
        proc = ctx.Process(target=_telemetry_main, name="rt_ident-telemetry", daemon=True,
                           args=(config, ring, sent, ready, truth, failed))
        setattr(proc, PLACEMENT_ATTR, placement)
        start_ignoring_signals(proc)
        return ctx, ring, sent, failed, ready, proc

    def _take(self, parts: tuple[Any, ...]) -> None:
        self._ctx, self._ring, self._sent, self._failed, self._ready, self._proc = parts
        self._schemas = {}                     # a new child has been told no window names yet

    def _current(self, wait_s: float = 0.0) -> bool:
        """True once no restart is under way (waiting up to ``wait_s`` for one): a finished one's child is
        taken in here, on the caller's thread. One that failed leaves no ring: hand-offs are dropped."""
        fut = self._replacing
        if fut is None:
            return True
        try:
            self._take(fut.result(timeout=wait_s))
            self._truth_pending = bool(self._truth)      # set meanwhile, perhaps: sent again
        except TimeoutError:
            return False
        except Exception as exc:  # noqa: BLE001 - said; the dead child is then left as it is
            log.error("telemetry: restart failed: %s", exc)
        self._replacing = None
        return True

    @property
    def alive(self) -> bool:
        """The child lives, or its replacement is under way."""
        return not self._current() or (self._proc is not None and self._proc.is_alive())

    @property
    def exitcode(self) -> int | None:
        return None if self._proc is None else self._proc.exitcode

    def restart(self) -> TelemetryProcess:
        """A new telemetry process in place of a dead one. An .rrd sink continues in a new file
        (``<name>-2.rrd``: the dead child's file keeps what it wrote, never overwritten). Returns at once:
        the new child is made and started beside the loop
        (:func:`~rt_ident.processes.context.beside_the_loop`); hand-offs until it is in are dropped."""
        if self._replacing is not None or self.config.sink == "off":
            return self
        old = self._proc
        self._sent_before = self.sent
        self._sent = None
        self._ring = None
        if self.config.sink == "rrd" and self.config.rrd_path:
            import dataclasses

            p = Path(self.config.rrd_path)
            self.earlier_rrd.append(str(p))
            self.config = dataclasses.replace(self.config, rrd_path=str(p.with_name(f"{p.stem}-2{p.suffix}")))
        config, truth, placement = self.config, dict(self._truth), self.placement

        def replacement() -> tuple[Any, ...]:
            end_helper(old)
            return self._parts(config, truth, placement)

        self._replacing = beside_the_loop(replacement)
        return self

    def wait_ready(self, timeout: float) -> bool:
        """Wait (outside the real-time loop!) until the child has opened its sink (a ``connect`` sink:
        until it takes blocks, connecting meanwhile). True if ready.

        Blocks published before that only fill the ring; with a short ring they are dropped.
        """
        if not self._current(timeout):
            return False
        if self._ready is None:
            return self.config.sink == "off"
        return bool(self._ready.wait(timeout))

    def wait_for_room(self, seconds: float) -> None:
        """From now on a hand-off that finds the ring full waits for the child to drain it, ``seconds``
        in all over the hand-offs that wait, instead of being dropped. For what follows the loop (the final
        fit's estimate and FRF): nothing real-time waits then, and a child a busy host starved during the
        run would otherwise leave the dashboard without the values the run reports."""
        self._room_s = max(0.0, float(seconds))

    def _put(self, put: Callable[[MessageRing], bool]) -> bool:
        """``put`` into the ring; where it is full, again while :meth:`wait_for_room` allows."""
        return self._ring is not None and (put(self._ring) or self._retry(put))

    def _retry(self, put: Callable[[MessageRing], bool]) -> bool:
        """``put`` again until it fits, while :meth:`wait_for_room`'s time lasts and the child lives."""
        ring = self._ring
        if ring is None or self._room_s <= 0.0:
            return False
        t0 = time.monotonic()
        try:
            while time.monotonic() - t0 < self._room_s and self.alive:
                time.sleep(0.002)
                if put(ring):
                    return True
            return False
        finally:
            self._room_s = max(0.0, self._room_s - (time.monotonic() - t0))

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

    def publish_fit(self, t: float, frf: Mapping[str, Any] | None) -> bool:
        """Queue a fit's FRF view (:func:`rt_ident.estimators.frf.frf_view`) drawn at time ``t``.
        Never blocks; False (and counted in ``dropped``) when it could not be queued."""
        if frf is None:
            return False
        return self._publish_view("frf:", t, frf)

    def publish_loop_gain(self, t: float, view: Mapping[str, Any] | None, margins: Mapping[str, Any] | None) -> bool:
        """Queue the active controller's loop gain (:func:`rt_ident.control.design.loop_gain_view`)
        with its phase margin and smaller gain margin, drawn at time ``t``."""
        if view is None:
            return False
        m = margins or {}
        pm = m.get("pm_deg")
        gm = m.get("gm_db")
        extra = {"pm_deg": np.array([np.nan if pm is None else float(pm)]),
                 "gm_db": np.array([np.nan if gm is None else float(gm)])}
        return self._publish_view("lg:", t, {**view, **extra})

    def _publish_view(self, prefix: str, t: float, arrays: Mapping[str, Any]) -> bool:
        if self.config.sink == "off":
            return True
        msg = {prefix + "t": np.array([float(t)])}
        for k, v in arrays.items():
            msg[prefix + k] = np.asarray(v, dtype=np.float64).ravel()
        if self._closed or not self._put(lambda r: r.put(msg)):
            self._dropped += 1
            return False
        return True

    def _push_truth(self) -> bool:
        if self._ring is None:  # not started: handed to the child at start()
            return self.config.sink != "off"
        msg = {_TRUTH + k: np.array([v]) for k, v in self._truth.items()}
        if self._closed or not self._put(lambda r: r.put(msg)):
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

    def publish(self, block: Mapping[str, Any], window: Mapping[str, float] | None = None) -> bool:
        """Queue one block without waiting. False (and ``dropped`` += 1) if it could not be queued.

        ``window``: tick signals (keys of ``TICK_KEYS``) that hold one value at every tick of the
        block's ``t_tick``, as name -> float. They travel as one vector (their names once, when the
        set of names changes) and are drawn exactly as if each were an array of that value.

        With ``sink == "off"`` the block is accepted and discarded (True, no counters change).
        """
        if self.config.sink == "off":
            return True
        msg = self._prepare(block)
        wid = None
        if window:
            if "t_tick" not in msg:
                raise DataError("publish(): window values need the block's 't_tick'")
            names = tuple(window)
            wid = self._window_id(names, msg)
            msg[_WINDOW_ID] = np.array([wid], dtype=np.int64)
            msg[_WINDOW] = np.fromiter(window.values(), dtype=np.float64, count=len(names))
        return self._send(lambda ring: ring.put(msg), names if window else None, wid)

    def publish_rows(self, keys: tuple[str, ...], rows: np.ndarray, n: int, index: np.ndarray | None = None,
                     window: tuple[tuple[str, ...], np.ndarray] | None = None) -> bool:
        """:meth:`publish` of ``{keys[i]: rows[index[i], :n]}`` (``index`` default: row i) and the window
        ``(names, values)``, written into the ring by one compiled call (rt_ident.processes.shm_ring.put_rows):
        the same message, without a dict, a validation pass and a packing loop per field. The real-time
        loop's hand-off; ``keys`` is checked once per tuple. With decimation it goes through :meth:`publish`."""
        if self.config.sink == "off":
            return True
        if index is None:
            index = np.arange(len(keys), dtype=np.int64)
        if self.config.decimation != 1:
            return self.publish({k: rows[i, :n] for k, i in zip(keys, index)},
                                None if window is None else dict(zip(window[0], window[1])))
        words = self._row_keys.get(keys)
        if words is None:                      # the checks _prepare makes, once for these keys
            if keys[0] != "t" or any(k not in BLOCK_ENTITIES for k in keys[1:] if k != "t_tick"):
                raise DataError(f"publish_rows(): keys {keys} are not a block's ('t' first, known entities)")
            if window is not None and "t_tick" not in keys:
                raise DataError("publish_rows(): window values need the block's 't_tick'")
            words = np.concatenate([key_words(k) for k in keys])
            self._row_keys[keys] = words
        self._n_seen += n
        wid, values, names, new_names = -1, _NO_VALUES, None, False
        if window is not None:
            names, values = window
            known = self._schemas.get(names)
            if known is None:
                wid, new_names = self._window_id(names, keys), True
            else:
                wid = known
        if self._replacing is not None:
            self._current()
        ring = self._ring
        if ring is None or self._closed or self._truth_pending or new_names:
            return self._send(lambda r: self._put_rows(r, words, index, rows, n, wid, values, names), names, wid)
        if not (self._put_rows(ring, words, index, rows, n, wid, values, names)    # the usual hand-off
                or self._room_s > 0.0 and self._retry(lambda r: self._put_rows(r, words, index, rows, n, wid,
                                                                               values, names))):
            self._dropped += 1
            return False
        self._published += 1
        return True

    @staticmethod
    def _put_rows(ring: MessageRing, words: np.ndarray, index: np.ndarray | None, rows: np.ndarray, n: int,
                  wid: int, values: np.ndarray, names: tuple[str, ...] | None) -> bool:
        h, di, df = ring.compiled_views()
        got = put_rows(h, di, df, ring.capacity, ring.max_messages, words, index, rows, n, _WINDOW_WORDS, wid,
                       values, names is not None)
        if got < 0:
            raise DataError(f"publish_rows(): a {n}-column block does not fit a {ring.capacity}-byte ring")
        return bool(got)

    def _window_id(self, names: tuple[str, ...], fields: Collection[str]) -> int:
        """The id of a window's names (a new one is sent to the child before the vector that uses it)."""
        wid = self._schemas.get(names)
        if wid is None:
            bad = [k for k in names if k not in TICK_KEYS or k in fields]
            if bad:
                raise DataError(f"publish(): window key {bad[0]!r} is not a tick signal or is also in the block")
            wid = len(self._schemas)
        return wid

    def _send(self, put: Callable[[MessageRing], bool], names: tuple[str, ...] | None, wid: int | None) -> bool:
        if self._replacing is not None:
            self._current()
        if self._ring is None or self._closed:
            self._dropped += 1
            return False
        if self._truth_pending:
            self._push_truth()
        if names is not None and wid is not None and names not in self._schemas:   # (both or neither)
            schema = {_WINDOW_SCHEMA: (wid, names)}
            if not self._put(lambda r: r.put_object(schema)):
                self._dropped += 1
                return False
            self._schemas[names] = wid      # the child has the names before the first vector that uses them
        if not self._put(put):
            self._dropped += 1
            return False
        self._published += 1
        return True

    def close(self, timeout: float = 5.0) -> dict[str, Any]:
        """Flush and stop the child within ~``timeout`` s whatever the sink does; an .rrd then gets
        its footer (:func:`finish_rrd`) within ``config.finish_timeout`` s more."""
        t0 = time.monotonic()
        deadline = t0 + max(0.0, timeout - 0.5)  # keep 0.5 s for terminate/kill
        self._current(max(0.0, deadline - t0))   # a restart under way: its child is closed too
        terminated = False
        if self._proc is not None and self._ring is not None and not self._closed:   # (started: both)
            self._closed = True
            self._ring.close_writer()
            self._proc.join(max(0.0, deadline - time.monotonic()))
            if self._proc.is_alive():
                log.warning("telemetry process did not finish within %.1f s; terminating", timeout)
                terminated = True
                end_helper(self._proc, 0.4, 0.1)
            self._footer = self._finish()
        self._closed = True
        return {
            **self._written(),
            **self._footer,
            **self._delivered(terminated),
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

    def _delivered(self, terminated: bool) -> dict[str, Any]:
        """Whether a viewer sink's viewer got the dashboard: ``{"delivered": bool, "write_error": why}``
        (``write_error``, as an .rrd's, makes the run report the dashboard lost); {} for other sinks."""
        if self.config.sink not in CLIENT_SINKS or self._proc is None:
            return {}
        host, port = viewer_address(self.config)
        code = self._failed.value if self._failed is not None else 0
        why = None
        if code == FAIL_NO_VIEWER:
            why = f"nothing listens at {host}:{port}: the dashboard was not delivered"
        elif code == FAIL_CONNECT:
            why = f"connecting to {host}:{port} failed: the dashboard was not delivered"
        elif code == FAIL_FLUSH:
            why = f"the viewer at {host}:{port} did not take the whole dashboard within {self.config.flush_timeout:g} s"
        elif terminated:
            why = f"the telemetry process did not finish sending to {host}:{port}: delivery not confirmed"
        return {"delivered": why is None, "write_error": why}

    def _finish(self) -> dict[str, Any]:
        """Add the .rrd's footer: ``{"footer": True}``, or False and ``footer_error`` (why not; the
        file is complete all the same, so this is no write error)."""
        if self.config.sink != "rrd" or not self.config.rrd_path:
            return {"footer": None, "footer_error": None}
        if not self._written()["written"]:
            return {"footer": False, "footer_error": "not added: the file was not fully written"}
        why = finish_rrd(self.config.rrd_path, self.config.finish_timeout, self.config.min_free_bytes)
        if why is not None:
            log.warning("telemetry: %s has no rerun footer (RrdReader.store(), `rerun rrd verify` refuse it; "
                        "`rerun rrd filter IN -o OUT` adds one): %s", self.config.rrd_path, why)
        return {"footer": why is None, "footer_error": why}

    def _written(self) -> dict[str, Any]:
        """Whether the .rrd holds what was sent: ``{"written": bool, "write_error": str | None}``.
        A disk found full by the child, a file that is not a regular file or is empty though blocks
        were sent (a write that failed: ENOSPC on the whole file, /dev/full) are write errors."""
        if self.config.sink != "rrd" or not self.config.rrd_path:
            return {"written": None, "write_error": None}
        path = Path(self.config.rrd_path)
        why = None
        if getattr(self, "_failed", None) is not None and self._failed.value == FAIL_DISK_FULL:
            why = f"no space left on the device of {path}: the dashboard stopped early"
        else:
            try:
                st = path.stat()
                import stat as _stat

                if not _stat.S_ISREG(st.st_mode):
                    why = f"{path} is not a regular file: nothing was stored"
                elif st.st_size == 0 and self.sent > 0:
                    why = f"{path} is empty though {self.sent} blocks were sent (a failed write)"
            except FileNotFoundError:
                why = f"{path} was never written: its telemetry process did not open it"
            except OSError as exc:
                why = f"{path}: {exc.strerror or exc}"
        return {"written": why is None, "write_error": why}

    def __enter__(self) -> TelemetryProcess:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
