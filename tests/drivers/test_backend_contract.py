"""One contract suite for every backend: the rules of :mod:`drivers.base` checked on real traffic.

The ``rig`` fixture is parametrized over ``sim``, ``canopen-emulated`` (CiA 402 drive
emulator on a fresh in-process python-can ``virtual`` channel), ``canopen-emulated:<variant>``
(the same as each vendor variant our master adapts to) and ``serial-emulated``
(board emulator on a pty), plus one ``hardware:<config>`` param per ``--hardware-config``
(marked ``hardware``: skipped unless ``--hardware``). Each test gets a freshly
constructed, not opened backend and, for emulated devices, a view of the device side
(:class:`DeviceView`); on real hardware there is no device view and only host-side
checks run. Teardown closes the backend, stops the emulator and fails if threads or
child processes started by the test are still alive.

Torques stay small: the host limit is :data:`CONTRACT_LIMIT` (or the config's, if
lower) and test commands are 40 % of it. Emulated drives run without a position-hold
loop (like a real drive in cyclic synchronous torque mode), so the device's applied
torque equals the command it received; their own torque limit is 1 N m, above the
host limit, so a host clamp failure would be visible on the device side.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import threading
import time
import tomllib
import uuid
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from drivers import make_backend
from drivers.base import Backend, SampleBlock, State
from drivers.errors import BackendStateError, DriverError
from rt_ident.axis.params import CONFIG_DIR

CONTRACT_LIMIT = 0.05   # N m: host torque limit during the contract run
FRACTION = 0.4          # test commands are this fraction of the limit
DEADLINE = 3.0          # s: every wait for data or a device reaction is bounded by this
HW_SETTLE = 0.3         # s: on real hardware a torque must be in force this soon (bounds the axis' travel)
STOP_GRACE = 1.0        # s: a stopped device must show zero torque and disabled within this
DEVICE_LIMIT = 1.0      # N m: power-stage limit of the emulated devices (above CONTRACT_LIMIT)
#: Drive variants (drivers.cia402.variants) our CANopen master adapts to, each a rig of its own; the others
#: it refuses (tests/drivers/test_drive_variants.py)
CANOPEN_VARIANTS = ["four-objects-per-pdo", "two-objects-per-pdo", "interpolation-period", "polarity-set",
                    "sync-counter"]
EMULATED = ["sim", "canopen-emulated", "serial-emulated"] + [f"canopen-emulated:{v}" for v in CANOPEN_VARIANTS]


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    if "rig" not in metafunc.fixturenames:
        return
    params: list[Any] = list(EMULATED)
    paths = [p.strip() for v in metafunc.config.getoption("--hardware-config") or [] for p in str(v).split(",")]
    paths = list(dict.fromkeys(p for p in paths if p))
    if metafunc.config.getoption("--hardware") and not paths:
        paths = [""]                      # fails in the fixture with a usage message
    params += [pytest.param(f"hardware:{p}", marks=pytest.mark.hardware, id=f"hardware:{p}") for p in paths]
    metafunc.parametrize("rig", params, indirect=True)


# ----- the rig --------------------------------------------------------------------------------
@dataclass
class DeviceView:
    """The device side of an emulated rig: what the power stage does, not what the host believes."""

    obj: Any                        # the emulator (or the sim backend, which holds the plant)
    torque: Callable[[], float]     # torque applied now [N m]
    enabled: Callable[[], bool]     # power stage on (any state that may apply torque)
    state: Callable[[], str]        # for messages (402 state, board status)

    def de_energized(self) -> bool:
        return not self.enabled() and self.torque() == 0.0


@dataclass
class Rig:
    kind: str
    backend: Backend
    device: DeviceView | None       # None on real hardware
    settle: float = DEADLINE        # s allowed for a torque command to be in force

    @property
    def command(self) -> float:
        return FRACTION * self.backend.torque_limit

    def tol(self) -> float:
        """Torque comparison tolerance [N m]: wire quantization (per mille of rated torque on CANopen)."""
        rated = getattr(self.backend, "rated_torque", math.nan)
        quantum = rated / 1000.0 if isinstance(rated, float) and math.isfinite(rated) else 0.0
        return max(1e-3, 0.51 * quantum)


def _toml(name: str) -> dict:
    return tomllib.loads((CONFIG_DIR / name).read_text())


def _sim_rig(stack: ExitStack) -> Rig:
    data = _toml("sim.toml")
    opts = {k: v for k, v in data["backend"].items() if k not in ("name", "emulate")}
    opts.update(axis=data["axis"], torque_limit=CONTRACT_LIMIT, position_hold=False, travel=None)
    be = make_backend("sim", opts)
    stack.callback(be.close)
    return Rig("sim", be, DeviceView(be, lambda: be.applied_torque, lambda: be.drive_enabled,
                                     lambda: "enabled" if be.drive_enabled else "disabled"))


def _canopen_rig(stack: ExitStack, profile: str = "generic") -> Rig:
    from drivers.cia402 import profile as p402
    from drivers.cia402.emulator import start_emulator_for

    data = _toml("canopen-virtual.toml")
    backend = {k: v for k, v in data["backend"].items() if k not in ("emulate", "port", "bus_options")}
    # own in-process bus per test; 500 Hz SYNC and lenient watchdogs (0.5 s of stale TPDOs, 1 s of heartbeat
    # silence, 200 ms between RPDOs) so that stalls on a loaded 2-core machine do not trip them: the drive
    # and the host's SYNC thread share this process, which is not real-time
    backend.update(interface="virtual", channel=f"contract-{uuid.uuid4().hex[:12]}", torque_limit=CONTRACT_LIMIT,
                   sync_rate_hz=500, stale_limit=250, startup_timeout=3.0, heartbeat_consumer_ms=1000,
                   rpdo_deadline_ms=200)
    emulator = {**data.get("emulator", {}), "position_hold": False, "travel": None, "faults": {},
                "torque_limit": DEVICE_LIMIT, "profile": profile}
    drive = start_emulator_for({"backend": backend, "emulator": emulator, "axis": data["axis"]})
    stack.callback(drive.stop)
    be = make_backend("canopen", backend)
    stack.callback(be.close)
    live = (p402.SWITCHED_ON, p402.OPERATION_ENABLED, p402.QUICK_STOP_ACTIVE, p402.FAULT_REACTION_ACTIVE)
    # the torque in the drive's own frame, the one the host commands in (position polarity reverses it at
    # the motor)
    return Rig("canopen-emulated" + ("" if profile == "generic" else f":{profile}"), be,
               DeviceView(drive, lambda: drive.applied_torque * drive.polarity_sign,
                          lambda: drive.state in live, lambda: drive.state))


def _serial_rig(stack: ExitStack) -> Rig:
    from drivers.encoder_board.config import parse_emulator, parse_serial
    from drivers.encoder_board.emulator import board_for
    from rt_ident.axis.params import AxisParams

    data = _toml("serial-virtual.toml")
    backend = {k: v for k, v in data["backend"].items() if k not in ("name", "emulate", "port")}
    # a stalled test thread must delay data, not lose it or trip the board's heartbeat watchdog; that
    # watchdog (2 s) is longer than STOP_GRACE, so it cannot pass the stop tests in place of safe_stop()
    emulator = {**data.get("emulator", {}), "hold": False, "travel": None, "heartbeat_timeout": 2.0,
                "tx_buffer": 1 << 24}
    board = board_for(parse_serial({**backend, "port": "-", "torque_limit": DEVICE_LIMIT}),
                      parse_emulator(emulator), AxisParams.from_mapping(data["axis"], where="axis"))
    stack.callback(board.stop)
    board.start()
    # host timeouts lengthened for the same reason (a starved board thread neither sends nor drains the pty)
    be = make_backend("serial", {**backend, "port": board.port, "torque_limit": CONTRACT_LIMIT,
                                 "read_timeout": 0.5, "write_timeout": 0.5,
                                 "startup_timeout": 3.0})
    stack.callback(be.close)
    return Rig("serial-emulated", be, DeviceView(board, lambda: board.applied_torque, lambda: board.enabled,
                                                 lambda: f"enabled={board.enabled} status=0x{board.status:04X}"))


def _hardware_backend(path: str, devices: dict[str, Any]) -> Rig:
    """The backend a run config names, with the host torque limit lowered to CONTRACT_LIMIT."""
    from rt_ident.config import load

    if not path:
        pytest.fail("--hardware needs --hardware-config PATH (a run config naming the real device)")
    cfg = load(path)
    opts = cfg.backend.options()
    if cfg.backend.name == "sim":
        opts.setdefault("axis", cfg.axis_params().as_dict())
    limit = float(opts.get("torque_limit", CONTRACT_LIMIT))
    opts["torque_limit"] = min(limit, CONTRACT_LIMIT)
    if cfg.backend.name == "canopen" and "stuck_torque_min" not in opts:
        opts["stuck_torque_min"] = 0.05 * limit   # keep the config's stuck-encoder threshold (default 5 %)
    emulator = devices.get(path)
    if emulator is not None and getattr(emulator, "port", None):
        opts["port"] = emulator.port
    return Rig(f"hardware:{path}", make_backend(cfg.backend.name, opts), None, settle=HW_SETTLE)


@pytest.fixture(scope="module")
def hardware_devices() -> Iterator[dict[str, Any]]:
    """Emulators that ``--hardware-config`` files ask for (``emulate = true``), one per config, shared like a
    real device is; started on first use, stopped at the end of the module."""
    devices: dict[str, Any] = {}
    yield devices
    for dev in devices.values():
        (getattr(dev, "close", None) or dev.stop)()


def _start_config_emulator(path: str, devices: dict[str, Any]) -> None:
    if not path or path in devices:
        return
    from rt_ident.config import load
    from rt_ident.processes.emulation import start_emulator

    cfg = load(path)
    if cfg.backend.emulate:
        devices[path] = start_emulator(cfg)


@pytest.fixture
def rig(request: pytest.FixtureRequest, hardware_devices: dict[str, Any]) -> Iterator[Rig]:
    kind: str = request.param
    hw_path = kind.removeprefix("hardware:") if kind.startswith("hardware:") else None
    if hw_path is not None:
        _start_config_emulator(hw_path, hardware_devices)
    # a config's emulator is shared by the tests (like a real device): its threads are not this test's
    check_threads = hw_path is None or hw_path not in hardware_devices
    threads_before = set(threading.enumerate())
    procs_before = set(mp.active_children())
    with ExitStack() as stack:
        if hw_path is not None:
            made = _hardware_backend(hw_path, hardware_devices)
            stack.callback(made.backend.close)
        else:
            if kind.startswith("canopen-emulated:"):
                made = _canopen_rig(stack, kind.split(":", 1)[1])
            else:
                made = {"sim": _sim_rig, "canopen-emulated": _canopen_rig, "serial-emulated": _serial_rig}[kind](stack)
        assert made.backend.state is State.CREATED
        yield made
    # the stack closed the backend first, then stopped the emulator (LIFO)
    end = time.monotonic() + DEADLINE
    while True:
        left = [t for t in threading.enumerate() if t not in threads_before and t.is_alive()] if check_threads else []
        procs = [p for p in mp.active_children() if p not in procs_before]
        if not (left or procs) or time.monotonic() > end:
            break
        time.sleep(0.01)
    assert not left, f"threads left running after teardown: {[t.name for t in left]}"
    assert not procs, f"child processes left running after teardown: {procs}"


# ----- helpers --------------------------------------------------------------------------------
def pump(backend: Backend, until: Callable[[list[SampleBlock]], bool], timeout: float = DEADLINE
         ) -> list[SampleBlock]:
    """Read about every millisecond until ``until(non-empty blocks so far)`` or the deadline."""
    blocks: list[SampleBlock] = []
    end = time.monotonic() + timeout
    while True:
        blk = backend.read()
        if len(blk):
            blocks.append(blk)
        if until(blocks) or time.monotonic() > end:
            return blocks
        time.sleep(0.001)


def wait_until(pred: Callable[[], bool], timeout: float = DEADLINE) -> bool:
    end = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > end:
            return pred()
        time.sleep(0.002)
    return True


def n_samples(blocks: list[SampleBlock]) -> int:
    return sum(len(b) for b in blocks)


def cat(blocks: list[SampleBlock], field: str) -> np.ndarray:
    return np.concatenate([getattr(b, field) for b in blocks])


def settle_on(rig: Rig, torque: float) -> list[SampleBlock]:
    """Pump until the host reports ``torque`` in force and (emulated) the device applies it; assert both."""
    tol, dev = rig.tol(), rig.device

    def done(blocks: list[SampleBlock]) -> bool:
        host = bool(blocks) and abs(float(blocks[-1].torque_cmd[-1]) - torque) <= tol
        return host and (dev is None or abs(dev.torque() - torque) <= tol)

    blocks = pump(rig.backend, done, rig.settle)
    assert done(blocks), (f"torque {torque:+.4f} N m not in force within {rig.settle} s: host reports "
                          f"{blocks[-1].torque_cmd[-1] if blocks else None}, device "
                          f"{dev.torque() if dev else 'n/a'}")
    return blocks


def assert_de_energized(rig: Rig) -> None:
    dev = rig.device
    if dev is not None:
        assert wait_until(dev.de_energized, STOP_GRACE), (f"device still energized: torque {dev.torque()} N m, "
                                              f"state {dev.state()}")


# ----- lifecycle --------------------------------------------------------------------------------
def test_read_and_write_before_activate_raise_backend_state_error(rig: Rig) -> None:
    be = rig.backend
    assert math.isfinite(be.sample_period) and be.sample_period > 0
    for _ in ("created", "open"):
        with pytest.raises(BackendStateError):
            be.read()
        with pytest.raises(BackendStateError):
            be.write(rig.command)
        if be.state is State.CREATED:
            be.open()
    assert be.state is State.OPEN and be.last_torque == 0.0
    if rig.device is not None:
        assert rig.device.de_energized(), f"open() energized the device: {rig.device.state()}"


def test_active_read_returns_equal_length_float64_blocks_with_increasing_seq_and_time(rig: Rig) -> None:
    be = rig.backend
    be.open()
    be.activate()
    assert be.state is State.ACTIVE
    blocks = pump(be, lambda b: len(b) >= 2 and n_samples(b) >= 20)
    assert len(blocks) >= 2 and n_samples(blocks) >= 20, f"only {n_samples(blocks)} samples in {DEADLINE} s"
    for blk in blocks:
        assert isinstance(blk, SampleBlock)
        n = len(blk)
        fields = [blk.t, blk.seq, blk.theta1, blk.theta2, blk.torque_cmd]
        assert all(a.shape == (n,) for a in fields)
        assert (blk.torque_meas is not None) == be.has_measured_torque
        if blk.torque_meas is not None:
            assert blk.torque_meas.shape == (n,)
        assert blk.theta1.dtype == np.float64 and blk.theta2.dtype == np.float64
        assert np.issubdtype(blk.seq.dtype, np.integer)
        assert isinstance(blk.lost, int) and blk.lost >= 0
    seq, t = cat(blocks, "seq"), cat(blocks, "t")
    assert np.all(np.diff(seq) > 0), "seq must increase strictly, also across reads"
    assert np.all(np.diff(t) >= 0), "t must not decrease, also across reads"
    for name in ("t", "theta1", "theta2", "torque_cmd"):
        assert np.all(np.isfinite(cat(blocks, name))), name


def test_blocks_cover_consecutive_sequence_numbers_unless_lost_says_so(rig: Rig) -> None:
    be = rig.backend
    be.open()
    be.activate()
    want = max(20, math.ceil(0.05 / be.sample_period))
    blocks = pump(be, lambda b: len(b) >= 4 and n_samples(b) >= want)
    assert len(blocks) >= 4, f"only {len(blocks)} non-empty reads in {DEADLINE} s"
    prev = None
    for blk in blocks:
        gaps = int(np.sum(np.diff(blk.seq) - 1))
        if prev is None:          # what preceded the first delivered sample is backend-specific
            assert gaps <= blk.lost, f"first block: {gaps} samples missing inside, lost = {blk.lost}"
        else:
            gaps += int(blk.seq[0]) - prev - 1
            assert gaps == blk.lost, f"block from seq {blk.seq[0]}: {gaps} samples missing, lost = {blk.lost}"
        prev = int(blk.seq[-1])


# ----- torque commands ----------------------------------------------------------------------------
def test_write_beyond_torque_limit_is_clamped_before_it_leaves_the_host(rig: Rig) -> None:
    be, dev = rig.backend, rig.device
    lim, tol = be.torque_limit, rig.tol()
    assert lim <= CONTRACT_LIMIT
    be.open()
    be.activate()
    be.write(3.0 * lim)
    assert be.clamped == 1 and be.last_torque == lim
    blocks = settle_on(rig, lim)
    if dev is not None:
        assert abs(dev.torque()) <= lim + tol
    be.write(-3.0 * lim)
    assert be.clamped == 2 and be.last_torque == -lim
    blocks += settle_on(rig, -lim)
    if dev is not None:
        assert abs(dev.torque()) <= lim + tol
    assert np.all(np.abs(cat(blocks, "torque_cmd")) <= lim + tol)
    nxt = int(blocks[-1].seq[-1]) + 1
    be.write(np.array([0.5 * lim, -4.0 * lim, 0.0]), start_seq=nxt)   # plans are clamped per value too
    assert be.clamped == 3 and be.last_torque == 0.0


def test_write_refuses_non_finite_torque_and_keeps_the_last_command(rig: Rig) -> None:
    be = rig.backend
    c = rig.command
    be.open()
    be.activate()
    be.write(c)
    blocks = settle_on(rig, c)
    nxt = int(blocks[-1].seq[-1]) + 1
    for bad in (math.nan, math.inf, -math.inf):
        with pytest.raises(DriverError, match="non-finite") as err:
            be.write(bad)
        assert not isinstance(err.value, BackendStateError)
    with pytest.raises(DriverError, match="non-finite"):
        be.write(np.array([0.0, math.nan]), start_seq=nxt)
    assert be.last_torque == c and be.clamped == 0
    after = pump(be, lambda b: n_samples(b) >= 10)
    assert n_samples(after) >= 10
    assert np.allclose(cat(after, "torque_cmd"), c, atol=rig.tol()), "a refused write changed the torque"
    if rig.device is not None:
        assert abs(rig.device.torque() - c) <= rig.tol()


def test_torque_plan_needs_start_seq_and_lands_on_those_sample_numbers(rig: Rig) -> None:
    """Plan values apply at exactly ``start_seq + i``. Values that reach the device after their sample
    (a loaded host) are dropped and the previous value holds: a late head of the plan is allowed, a
    shifted plan is not (the plan's sign changes must sit exactly at their sample numbers)."""
    be, c, tol = rig.backend, rig.command, rig.tol()
    be.open()
    be.activate()
    dt = be.sample_period
    with pytest.raises(DriverError, match="start_seq"):
        be.write(np.array([c, c]))
    assert be.last_torque == 0.0
    q = max(2, math.ceil(0.0125 / dt))
    # +c, -c, +c (zero net speed and travel on a free axis), then 0 holds
    plan = np.concatenate([np.full(q, c), np.full(2 * q, -c), np.full(q, c), [0.0]])
    verified = False
    for _ in range(5):        # samples may be lost or the plan late on a loaded machine: up to 5 plans
        # catch up with the device first (a read returning under ~5 ms of samples), then plan 0.1 s ahead
        blocks = pump(be, lambda b: len(b) >= 2 and len(b[-1]) <= max(2, 0.005 / dt))
        assert blocks, f"no samples in {DEADLINE} s"
        start = int(blocks[-1].seq[-1]) + max(10, math.ceil(0.1 / dt))
        be.write(plan, start_seq=start)
        assert be.last_torque == 0.0

        def done(b: list[SampleBlock], end: int = start + plan.size + 5) -> bool:
            return bool(b) and int(b[-1].seq[-1]) >= end and abs(float(b[-1].torque_cmd[-1])) <= tol

        blocks = pump(be, done)
        assert done(blocks), "the plan's samples did not arrive, or its last value (0) does not hold"
        seq, cmd = cat(blocks, "seq"), cat(blocks, "torque_cmd")
        assert np.allclose(cmd[seq < start], 0.0, atol=tol), "the plan was applied before its start_seq"
        k, got = seq[seq >= start] - start, cmd[seq >= start]
        want = plan[np.minimum(k, plan.size - 1)]      # after the plan its last value holds
        moved = np.abs(got) > tol
        late = int(np.argmax(moved)) if np.any(moved) else k.size   # late head: the old value (0) held
        assert np.allclose(got[late:], want[late:], atol=tol), "plan values not at their sample numbers"
        # verified when an applied plan value precedes the first sign change and one follows it
        if late < k.size and k[late] < q and np.any((k >= q) & (k < 3 * q)):
            verified = True
            break
    assert verified, "no plan was delivered around its sign change in 5 tries"


def test_a_leased_plan_holds_its_last_value_for_the_lease_then_the_torque_is_zero(rig: Rig) -> None:
    """``write(plan, start_seq=s, lease=n)`` and nothing more: the last value holds ``n`` samples past the
    plan, then zero reaches the device - a host that stops planning leaves the axis coasting."""
    be, c, tol = rig.backend, rig.command, rig.tol()
    be.open()
    be.activate()
    dt = be.sample_period
    q = max(2, math.ceil(0.0125 / dt))
    plan = np.concatenate([np.full(2 * q, c), np.full(q, -c)])    # +c 2q, -c q, then -c held q: no net speed
    verified = False
    for _ in range(5):        # samples may be lost or the plan late on a loaded machine: up to 5 plans
        blocks = pump(be, lambda b: len(b) >= 2 and len(b[-1]) <= max(2, 0.005 / dt))
        assert blocks, f"no samples in {DEADLINE} s"
        start = int(blocks[-1].seq[-1]) + max(10, math.ceil(0.1 / dt))
        be.write(plan, start_seq=start, lease=q)
        assert be.last_torque == -c                    # what the host last planned, not the lease's zero
        end = start + plan.size + q

        def done(b: list[SampleBlock]) -> bool:
            return bool(b) and int(b[-1].seq[-1]) >= end + 5

        blocks = pump(be, done)
        assert done(blocks), "the samples after the lease did not arrive"
        seq, cmd = cat(blocks, "seq"), cat(blocks, "torque_cmd")
        held = (seq >= start + plan.size) & (seq < end)
        after = seq >= end
        assert np.allclose(cmd[after], 0.0, atol=tol), "the torque did not drop to zero when the lease ran out"
        if np.any(held) and np.allclose(cmd[held], -c, atol=tol):   # the plan was on time: its hold is seen
            verified = True
            break
    assert verified, "no plan's lease was seen holding its last value in 5 tries"
    if rig.device is not None:
        assert wait_until(lambda: abs(rig.device.torque()) <= tol), "the device still applies torque"


def test_torque_command_reaches_the_device_within_bounded_reads(rig: Rig) -> None:
    be, c = rig.backend, rig.command
    be.open()
    be.activate()
    for value in (c, -c, 0.0):      # both signs, then back to rest: a stale value cannot pass
        be.write(value)
        assert be.last_torque == value
        settle_on(rig, value)


# ----- stopping ---------------------------------------------------------------------------------
def _count_calls(monkeypatch: pytest.MonkeyPatch, be: Backend, hook: str) -> list[int]:
    calls = [0]
    orig = getattr(be, hook)

    def counted() -> Any:
        calls[0] += 1
        return orig()

    monkeypatch.setattr(be, hook, counted)
    return calls


def test_safe_stop_zeroes_torque_disables_the_drive_and_stop_and_close_are_idempotent(
        rig: Rig, monkeypatch: pytest.MonkeyPatch) -> None:
    be, c = rig.backend, rig.command
    be.open()
    be.activate()
    be.write(c)
    settle_on(rig, c)
    stops, closes = _count_calls(monkeypatch, be, "_safe_stop"), _count_calls(monkeypatch, be, "_close")
    be.safe_stop()
    assert be.state is State.STOPPED and be.last_torque == 0.0
    assert be.stop_unconfirmed is None, be.stop_unconfirmed        # the device reported itself disabled
    assert_de_energized(rig)
    be.safe_stop()
    assert be.state is State.STOPPED and stops[0] == 1
    with pytest.raises(BackendStateError):
        be.write(c)               # a stopped backend cannot be re-energized by a command
    with pytest.raises(BackendStateError):
        be.read()
    be.close()
    be.close()
    assert be.state is State.CLOSED and stops[0] == 1 and closes[0] == 1
    assert_de_energized(rig)


class ContractBoom(Exception):
    """Raised inside a with-block by the context-manager test."""


def test_context_manager_exit_on_exception_ends_with_zero_torque_disabled_and_propagates(rig: Rig) -> None:
    be, c = rig.backend, rig.command
    with pytest.raises(ContractBoom, match="inside the with-block"), be as entered:
        assert entered is be and be.state is State.OPEN
        be.activate()
        be.write(c)
        settle_on(rig, c)
        raise ContractBoom("inside the with-block")
    assert be.state is State.CLOSED and be.last_torque == 0.0 and be.stop_unconfirmed is None
    assert be.stop_cause == "ContractBoom"
    assert_de_energized(rig)


def test_close_without_activate_leaves_nothing_energized(rig: Rig) -> None:
    be, dev = rig.backend, rig.device
    be.open()
    be.close()
    assert be.state is State.CLOSED and be.last_torque == 0.0
    with pytest.raises(BackendStateError):
        be.activate()             # a closed backend cannot be energized
    with pytest.raises(BackendStateError):
        be.write(rig.command)
    if dev is not None:
        end = time.monotonic() + 0.05
        while time.monotonic() < end:   # stays de-energized, not just at one instant
            assert dev.de_energized(), f"device energized after close(): {dev.state()}"
            time.sleep(0.005)
