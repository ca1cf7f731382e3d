"""Drive variants (drivers.cia402.variants): what the emulated drive answers as a real vendor's drive would,
and how our master meets each: it adapts (PDO mapping across TPDOs, 0x60C2, read-only 0x1006, polarity)
or refuses in one line naming the object and the drive's abort code by name."""

from __future__ import annotations

import time
import uuid

import canopen
import numpy as np
import pytest
from canopen.sdo import SdoAbortedError

from drivers.cia402 import profile as p402
from drivers.cia402.drive import Cia402Backend
from drivers.cia402.emulator import start_emulator_for
from drivers.cia402.variants import PROFILES, interpolation_period
from drivers.errors import ProtocolError
from rt_ident.axis.params import CONFIG_DIR
from rt_ident.errors import ConfigError
from tests.drivers.test_canopen_backend import assert_drive_safe, backend_cfg, pump

EDS = CONFIG_DIR / "cia402_generic.eds"


def _rig(profile: str, **emulator):
    # a loaded machine can hold the in-process drive's or host's heartbeat back for longer than 250 ms
    cfg = {"backend": backend_cfg(f"v-{uuid.uuid4().hex[:10]}", heartbeat_consumer_ms=1000),
           "emulator": {"position_hold": True, "profile": profile, **emulator}}
    return cfg, start_emulator_for(cfg)


def _sdo_client(channel: str) -> tuple[canopen.Network, canopen.RemoteNode]:
    net = canopen.Network()
    net.connect(interface="virtual", channel=channel)
    node = canopen.RemoteNode(5, str(EDS))
    net.add_node(node)
    node.sdo.RESPONSE_TIMEOUT = 2.0     # the in-process drive answers late on a loaded test worker
    return net, node


def _abort(call) -> int:
    with pytest.raises(SdoAbortedError) as err:
        call()
    return err.value.code


@pytest.mark.parametrize("profile,index,code,name", [
    ("no-additional-position", "0x60E4:01", 0x06020000, "object does not exist in the object dictionary"),
    ("torque-actual-not-mappable", "0x6077", 0x06040041, "object cannot be mapped to the PDO"),
])
def test_our_master_refuses_a_drive_it_cannot_stream_in_one_line_naming_the_object_and_the_abort(
        profile, index, code, name):
    cfg, drive = _rig(profile)
    try:
        be = Cia402Backend(cfg["backend"])
        with pytest.raises(ProtocolError) as err:
            be.open()
        msg = str(err.value)
        assert index in msg and f"0x{code:08X}" in msg and name in msg and "\n" not in msg, msg
        assert be.state.name != "OPEN"
        assert_drive_safe(drive)
    finally:
        drive.stop()


def test_the_refused_variants_answer_with_their_abort_codes_to_any_master():
    cfg, drive = _rig("no-additional-position")
    net, node = _sdo_client(cfg["backend"]["channel"])
    try:
        assert _abort(lambda: node.sdo.upload(0x60E4, 1)) == 0x06020000
        node.sdo.download(0x1801, 1, (0x80000285).to_bytes(4, "little"))
        node.sdo.download(0x1A01, 0, b"\x00")
        entry = p402.mapping_entry(0x60E4, 1, 32).to_bytes(4, "little")
        assert _abort(lambda: node.sdo.download(0x1A01, 1, entry)) == 0x06020000
    finally:
        net.disconnect()
        drive.stop()
    cfg, drive = _rig("torque-actual-not-mappable")
    net, node = _sdo_client(cfg["backend"]["channel"])
    try:
        assert len(node.sdo.upload(p402.TORQUE_ACTUAL, 0)) == 2       # readable by SDO
        node.sdo.download(0x1800, 1, (0x80000185).to_bytes(4, "little"))
        node.sdo.download(0x1A00, 0, b"\x00")
        entry = p402.mapping_entry(p402.TORQUE_ACTUAL, 0, 16).to_bytes(4, "little")
        assert _abort(lambda: node.sdo.download(0x1A00, 3, entry)) == 0x06040041
    finally:
        net.disconnect()
        drive.stop()


def test_a_drive_with_four_entries_per_pdo_refuses_a_fifth_entry_and_a_count_of_five():
    cfg, drive = _rig("four-objects-per-pdo")
    net, node = _sdo_client(cfg["backend"]["channel"])
    try:
        node.sdo.download(0x1800, 1, (0x80000185).to_bytes(4, "little"))
        entry = p402.mapping_entry(p402.STATUSWORD, 0, 16).to_bytes(4, "little")
        assert _abort(lambda: node.sdo.download(0x1A00, 5, entry)) == 0x06090011
        node.sdo.download(0x1A00, 0, b"\x00")
        for sub in range(1, 5):
            node.sdo.download(0x1A00, sub, entry)
        assert _abort(lambda: node.sdo.download(0x1A00, 0, b"\x05")) == 0x06040042
        node.sdo.download(0x1A00, 0, b"\x04")                            # 4 x 16 bits: fits
    finally:
        net.disconnect()
        drive.stop()


@pytest.mark.parametrize("profile", ["four-objects-per-pdo", "two-objects-per-pdo"])
def test_our_master_maps_the_streamed_objects_into_as_many_entries_per_pdo_as_the_drive_takes(profile):
    cfg, drive = _rig(profile, position_hold=False, travel=None)      # the drive applies what it is sent
    try:
        with Cia402Backend(cfg["backend"]) as be:
            sizes = [st.size for _, st in be._setup.tpdo_layouts]
            # statusword 2 + position 4 + torque 2 bytes, scale 4 bytes: two frames per SYNC either way
            assert sizes == ([8, 4] if profile == "four-objects-per-pdo" else [6, 6])
            be.activate()
            blocks = pump(be, 0.5, lambda seq: np.full(len(seq), 0.01), samples=60)
            blk = blocks[-1]
            assert sum(len(b) for b in blocks) > 50
            # every streamed value lands where it belongs: torque actual, motor and table moving together
            assert blk.torque_meas is not None and blk.torque_meas[-1] == pytest.approx(0.01, abs=0.002)
            assert blk.theta1[-1] > blocks[0].theta1[0] and blk.theta2[-1] > blocks[0].theta2[0]
        assert_drive_safe(drive)
    finally:
        drive.stop()


def test_a_drive_that_needs_0x60C2_faults_on_enable_without_it_and_takes_our_masters_setting():
    cfg, drive = _rig("interpolation-period")
    net, node = _sdo_client(cfg["backend"]["channel"])
    try:
        assert _abort(lambda: node.sdo.download(p402.CYCLE_PERIOD, 0, (1000).to_bytes(4, "little"))) == 0x06010002
        assert _abort(lambda: node.sdo.download(0x60C2, 2, (-7).to_bytes(1, "little", signed=True))) == 0x06090030
        node.sdo.download(p402.MODES_OF_OPERATION, 0, bytes([p402.MODE_CST]))
        node.nmt.send_command(0x01)
        for cw in (p402.CW_SHUTDOWN, p402.CW_SWITCH_ON, p402.CW_ENABLE_OPERATION):
            node.sdo.download(p402.CONTROLWORD, 0, cw.to_bytes(2, "little"))
            net.send_message(0x80, b"")                                  # the drive steps at a SYNC
            time.sleep(0.02)
        assert drive.state == p402.FAULT and drive.emcy_codes == [0x6320]
    finally:
        net.disconnect()
        drive.stop()
    cfg, drive = _rig("interpolation-period")
    try:
        with Cia402Backend(cfg["backend"]) as be:                       # 0x1006 read-only: carries on
            be.activate()
            assert drive.enabled and sum(len(b) for b in pump(be, 0.5)) > 10
            value, power = interpolation_period(1e-3)
            assert (value, power) == (1, -3)
            with drive._lock:
                node_ = drive._node
                assert node_ is not None
                assert node_.get_data(0x60C2, 1) == bytes([value])
                assert node_.get_data(0x60C2, 2) == power.to_bytes(1, "little", signed=True)
        assert_drive_safe(drive)
    finally:
        drive.stop()


def test_interpolation_period_takes_the_coarsest_exact_power_of_ten():
    assert interpolation_period(5e-4) == (5, -4)
    assert interpolation_period(2e-3) == (2, -3)
    assert interpolation_period(0.25) == (25, -2)
    assert interpolation_period(1 / 3000) == (33, -5)                  # no exact one: the closest


def test_our_master_reads_the_polarity_of_a_drive_that_has_it_set_and_reverses_the_scale():
    cfg, drive = _rig("polarity-set")
    try:
        with Cia402Backend(cfg["backend"]) as be:
            assert be.identity()["polarity"] == p402.POLARITY_POSITION and be.scale_sign == -1
        assert_drive_safe(drive)
    finally:
        drive.stop()


def test_an_unknown_profile_is_refused_naming_the_profiles_there_are():
    with pytest.raises(ConfigError) as err:
        start_emulator_for({"backend": backend_cfg("x"), "emulator": {"profile": "acme"}})
    assert err.value.field == "emulator.profile" and all(name in str(err.value) for name in PROFILES)


def test_every_variant_is_either_adapted_to_in_the_contract_suite_or_refused_here():
    from tests.drivers.test_backend_contract import CANOPEN_VARIANTS

    refused = {"no-additional-position", "torque-actual-not-mappable"}
    assert set(CANOPEN_VARIANTS) | refused | {"generic"} == set(PROFILES) and not refused & set(CANOPEN_VARIANTS)
