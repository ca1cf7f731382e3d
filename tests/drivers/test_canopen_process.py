"""The emulated CiA 402 drive in its own process on python-can's udp_multicast bus.

The whole product (``rt_ident.compose.run.run``) runs briefly against
``configs/canopen-virtual.toml`` with its drive in a child process
(:class:`rt_ident.processes.emulation.EmulatorProcess`); each test gets a free UDP port. The
drive's state is read from the report its process sends when it is closed - taken
before the drive leaves the bus, i.e. as the host left it. The runs are real-time like
the product (SCHED_FIFO where permitted; the test process's scheduling, memory locking
and GC are restored afterwards). Thresholds are loose on purpose (a loaded 2-core
machine): the assertions are about data arriving, safe stops and no orphan processes.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import can
import pytest

import rt_ident.compose.run as run_mod
from drivers.cia402 import profile as p402
from drivers.cia402.bus import open_bus
from drivers.cia402.frames import FrameIO
from rt_ident.axis.params import CONFIG_DIR
from rt_ident.config import load
from rt_ident.errors import RtIdentError
from rt_ident.processes.emulation import EmulatorProcess, free_udp_port

CONFIG = CONFIG_DIR / "canopen-virtual.toml"
ROOT = Path(__file__).resolve().parents[2]
GROUP = "239.74.163.2"
_ALL_CPUS = os.sched_getaffinity(0)


def _config(**over):
    base = {"loop.duration": 2.0, "telemetry.sink": "off", "recording.enabled": False,
            "backend.stale_limit": 200,           # a loaded test machine must not trip the watchdog
            # ... nor the drive's heartbeat consumer: a loaded machine can hold the host's heartbeat back
            # for 250 ms (EMCY 0x8130); heartbeat loss is tested in test_canopen_backend
            "backend.heartbeat_consumer_ms": 1000,
            # ... nor the host's own watchdog: the drive process held off for tens of ms sends no fresh data
            "safety.watchdog_ticks": 200,
            # the probe's torque, which the drive holds through the host's late writes: at the shipped 0.3 N m a
            # few ms of lateness in a row took the table past the speed limit (what is tested is the process)
            "excitation.peak": 0.1}
    return load(CONFIG, **{**base, **over})


@pytest.fixture(autouse=True)
def _restore_scheduling(restore_scheduling):
    """Every test here may run the loop real-time (conftest's ``restore_scheduling`` undoes it)."""
    yield


def _gone(pid: int, timeout: float = 5.0) -> bool:
    """The process has exited (a zombie counts as exited)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            with open(f"/proc/{pid}/stat") as fh:
                if fh.read().rsplit(")", 1)[1].split()[0] == "Z":
                    return True
        except (FileNotFoundError, ProcessLookupError):
            return True
        time.sleep(0.05)
    return False


def _assert_drive_left_safe(emu: EmulatorProcess) -> None:
    assert emu.stats is not None, "the emulator did not report"
    assert emu.stats["applied_torque"] == 0.0 and not emu.stats["enabled"]
    assert emu.stats["state"] in (p402.SWITCH_ON_DISABLED, p402.FAULT)
    assert not emu.alive and _gone(emu.pid)


# ----- frames on the wire ------------------------------------------------------------------------
def test_frameio_speaks_python_cans_udp_format_and_does_not_receive_its_own_frames():
    kw = {"interface": "udp_multicast", "channel": GROUP, "port": free_udp_port(), "hop_limit": 0}
    got: list = []
    other, mine = open_bus(kw), open_bus(kw)              # python-can's bus class, confined to this host
    io = FrameIO(mine, got.extend, bus_kwargs=kw).open()
    try:
        assert not io.own_frames_back
        # the kernel turns receive stamping on lazily (a deferred work item) when the first socket on the
        # host asks for it: until then a frame is stamped when it is read. Wait for a frame stamped on arrival.
        end = time.monotonic() + 5.0
        while time.monotonic() < end:
            other.send(can.Message(arbitration_id=0x700, data=b"\x05", is_extended_id=False))
            time.sleep(0.02)
            began = time.monotonic()
            io.pump()
            if got and got[-1][2] < began - 0.01:
                break
        assert got and got[-1][2] < began - 0.01, "no frame stamped on arrival within 5 s"
        got.clear()
        io.send(0x80, b"")
        other.send(can.Message(arbitration_id=0x185, data=b"\x01\x02\x03", is_extended_id=False))
        other.send(can.Message(arbitration_id=0x186, data=b"\x04", is_extended_id=False))
        io.send(0x205, b"\x0f\x00\x10\x00")
        seen = [other.recv(1.0) for _ in range(2)]   # python-can decodes what FrameIO sent, not its own frames
        assert [(m.arbitration_id, bytes(m.data)) for m in seen] == [(0x80, b""), (0x205, b"\x0f\x00\x10\x00")]
        assert not seen[0].is_extended_id and other.recv(0.1) is None
        end = time.monotonic() + 2.0
        while len(got) < 2 and time.monotonic() < end:
            io.pump()
        time.sleep(0.05)
        io.pump()
        assert [(cob, bytes(data)) for cob, data, _ in got] == [(0x185, b"\x01\x02\x03"), (0x186, b"\x04")]
        assert got[0][2] <= got[1][2] <= time.monotonic()   # kernel arrival times, monotonic
        assert io.dropped == 0 and io.malformed == 0
    finally:
        io.close()
        other.shutdown()
        mine.shutdown()


def _non_loopback_ipv4() -> str | None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.connect(("192.0.2.1", 9))                  # no packet is sent: this only picks the route's source
            ip = s.getsockname()[0]
        except OSError:
            return None
    return None if ip.startswith("127.") else ip


def test_the_emulated_bus_ignores_frames_from_the_network_and_keeps_those_of_the_host():
    ip = _non_loopback_ipv4()
    if ip is None:
        pytest.skip("this machine has no non-loopback IPv4 address")
    kw = {"interface": "udp_multicast", "channel": GROUP, "port": free_udp_port(), "hop_limit": 1}
    got: list = []
    mine, peer = open_bus(kw), open_bus(kw)
    io = FrameIO(mine, got.extend, bus_kwargs=kw).open()
    try:
        sock = mine._multicast._socket
        assert sock.getsockname()[0] == GROUP                 # bound to the group, not 0.0.0.0
        assert sock.getsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL) == 0     # hop_limit 1 overridden
        emcy = can.Message(arbitration_id=0x85, data=bytes(8), is_extended_id=False)
        from can.interfaces.udp_multicast.utils import pack_message

        evil = pack_message(emcy)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            for _ in range(50):                              # to this host's own address, and to the group
                tx.sendto(evil, (ip, kw["port"]))            # from the LAN side
                tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(ip))
                tx.sendto(evil, (GROUP, kw["port"]))
        peer.send(can.Message(arbitration_id=0x80, is_extended_id=False))   # one legitimate frame from this host
        end = time.monotonic() + 1.0
        while not got and time.monotonic() < end:
            io.pump()
        time.sleep(0.1)
        io.pump()
        assert [(cob, bytes(d)) for cob, d, _ in got] == [(0x80, b"")], got
    finally:
        io.close()
        mine.shutdown()
        peer.shutdown()


# ----- the whole product ---------------------------------------------------------------------------
#: runs a test makes before it accepts that the host ended every one
ATTEMPTS = 3


def _run_unless_the_host_ends_it(emulators, host_made_end, cfg, **kw) -> tuple[dict, EmulatorProcess]:
    """``run_mod.run(cfg)`` until a run ends without the host ending it (ATTEMPTS at most): a run the host
    ended is checked for its safe end only; when the host ended them all, skip naming it."""
    reasons = []
    for _ in range(ATTEMPTS):
        emulators.clear()
        summary = run_mod.run(cfg, **kw)
        (emu,) = emulators
        why = host_made_end(summary["stop"], emu.stats)
        if why is None:
            return summary, emu
        assert summary["stop"]["final_torque"] == 0.0 and summary["stop"]["backend_state"] == "closed"
        _assert_drive_left_safe(emu)
        reasons.append(why)
    pytest.skip(f"the host ended all {ATTEMPTS} runs: {reasons}")


@pytest.mark.xdist_group("realtime")
def test_run_against_the_drive_process_streams_and_stops_at_zero_torque_disabled(emulators, host_made_end):
    summary, emu = _run_unless_the_host_ends_it(emulators, host_made_end, _config())
    assert summary["stop"]["cause"] is None, summary["stop"]
    assert summary["stop"]["final_torque"] == 0.0 and summary["stop"]["backend_state"] == "closed"
    loop = summary["loop"]
    # what tells a starved SYNC sender, a starved drive and misassigned windows apart
    keys = ("ticks", "samples", "lost_samples", "lost_longest", "overruns", "stalls")
    why = repr({"loop": {k: loop[k] for k in keys}, "bus": summary["backend_counters"],   # a str: not cut short
                "realtime": summary["realtime"],
                "drive": {k: emu.stats.get(k) for k in ("syncs", "late_syncs", "samples", "silent_samples",
                                                         "pickup_time", "answer_time")}})
    # 2 s at 2 kHz = 4000 SYNCs: half of them came, or the starved emulated drive answered too late to send
    assert loop["samples"] + emu.stats["late_syncs"] > 2000, why
    # lost: at most a quarter beyond those the emulated drive answered too late to send
    total = loop["samples"] + loop["lost_samples"]
    assert loop["lost_samples"] < emu.stats["late_syncs"] + 0.25 * total, why
    assert isinstance(emu, EmulatorProcess)
    cpus = sorted(_ALL_CPUS)
    if len(cpus) >= 2:                              # the drive stays off the loop's CPU (the last one)
        assert emu.placement["cpus"] == cpus[:-1]
    assert emu.stats["samples"] >= loop["samples"] and emu.stats["nmt_state"] == "PRE-OPERATIONAL"
    _assert_drive_left_safe(emu)
    assert emu.stats["state"] == p402.SWITCH_ON_DISABLED


@pytest.mark.xdist_group("realtime")
def test_drive_fault_in_the_drive_process_stops_the_run_safely(emulators, host_made_end):
    cfg = _config(**{"emulator.faults": {"emcy_at_sample": 600, "emcy_code": 0x2310}})
    summary, emu = _run_unless_the_host_ends_it(emulators, host_made_end, cfg)
    assert summary["stop"]["cause"] == "device-fault" and "0x2310" in summary["stop"]["message"]
    assert summary["stop"]["final_torque"] == 0.0 and summary["stop"]["backend_state"] == "closed"
    _assert_drive_left_safe(emu)
    assert emu.stats["state"] == p402.FAULT and emu.stats["emcy_codes"] == [0x2310]


@pytest.mark.xdist_group("realtime")
def test_exception_in_the_loop_leaves_no_emulator_process(emulators):
    def boom(tick: int) -> None:
        if tick == 100:
            raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        run_mod.run(_config(), tick_hook=boom)
    (emu,) = emulators
    _assert_drive_left_safe(emu)


def test_emulator_process_exits_when_its_parent_is_killed(tmp_path):
    script = tmp_path / "parent.py"
    script.write_text(
        "import sys, time\n"
        "from rt_ident.config import load\n"
        "from rt_ident.processes.emulation import start_emulator\n"
        "if __name__ == '__main__':\n"
        f"    emu = start_emulator(load({str(CONFIG)!r}, **{{'loop.realtime': False}}))\n"
        "    print(emu.pid, flush=True)\n"
        "    time.sleep(60)\n")
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        line = parent.stdout.readline()
        assert line.strip().isdigit(), f"parent printed {line!r} (exit code {parent.poll()})"
        child = int(line)
        assert not _gone(child, timeout=0.2)
    finally:
        parent.send_signal(signal.SIGKILL)
        parent.wait(10)
    assert _gone(child, timeout=5.0), f"emulator {child} outlived its parent"


def test_emulator_process_reports_a_start_failure_and_exits():
    bad = {"backend": {"interface": "udp_multicast", "channel": GROUP, "port": free_udp_port(), "node_id": 5,
                       "torque_limit": 1.0, "counts_per_rev": 4096, "scale_resolution": 1e-6},
           "emulator": {"eds": "missing.eds"}}
    with pytest.raises(RtIdentError, match=r"failed to start: ConfigError.*missing\.eds"):
        EmulatorProcess("drivers.cia402.emulator", bad)
    assert not [p for p in multiprocessing.active_children() if "emulator" in p.name]


# ----- real-time placement --------------------------------------------------------------------------
def _threads(pid: int) -> dict[int, tuple[int, int, frozenset]]:
    """tid -> (policy without the reset-on-fork flag, SCHED_FIFO priority, CPUs) of every thread of ``pid``."""
    out = {}
    for tid in (int(t) for t in os.listdir(f"/proc/{pid}/task")):
        try:
            out[tid] = (os.sched_getscheduler(tid) & ~os.SCHED_RESET_ON_FORK, os.sched_getparam(tid).sched_priority,
                        frozenset(os.sched_getaffinity(tid)))
        except OSError:                              # the thread has just ended
            pass
    return out


@pytest.mark.xdist_group("realtime")
@pytest.mark.slow
def test_during_a_run_only_the_loop_and_its_sync_sender_are_real_time_on_the_loop_cpu(emulators, host_made_end):
    # RT throttling needs 950 ms of SCHED_FIFO in a second on one CPU: the loop's CPU holds the loop
    # (FIFO 50) and the SYNC sender (FIFO 51) and no other real-time thread; the drive's real-time
    # threads are elsewhere; the idle poller there is SCHED_IDLE. After the run nothing of this
    # process is real-time any more.
    cpus = sorted(_ALL_CPUS)
    if len(cpus) < 2:
        pytest.skip("the loop gets a CPU of its own only with two or more")
    loop_cpu = cpus[-1]
    seen = {}

    def look(tick: int) -> None:
        if tick == 300:
            seen["run"] = _threads(os.getpid())
            seen["drive"] = _threads(emulators[0].pid)
            seen["main"] = threading.get_native_id()

    for _ in range(ATTEMPTS):                   # the threads as tick 300 saw them, however the run ended later
        seen.clear()
        emulators.clear()
        summary = run_mod.run(_config(**{"loop.duration": 1.0}), tick_hook=look)
        if summary["stop"]["cause"] is not None:     # only the host may have ended it
            assert host_made_end(summary["stop"], emulators[0].stats), summary["stop"]
        if "run" in seen:
            break
    else:
        pytest.skip(f"the host ended all {ATTEMPTS} runs before tick 300: {summary['stop']}")
    if summary["realtime"].get("sched_fifo") is not True:
        pytest.skip(f"SCHED_FIFO not granted here: {summary['realtime'].get('sched_fifo')}")
    fifo = {tid: (prio, cpus_) for tid, (pol, prio, cpus_) in seen["run"].items() if pol == os.SCHED_FIFO}
    assert seen["main"] in fifo and fifo.pop(seen["main"]) == (50, frozenset({loop_cpu}))
    assert list(fifo.values()) == [(51, frozenset({loop_cpu}))]            # the SYNC sender, one step above
    idle = [c for pol, _, c in seen["run"].values() if pol == os.SCHED_IDLE]
    assert idle == [frozenset({loop_cpu})]                                # the idle poller
    drive_fifo = [(prio, c) for pol, prio, c in seen["drive"].values() if pol == os.SCHED_FIFO]
    assert drive_fifo and all(prio == 40 and loop_cpu not in c for prio, c in drive_fifo)
    assert all(loop_cpu not in c for _, _, c in seen["drive"].values())
    after = _threads(os.getpid())
    assert not [t for t, (pol, _, _) in after.items() if pol == os.SCHED_FIFO]
    assert os.sched_getaffinity(0) == _ALL_CPUS


def test_an_emulator_process_turns_only_its_devices_threads_real_time(tmp_path, monkeypatch):
    # importing numba, canopen and the plant and building the device is most of the start-up's CPU time, and
    # the interpreter's exit adds more: at SCHED_FIFO they would hold the CPU against another run's drive at
    # the same priority, which then sends nothing. A thread from before the device (numpy's BLAS pool) stays.
    (tmp_path / "fake_device_for_placement.py").write_text(
        "import os, threading\n"
        "AT_IMPORT = os.sched_getscheduler(0)\n"
        "POOL_DONE = threading.Event()\n"
        "POOL = threading.Thread(target=POOL_DONE.wait, daemon=True)\n"
        "POOL.start()\n"
        "class Device:\n"
        "    port = None\n"
        "    def __init__(self):\n"
        "        self.at_start = os.sched_getscheduler(0)\n"
        "        self.cpus = sorted(os.sched_getaffinity(0))\n"
        "        self.done = threading.Event()\n"
        "        self.thread = threading.Thread(target=self.done.wait)\n"
        "        self.thread.start()\n"
        "    def stats(self):\n"
        "        return {'import': AT_IMPORT, 'start': self.at_start, 'cpus': self.cpus,\n"
        "                'main': os.sched_getscheduler(0), 'pool': os.sched_getscheduler(POOL.native_id),\n"
        "                'streaming': os.sched_getscheduler(self.thread.native_id),\n"
        "                'streaming_cpus': sorted(os.sched_getaffinity(self.thread.native_id))}\n"
        "    def stop(self):\n"
        "        self.done.set()\n"
        "        self.thread.join()\n"
        "def start_emulator_for(config):\n"
        "    return Device()\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    cpus = sorted(_ALL_CPUS)
    emu = EmulatorProcess("fake_device_for_placement", {}, placement={"cpus": cpus[:1], "fifo_priority": 40})
    emu.close()
    if emu.placement.get("sched_fifo") != 40:
        pytest.skip(f"SCHED_FIFO not granted here: {emu.placement}")
    assert emu.placement == {"cpus": cpus[:1], "sched_fifo": 40}
    st = emu.stats
    assert st["import"] == st["start"] == st["main"] == st["pool"] == os.SCHED_OTHER
    assert st["streaming"] == os.SCHED_FIFO
    assert st["cpus"] == st["streaming_cpus"] == cpus[:1]
