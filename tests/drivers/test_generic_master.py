"""The emulated CiA 402 drive in its default configuration, driven by a generic master (python canopen's
``BaseNode402``) on a bus without echo, as each vendor variant too (drivers.cia402.variants); CiA 301 PDO
transmission types, inhibit time and event timer."""

from __future__ import annotations

import configparser
import threading
import time
import uuid

import can
import canopen
import numpy as np
import pytest
from canopen.sdo import SdoAbortedError

from drivers.cia402 import profile as p402
from drivers.cia402.bus import open_bus
from drivers.cia402.emulated_drive import EmulatedCia402Drive
from drivers.cia402.faults import FaultConfig
from drivers.cia402.variants import PROFILES
from rt_ident.axis.params import CONFIG_DIR, thomson_x
from rt_ident.axis.plant import PlantSimulator, SensorConfig
from tests.drivers.test_canopen_process import GROUP, free_udp_port

EDS = CONFIG_DIR / "cia402_generic.eds"
NODE = 5


def _bus(interface: str) -> dict:
    if interface == "virtual":
        return {"interface": "virtual", "channel": f"g-{uuid.uuid4().hex[:8]}"}
    return {"interface": "udp_multicast", "channel": GROUP, "port": free_udp_port()}


class _Master:
    """A canopen ``Network`` on the bus (for udp_multicast python-can's ``rt_ident_udp`` interface: confined,
    no echo) with the drive's node."""

    def __init__(self, kw: dict) -> None:
        # as a user of another CANopen tool connects: python-can's interface of this package (no echo)
        bus = can.Bus(interface="rt_ident_udp", channel=kw["channel"], port=kw["port"]) \
            if kw["interface"] == "udp_multicast" else open_bus(kw)
        self.net = canopen.Network(bus)
        self.net.NOTIFIER_CYCLE = 0.05
        self.net.connect()
        self.node = canopen.BaseNode402(NODE, str(EDS))
        self.net.add_node(self.node)
        self.node.sdo.RESPONSE_TIMEOUT = 2.0     # the in-process drive answers late on a loaded test worker
        # canopen's state-change waits (0.2-0.8 s) likewise: a statusword TPDO came later in a CI run
        self.node.TIMEOUT_SWITCH_STATE_FINAL, self.node.TIMEOUT_SWITCH_STATE_SINGLE = 5.0, 2.0
        self.node.TIMEOUT_CHECK_TPDO = 1.0
        self.frames: dict[int, list[tuple[float, float]]] = {}   # cob -> [(received, time on the bus)]
        self._lock = threading.Lock()
        self.net.subscribe(0x180 + NODE, self._count)

    def _count(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self._lock:
            self.frames.setdefault(can_id, []).append((time.monotonic(), timestamp))

    def count(self, can_id: int, since: float = 0.0) -> int:
        with self._lock:
            return sum(t >= since for t, _ in self.frames.get(can_id, ()))

    def bus_times(self, can_id: int, since: float = 0.0) -> list[float]:
        """Times on the bus of the frames received since ``since`` (the virtual bus: when they were sent)."""
        with self._lock:
            return [ts for t, ts in self.frames.get(can_id, ()) if t >= since]

    def close(self) -> None:
        self.net.sync.stop()
        self.net.disconnect()


def _drive(kw: dict, profile: str = "generic", faults: FaultConfig | None = None) -> EmulatedCia402Drive:
    plant = PlantSimulator(thomson_x(), 1e-3, sensors=SensorConfig())
    return EmulatedCia402Drive(NODE, EDS, kw, plant, faults, rated_torque=0.5, profile=profile)


def _to_cst(m: _Master, profile: str) -> None:
    """What a user of a generic master does before enabling: the 402 set-up, CST, the statusword's event
    timer, and on a drive that needs it the interpolation time period (1 ms, the SYNC below: 1 x 10^-3 s);
    SYNC running."""
    node = m.node
    node.nmt.state = "PRE-OPERATIONAL"
    node.setup_402_state_machine()                    # reads the PDO configuration by SDO
    assert node.tpdo[1].trans_type == 255 and [v.index for v in node.tpdo[1]] == [p402.STATUSWORD]
    assert node.rpdo[1].trans_type == 255 and [v.index for v in node.rpdo[1]] == [p402.CONTROLWORD]
    node.op_mode = "CYCLIC SYNCHRONOUS TORQUE"
    assert node.op_mode == "CYCLIC SYNCHRONOUS TORQUE"
    # BaseNode402 checks a state change by waiting for the *next* statusword TPDO; one that arrives before
    # it starts to wait is missed, and an event-driven TPDO then never comes again. The event timer resends.
    node.sdo[0x1800][5].raw = 50
    if PROFILES[profile].interpolation_period:        # not in the generic EDS: written by index
        node.sdo.download(0x60C2, 2, (-3).to_bytes(1, "little", signed=True))
        node.sdo.download(0x60C2, 1, bytes([1]))
    if node.sdo[0x1019].raw:                          # canopen's periodic SYNC carries no counter
        node.sdo[0x1019].raw = 0
    m.net.sync.start(0.001)                           # CST: the drive applies torque at each SYNC


@pytest.mark.parametrize("interface,profile", [("virtual", "generic")] + [("udp_multicast", p) for p in PROFILES])
def test_basenode402_enables_the_drive_in_its_default_configuration_and_torque_moves_it(interface, profile):
    kw = _bus(interface)
    with _drive(kw, profile) as drive:
        m = _Master(kw)
        try:
            node = m.node
            _to_cst(m, profile)
            node.nmt.state = "OPERATIONAL"
            node.state = "SWITCH ON DISABLED"             # waits for TPDO1 (sent on entering OPERATIONAL)
            node.state = "OPERATION ENABLED"
            assert node.state == "OPERATION ENABLED" and drive.state == p402.OPERATION_ENABLED
            p0 = node.sdo[p402.POSITION_ACTUAL].raw
            node.sdo[p402.TARGET_TORQUE].raw = 50         # 5 % of the rated torque
            end = time.monotonic() + 2.0
            while abs(node.sdo[p402.POSITION_ACTUAL].raw - p0) < 100 and time.monotonic() < end:
                time.sleep(0.01)
            assert abs(node.sdo[p402.POSITION_ACTUAL].raw - p0) >= 100 and drive.applied_torque != 0.0
            node.sdo[p402.TARGET_TORQUE].raw = 0
            node.state = "SWITCH ON DISABLED"
            assert drive.state == p402.SWITCH_ON_DISABLED and drive.applied_torque == 0.0
        finally:
            m.close()


@pytest.mark.parametrize("profile", list(PROFILES))
def test_basenode402_resets_an_injected_fault_and_enables_the_drive_again(profile):
    kw = _bus("udp_multicast")
    with _drive(kw, profile, faults=FaultConfig(emcy_at_sample=200, emcy_code=0x2310)) as drive:
        m = _Master(kw)
        try:
            node = m.node
            _to_cst(m, profile)
            node.nmt.state = "OPERATIONAL"
            node.state = "SWITCH ON DISABLED"
            node.state = "OPERATION ENABLED"
            end = time.monotonic() + 2.0
            while node.state != "FAULT" and time.monotonic() < end:   # the event-driven statusword says so
                time.sleep(0.01)
            assert node.state == "FAULT" and drive.state == p402.FAULT and drive.applied_torque == 0.0
            end = time.monotonic() + 1.0
            while not node.emcy.log and time.monotonic() < end:
                time.sleep(0.01)
            assert [e.code for e in node.emcy.log] == [0x2310]
            node.state = "SWITCH ON DISABLED"             # fault reset: rising edge of controlword bit 7
            assert drive.state == p402.SWITCH_ON_DISABLED
            node.state = "OPERATION ENABLED"
            assert drive.state == p402.OPERATION_ENABLED
            node.state = "SWITCH ON DISABLED"
            assert drive.state == p402.SWITCH_ON_DISABLED and drive.applied_torque == 0.0
        finally:
            m.close()


@pytest.mark.parametrize("profile", list(PROFILES))
def test_every_mandatory_object_of_the_eds_reads_by_sdo(profile):
    eds = configparser.ConfigParser(interpolation=None)
    eds.optionxform = str                                 # type: ignore[assignment,method-assign]
    eds.read(EDS)
    sec = eds["MandatoryObjects"]
    indices = [int(sec[str(i)], 0) for i in range(1, int(sec["SupportedObjects"], 0) + 1)]
    assert {0x1000, 0x1001, 0x1018} <= set(indices)
    kw = _bus("virtual")
    with _drive(kw, profile):
        m = _Master(kw)
        try:
            for index in indices:
                obj = m.node.object_dictionary[index]
                variables = list(obj.values()) if isinstance(obj, (canopen.objectdictionary.ODRecord,
                                                                    canopen.objectdictionary.ODArray)) else [obj]
                for var in variables:
                    assert len(m.node.sdo.upload(index, var.subindex)) > 0, f"0x{index:04X}:{var.subindex}"
        finally:
            m.close()


def test_pdo_mapping_only_while_disabled_entries_only_while_the_count_is_0_and_at_most_8_bytes():
    kw = _bus("virtual")
    with _drive(kw):
        m = _Master(kw)
        try:
            sdo = m.node.sdo
            with pytest.raises(SdoAbortedError) as err:   # TPDO1 is valid: its mapping is locked
                sdo[0x1A00][0].raw = 0
            assert err.value.code == 0x08000022
            sdo[0x1800][1].raw = 0x80000180 + NODE        # disabled: mapping allowed
            with pytest.raises(SdoAbortedError) as err:   # the count is not 0 yet: entries locked
                sdo[0x1A00][1].raw = p402.mapping_entry(0x6064, 0, 32)
            assert err.value.code == 0x08000022
            sdo[0x1A00][0].raw = 0
            for sub, entry in enumerate([(0x6064, 32), (0x6077, 16), (0x6041, 16), (0x6041, 16)], start=1):
                sdo[0x1A00][sub].raw = p402.mapping_entry(entry[0], 0, entry[1])
            with pytest.raises(SdoAbortedError) as err:   # 80 bits
                sdo[0x1A00][0].raw = 4
            assert err.value.code == 0x06040042
            sdo[0x1A00][0].raw = 3
            sdo[0x1800][1].raw = 0x180 + NODE
        finally:
            m.close()


def _until(pred, timeout: float = 5.0) -> bool:
    end = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > end:
            return False
        time.sleep(0.002)
    return True


def _sync_handled(m: _Master, drive: EmulatedCia402Drive) -> None:
    """One SYNC, and wait until the drive has handled it (its TPDOs sent: ``stats()`` waits for the lock
    the SYNC handler holds), so that no SYNC arrives while the previous is being answered."""
    n = drive.stats()["syncs"]
    m.net.send_message(0x80, b"")
    assert _until(lambda: drive.stats()["syncs"] > n)


def test_tpdo_transmission_types_event_timer_and_inhibit_time():
    """CiA 301: 255 with an event timer sends without a change, never sooner than the timer; the inhibit time
    spaces the TPDOs of a changing statusword; 1..240 answers every n-th SYNC; 0 only the SYNC after a
    change. Spacings are the frames' send times on the virtual bus and the SYNCs go one at a time: nothing
    here depends on how fast the machine runs the test."""
    kw = _bus("virtual")
    with _drive(kw) as drive:
        m = _Master(kw)
        cob = 0x180 + NODE
        try:
            sdo = m.node.sdo
            sdo[0x1800][5].raw = 20                       # event timer 20 ms
            m.node.nmt.state = "OPERATIONAL"
            t0 = time.monotonic()
            assert _until(lambda: m.count(cob, t0) >= 5)  # the statusword stands still: the timer sends
            gaps = np.diff(m.bus_times(cob, t0))
            assert gaps.min() >= 0.019, gaps
            sdo[0x1800][5].raw = 0
            # inhibit time 50 ms: controlword toggles every 5 ms change the statusword, TPDO1 at most every 50 ms
            sdo[0x1800][1].raw = 0x80000000 + cob
            sdo[0x1800][3].raw = 500
            sdo[0x1800][1].raw = cob
            t0 = time.monotonic()
            for i in range(40):                           # >= 0.2 s of SWITCH ON DISABLED <-> READY TO SWITCH ON
                m.net.send_message(0x200 + NODE, (p402.CW_SHUTDOWN if i % 2 == 0 else 0).to_bytes(2, "little"))
                time.sleep(0.005)
            assert _until(lambda: m.count(cob, t0) >= 3)
            gaps = np.diff(m.bus_times(cob, t0))
            assert gaps.min() >= 0.049, gaps
            assert drive.state in (p402.SWITCH_ON_DISABLED, p402.READY_TO_SWITCH_ON)
            # every 3rd SYNC
            m.node.nmt.state = "PRE-OPERATIONAL"
            sdo[0x1800][1].raw = 0x80000000 + cob
            sdo[0x1800][2].raw = 3
            sdo[0x1800][1].raw = cob
            m.node.nmt.state = "OPERATIONAL"
            assert _until(lambda: drive.nmt_state == "OPERATIONAL")
            t0 = time.monotonic()
            first = drive.stats()["syncs"]
            for _ in range(30):
                _sync_handled(m, drive)
            due = sum((first + i) % 3 == 0 for i in range(1, 31))
            assert due == 10 and _until(lambda: m.count(cob, t0) >= due)
            time.sleep(0.05)
            assert m.count(cob, t0) == due
            # type 0: at a SYNC only after a change (none here: the statusword stands still)
            sdo[0x1800][1].raw = 0x80000000 + cob
            sdo[0x1800][2].raw = 0
            sdo[0x1800][1].raw = cob
            t0 = time.monotonic()
            _sync_handled(m, drive)                       # the first SYNC after the change of PDO set: sent
            assert _until(lambda: m.count(cob, t0) == 1)
            t0 = time.monotonic()
            for _ in range(10):
                _sync_handled(m, drive)
            time.sleep(0.05)
            assert m.count(cob, t0) == 0
        finally:
            m.close()


def test_a_sync_counter_starts_a_synchronous_tpdo_at_its_start_value_and_a_sync_without_it_is_ignored():
    """CiA 301: 0x1019 (0, or 2..240, changed only while 0x1006 is 0) makes every SYNC carry a counter; a
    TPDO of type n with a start value (0x18xx:06) first goes out at the SYNC whose counter equals it, then
    every n-th; a SYNC without the counter is not acted on (EMCY 0x8240, once until a right one comes)."""
    kw = _bus("virtual")
    with _drive(kw) as drive:
        m = _Master(kw)
        try:
            sdo = m.node.sdo
            with pytest.raises(SdoAbortedError) as err:
                sdo[0x1019].raw = 1
            assert err.value.code == 0x06090030
            sdo[0x1006].raw = 1000
            with pytest.raises(SdoAbortedError) as err:
                sdo[0x1019].raw = 4
            assert err.value.code == 0x08000022
            sdo[0x1006].raw = 0
            sdo[0x1019].raw = 4
            sdo[0x1800][1].raw = 0x80000180 + NODE        # TPDO1 (the statusword): every 2nd SYNC from counter 3
            sdo[0x1800][2].raw = 2
            sdo[0x1800][6].raw = 3
            sdo[0x1800][1].raw = 0x180 + NODE
            m.node.nmt.state = "OPERATIONAL"
            cob = 0x180 + NODE

            def sync(data: bytes) -> int:
                n = drive.stats()["syncs"]
                m.net.send_message(0x80, data)
                return n

            sent_at = []
            for i, counter in enumerate([1, 2, 3, 4, 1, 2, 3, 4], start=1):
                n = sync(bytes([counter]))
                assert _until(lambda n=n: drive.stats()["syncs"] > n)
                if counter in (1, 3) and i >= 3:                         # SYNCs 3, 5, 7
                    assert _until(lambda k=len(sent_at) + 1: m.count(cob) >= k), (i, counter)
                    sent_at.append(i)
            time.sleep(0.1)
            assert m.count(cob) == 3 and sent_at == [3, 5, 7]
            for _ in range(2):                                           # no counter: not a SYNC for it
                n = sync(b"")
            assert _until(lambda: [e.code for e in m.node.emcy.log] == [0x8240])
            time.sleep(0.05)
            assert drive.stats()["syncs"] == n and drive.sync_length_errors == 2
            assert [e.code for e in m.node.emcy.log] == [0x8240]
        finally:
            m.close()
