"""The one contract every hardware path implements.

Lifecycle (as in ros2_control): ``open()`` (configure: connect, set up)
-> ``activate()`` (energize: drive enabled, torque accepted) -> ``read()`` /
``write()`` every tick -> ``safe_stop()`` (zero torque, drive disabled) ->
``close()``. The public methods here are template methods: they keep the
lifecycle state, clamp torque before it leaves the host and make
``safe_stop()``/``close()`` idempotent; subclasses implement the ``_``-prefixed
hooks. Used as a context manager, a backend is opened on entry and always
ends with ``safe_stop()`` then ``close()`` on exit, whatever happened.

Torque commands are per sample: ``write(value)`` holds one torque from now
on; ``write(values, start_seq=s)`` asks for ``values[i]`` to be applied to the
sample whose sequence number is ``s + i`` (a plan; a newer plan replaces the
rest of an older one; samples not covered hold the last value). That lets a
1 kHz loop excite a 662 Hz mode at the backend's own sample rate.
``write(values, start_seq=s, lease=n)`` bounds the hold: the plan's last value
holds for ``n`` samples after the plan, then the torque is zero until a newer
plan. A host that stops planning (stalled, or without fresh feedback) then
leaves the axis coasting instead of accelerating it under a held torque: a
drive in torque mode applies whatever it was last sent, for as long as it is
enabled.

Polarity: ``torque_sign``, ``motor_encoder_sign`` and ``scale_sign`` (each +1 or -1, from the backend's
config) are applied here, so that everything above the backend sees one convention: positive torque
accelerates theta1 positive, and theta2 = x / lead follows theta1. The hooks below work in the device's
own convention (what it is sent, what it reports).
"""

from __future__ import annotations

import enum
import logging
import math
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass
from types import TracebackType
from typing import Annotated, Any, ClassVar

import numpy as np
from pydantic import AfterValidator

from drivers.errors import BackendStateError, DriverError
from rt_ident.errors import ConfigError

log = logging.getLogger(__name__)



def _ordered(v: tuple[float, float]) -> tuple[float, float]:
    if not v[0] < v[1]:
        raise ValueError(f"must be [min, max] in m with min < max, got {list(v)}")
    return v


#: A device's table travel in a config: [min, max] in m on the scale, min < max.
Travel = Annotated[tuple[float, float], AfterValidator(_ordered)]

#: torques closer than this [N m] are the same command: one sum computed in another order differs in its last bits
SAME_TORQUE = 1e-9

_ZERO = np.zeros(1)     # the lease's one-value plan (backends copy what they keep; written every tick)
_ZERO.flags.writeable = False


@dataclass(slots=True, eq=False)
class SampleBlock:
    """All samples a backend produced since the previous ``read()`` (a value: nothing changes one after
    it is made; not frozen only because a frozen dataclass's construction costs twice as much, every
    tick, on every axis).

    Arrays share one length. ``t`` are hardware timestamps [s] (the device's
    clock where it has one), ``seq`` monotonically increasing sequence numbers
    (a gap means lost samples), ``theta1`` motor angle [rad], ``theta2`` table
    angle x/l [rad], ``torque_cmd`` the host command in force for that sample
    [N m], ``torque_meas`` the torque the device reports applying [N m] or
    ``None`` when the hardware has no such signal.
    """

    t: np.ndarray
    seq: np.ndarray
    theta1: np.ndarray
    theta2: np.ndarray
    torque_cmd: np.ndarray
    torque_meas: np.ndarray | None = None
    lost: int = 0  # samples known lost in this block (sequence gaps)

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @property
    def torque(self) -> np.ndarray:
        """The best torque signal: measured when available, else commanded."""
        return self.torque_meas if self.torque_meas is not None else self.torque_cmd

    @staticmethod
    def empty(with_measured: bool = False) -> SampleBlock:
        z = np.empty(0)
        return SampleBlock(z, np.empty(0, dtype=np.int64), z, z, z, z if with_measured else None)


#: the identity keys that name one physical unit (the board's INFO, the drive's 0x1018)
UNIT_KEYS = ("vendor_id", "product_code", "model", "serial_number")


def unit_of(identity: Mapping[str, Any]) -> dict[str, Any] | None:
    """The unit a device says it is (its serial number, with the model or vendor and product it is
    unique within); None when it reports no serial number (0 or absent: no unit can be told apart)."""
    if not identity.get("serial_number"):
        return None
    return {k: identity[k] for k in UNIT_KEYS if identity.get(k) is not None}


#: the settings a device may report (the board's INFO) that the host must be told the same: the scales of
#: its angles and the period of its samples
DEVICE_SETTINGS = ("counts_per_rev", "scale_resolution", "sample_rate_hz")


def settings_differ(identity: Mapping[str, Any], options: Mapping[str, Any]) -> dict[str, tuple[float, float]]:
    """``{key: (the device's, the config's)}`` for each of :data:`DEVICE_SETTINGS` the device reports
    (non-zero: zero is "not configured") unlike the config's backend ``options``."""
    out = {}
    for k in DEVICE_SETTINGS:
        dev, told = identity.get(k), options.get(k)
        if isinstance(dev, (int, float)) and dev and isinstance(told, (int, float)) \
                and not math.isclose(float(dev), float(told), rel_tol=1e-6):
            out[k] = (float(dev), float(told))
    return out


def describe_unit(unit: Mapping[str, Any] | None) -> str:
    """``serial 7 (model emulated-board)``; "a unit that reports no serial number" for None."""
    if not unit:
        return "a unit that reports no serial number"
    rest = ", ".join(f"{k.replace('_', ' ')} {v:#x}" if isinstance(v, int) else f"{k} {v}"
                     for k, v in unit.items() if k != "serial_number")
    return f"serial {unit['serial_number']}" + (f" ({rest})" if rest else "")


def _sign(cfg: Mapping[str, Any], key: str) -> int:
    v = cfg.get(key, 1)
    if isinstance(v, bool) or v not in (1, -1):
        raise ConfigError(f"backend.{key}", f"must be 1 or -1, got {v!r}")
    return int(v)


class State(enum.Enum):
    CREATED = "created"
    OPEN = "open"
    ACTIVE = "active"
    STOPPED = "stopped"
    CLOSED = "closed"


class Backend(ABC):
    """Base class of every backend. Constructors do no I/O."""

    #: registry name, e.g. "sim"
    name: ClassVar[str] = "base"

    def __init__(self, config: Mapping[str, Any] | None = None) -> None:
        cfg = dict(config or {})
        limit = cfg.get("torque_limit", math.inf)
        try:
            limit = float(limit)
        except (TypeError, ValueError):
            raise ConfigError("backend.torque_limit", f"must be a number, got {limit!r}") from None
        if not limit > 0:
            raise ConfigError("backend.torque_limit", f"must be > 0, got {limit!r}")
        self.torque_limit: float = limit
        self.torque_sign = _sign(cfg, "torque_sign")
        self.motor_encoder_sign = _sign(cfg, "motor_encoder_sign")
        self.scale_sign = _sign(cfg, "scale_sign")
        self.state = State.CREATED
        self.clamped = 0            # commands clamped to the torque limit
        self.last_torque = 0.0      # last value that left the host
        self.stop_cause: str | None = None
        self.stop_unconfirmed: str | None = None  # after safe_stop(): what the device did not confirm (None: all)
        self._link_at_close = ""    # the link as close() found it (link_trouble() after the device is released)

    # ----- properties each backend provides --------------------------------
    @property
    @abstractmethod
    def sample_period(self) -> float:
        """Nominal time between samples [s]."""

    @property
    def has_measured_torque(self) -> bool:
        return False

    # ----- lifecycle (template methods) ------------------------------------
    def open(self) -> Backend:
        if self.state is not State.CREATED:
            raise BackendStateError(f"open() in state {self.state.value}")
        self._open()
        self.state = State.OPEN
        return self

    def activate(self) -> None:
        if self.state is not State.OPEN:
            raise BackendStateError(f"activate() in state {self.state.value}")
        self._activate()
        self.state = State.ACTIVE

    def read(self) -> SampleBlock:
        if self.state is not State.ACTIVE:
            raise BackendStateError(f"read() in state {self.state.value}")
        block = self._read()
        if self.torque_sign == self.motor_encoder_sign == self.scale_sign == 1:
            return block
        return self._to_host(block)

    def _to_host(self, b: SampleBlock) -> SampleBlock:
        """A device block in the host's convention (the signs; see the module docstring)."""
        st, s1, s2 = self.torque_sign, self.motor_encoder_sign, self.scale_sign
        return SampleBlock(b.t, b.seq, b.theta1 if s1 == 1 else -b.theta1, b.theta2 if s2 == 1 else -b.theta2,
                           b.torque_cmd if st == 1 else -b.torque_cmd,
                           None if b.torque_meas is None else b.torque_meas if st == 1 else -b.torque_meas,
                           b.lost)

    @property
    def signs(self) -> dict[str, int]:
        """The polarity settings in force (host side)."""
        return {"torque_sign": self.torque_sign, "motor_encoder_sign": self.motor_encoder_sign,
                "scale_sign": self.scale_sign}

    def identity(self) -> dict[str, Any]:
        """What the device says it is, while open (before or after activation): identity objects,
        limits, polarity. Empty when the device has nothing to say."""
        if self.state not in (State.OPEN, State.ACTIVE):
            raise BackendStateError(f"identity() in state {self.state.value}")
        return self._identity()

    def _identity(self) -> dict[str, Any]:
        return {}

    def read_position(self) -> tuple[float, float] | None:
        """(theta1, theta2) [rad] while open and not yet active: where the axis is before anything is
        energized (the run checks it against the window and the reference). None: the device cannot
        say before it streams."""
        if self.state is not State.OPEN:
            raise BackendStateError(f"read_position() in state {self.state.value}")
        pos = self._read_position()
        if pos is None:
            return None
        return self.motor_encoder_sign * pos[0], self.scale_sign * pos[1]

    def _read_position(self) -> tuple[float, float] | None:
        return None

    #: a simulation in this process (the loop reports its stepping apart from the tick's work)
    simulated = False

    @property
    def samples_in_real_time(self) -> bool:
        """Whether the device samples on a clock that runs on while the host stalls (so a stalled host
        has a backlog to read); False for a simulation that makes samples only when read."""
        return True

    def read_phase(self) -> float | None:
        """Seconds from now until a sample the device takes on the host's signal (a SYNC the host sends)
        has been answered, or None: the device samples on its own clock. The loop puts its ticks there
        (modulo the sample period): each tick then reads the newest sample, and the torque it plans
        makes the next one, the one-tick delay the controller is designed with."""
        return None

    def fault_detail(self) -> str:
        """What the device said about its own fault once it was stopped ("; ..."), or "": for a fault the
        run saw only as a state, the device's error code read afterwards."""
        return ""

    def link_trouble(self) -> str:
        """What was failing on the link to the device when a host-side check stopped the run ("; ..."), or
        "": a trip can be the first sign of a link that went while the device held its last torque. Once
        closed: as the close found it, after the safe stop (which gave a vanishing link time to show)."""
        return self._link_at_close if self.state is State.CLOSED else self._link_trouble()

    def _link_trouble(self) -> str:
        """The hook of :meth:`link_trouble` on an open device."""
        return ""

    def step_ahead(self, seconds: float) -> None:  # noqa: B027 - optional: a real device needs nothing
        """Called by the loop after each tick with the time to its next deadline: a simulated device
        may produce the samples due by then now, so that read() only hands them out (the sim does,
        in paced mode). A real device produces them by itself: nothing to do."""

    def write(self, torque: float | np.ndarray, *, start_seq: int | None = None, lease: int | None = None) -> None:
        """Send a torque command, clamped to ``torque_limit`` before it leaves the host.

        ``lease`` (plans only): samples the plan's last value holds after the plan ends before the
        command drops to zero - sent now, as a one-value plan of 0 that far ahead (every backend's
        plan keeps an older plan's last value across a gap, and a newer plan replaces it).
        """
        if self.state is not State.ACTIVE:
            raise BackendStateError(f"write() in state {self.state.value}")
        values = np.asarray(torque, dtype=float)
        lim = self.torque_limit
        # this runs every tick for every axis, on a plan of a few dozen values. Fast path, one dot
        # product: a sum of squares within limit^2 bounds every |value| by the limit, and a NaN or an
        # inf makes the sum NaN or inf (so does overflow: then the exact check below decides)
        if values.size and not float(values.ravel() @ values.ravel()) <= lim * lim:
            hi, lo = float(values.max()), float(values.min())
            if not (math.isfinite(hi) and math.isfinite(lo)):
                raise DriverError("non-finite torque command refused")
            if hi > lim or lo < -lim:
                self.clamped += int(np.count_nonzero(np.abs(values) > lim))
                values = np.clip(values, -lim, lim)
        sent = values if self.torque_sign == 1 else -values
        if values.ndim == 0:
            self._write_hold(float(sent))
            self.last_torque = float(values)
        else:
            if start_seq is None:
                raise DriverError("a torque plan (array) needs start_seq")
            if lease is not None and values.size and lease >= 0:
                self._write_leased_plan(sent, int(start_seq), int(lease))
            else:
                self._write_plan(sent, int(start_seq))
            if values.size:
                self.last_torque = float(values[-1])
                if lease is not None and lease < 0:
                    raise DriverError(f"lease must be >= 0 samples, got {lease}")

    def safe_stop(self, cause: str | None = None) -> None:
        """Quick stop -> zero torque -> drive disabled. Idempotent; never raises.

        Failures while stopping are logged: the caller is already on its way out
        and a second exception would hide the first.
        """
        if self.state in (State.STOPPED, State.CLOSED, State.CREATED):
            return
        if cause and self.stop_cause is None:
            self.stop_cause = cause
        try:
            self.stop_unconfirmed = self._safe_stop()
        except Exception as exc:  # noqa: BLE001 - must not raise from a stop path
            log.exception("%s: safe_stop failed", self.name)
            self.stop_unconfirmed = f"the stop failed: {type(exc).__name__}: {exc}"
        self.last_torque = 0.0
        self.state = State.STOPPED

    def close(self) -> None:
        """Release the device. Idempotent; always stops first."""
        if self.state is State.CLOSED:
            return
        self.safe_stop()
        try:
            self._link_at_close = self._link_trouble()
        except Exception:  # noqa: BLE001 - a diagnosis, never a reason not to close
            log.exception("%s: looking at the link failed", self.name)
        try:
            self._close()
        except Exception:  # noqa: BLE001
            log.exception("%s: close failed", self.name)
        self.state = State.CLOSED

    def __enter__(self) -> Backend:
        return self.open()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        cause = None
        if exc is not None:
            cause = getattr(exc, "cause", type(exc).__name__)
        self.safe_stop(cause)
        self.close()

    # ----- hooks ----------------------------------------------------------
    @abstractmethod
    def _open(self) -> None: ...

    @abstractmethod
    def _activate(self) -> None: ...

    @abstractmethod
    def _read(self) -> SampleBlock: ...

    @abstractmethod
    def _write_hold(self, torque: float) -> None: ...

    @abstractmethod
    def _write_plan(self, torques: np.ndarray, start_seq: int) -> None:
        """Keep ``torques`` for samples ``start_seq`` on (copy them: the caller may reuse its array)."""

    def _write_leased_plan(self, torques: np.ndarray, start_seq: int, lease: int) -> None:
        """A plan and its lease (``write(..., lease=)``): the plan, then a one-value plan of 0 ``lease``
        samples after its end. A backend whose device or sender can act between the two calls does both
        as one step (the sim in one compiled call, the board in one write, CANopen under the sender's
        lock): a host that stops in between would leave the plan's last value held with no end."""
        self._write_plan(torques, start_seq)
        self._write_plan(_ZERO, start_seq + torques.size + lease)

    @abstractmethod
    def _safe_stop(self) -> str | None:
        """Quick stop, zero torque, disable. Called at most once per activation. Returns None when the device
        confirmed its disable (or was never enabled by this host), else one line: what was not confirmed, and
        what the device does on its own once the host falls silent."""

    @abstractmethod
    def _close(self) -> None: ...
