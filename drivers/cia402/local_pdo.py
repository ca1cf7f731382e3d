"""PDO tables of a ``canopen.LocalNode`` (the emulated drive's side of CiA 301 PDO mapping).

``LocalNode`` stores whatever an SDO client writes; a real device refuses a mapping
while its PDO is valid (CiA 301: map only with COB-ID bit 31 set; abort 0x08000022, "present
device state"), one that names a missing object (abort 0x06020000), an object that is not
PDO-mappable or mapped with the wrong length (0x06040041), or more than 8 bytes or more entries
than the drive's mapping record has (0x06040042); an entry written while sub-index 0 is not 0 (CiA 301's
sequence clears the count first: abort 0x08000022).
:func:`check_mapping_write` does that; :func:`pdo_layouts` reads the valid PDOs and
their mappings as ``struct`` layouts.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import canopen
from canopen.sdo import SdoAbortedError

from drivers.cia402 import profile as p402


def od_value(node: canopen.LocalNode, index: int, subindex: int = 0) -> int:
    """Current value of an integer object of the local node (written, read callback, or EDS default)."""
    var = node.object_dictionary.get_variable(index, subindex)
    if var is None:                          # as a device answers a read of a missing object
        raise SdoAbortedError(0x06020000)
    value = var.decode_raw(node.get_data(index, subindex))
    if not isinstance(value, int):
        raise TypeError(f"object 0x{index:04X}:{subindex:02X} holds {type(value).__name__}, not an integer")
    return value


def _data_type(node: canopen.LocalNode, index: int, subindex: int) -> int:
    var = node.object_dictionary.get_variable(index, subindex)
    if var is None or var.data_type is None:  # check_mapping_write let no such mapping in
        raise SdoAbortedError(0x06020000)
    return var.data_type


def check_mapping_write(node: canopen.LocalNode, index: int, subindex: int, value: int) -> None:
    """Refuse a write to an RPDO (0x16xx) / TPDO (0x1Axx) mapping parameter the way a device would."""
    comm = index - 0x200                     # 0x16xx -> 0x14xx, 0x1Axx -> 0x18xx
    if node.object_dictionary.get_variable(comm, 1) is not None and not od_value(node, comm, 1) & p402.PDO_INVALID:
        raise SdoAbortedError(0x08000022)    # the PDO is valid: mapping only while disabled (CiA 301)
    if subindex == 0:
        record = node.object_dictionary[index]
        if value > max((s for s in getattr(record, "subindices", {0: None})), default=0):
            raise SdoAbortedError(0x06040042)   # more entries than this drive's mapping record has
        bits = sum(p402.split_mapping_entry(od_value(node, index, s))[2] for s in range(1, value + 1))
        if bits > 64:
            raise SdoAbortedError(0x06040042)
        return
    if od_value(node, index, 0) != 0:
        raise SdoAbortedError(0x08000022)    # entries only while the count is 0 (CiA 301)
    if value == 0:
        return
    obj, sub, bits = p402.split_mapping_entry(value)
    var = node.object_dictionary.get_variable(obj, sub)
    if var is None:
        raise SdoAbortedError(0x06020000)
    rpdo = index < 0x1800
    if (not var.pdo_mappable or bits != len(var) or (rpdo and not var.writable)
            or (not rpdo and not var.readable)):
        raise SdoAbortedError(0x06040041)


@dataclass(frozen=True)
class PdoLayout:
    """One valid PDO: 11-bit COB-ID, transmission type, packing, mapped (index, subindex) keys; for a
    TPDO its inhibit time (0x18xx:03, 100 us units) and event timer (0x18xx:05, ms) in seconds, for an
    RPDO its deadline (the event timer 0x14xx:05, ms) in seconds."""

    cob: int
    trans_type: int
    struct: struct.Struct
    keys: tuple[tuple[int, int], ...]
    inhibit_s: float = 0.0
    event_s: float = 0.0
    sync_start: int = 0        # TPDO 0x18xx:06: with the SYNC counter on, the counter value it starts at


def _optional(node: canopen.LocalNode, index: int, subindex: int) -> int:
    return od_value(node, index, subindex) if node.object_dictionary.get_variable(index, subindex) else 0


def _layout(node: canopen.LocalNode, comm: int, mapping: int) -> PdoLayout | None:
    cob = od_value(node, comm, 1)
    if cob & p402.PDO_INVALID:
        return None
    keys = tuple(p402.split_mapping_entry(od_value(node, mapping, s))[:2]
                 for s in range(1, od_value(node, mapping, 0) + 1))
    st = p402.pdo_struct([_data_type(node, i, s) for i, s in keys])
    tx = comm >= 0x1800
    return PdoLayout(cob & 0x7FF, od_value(node, comm, 2), st, keys,
                     inhibit_s=1e-4 * _optional(node, comm, 3) if tx else 0.0,
                     event_s=1e-3 * _optional(node, comm, 5),
                     sync_start=_optional(node, comm, 6) if tx else 0)


def pdo_layouts(node: canopen.LocalNode) -> tuple[list[PdoLayout], list[PdoLayout]]:
    """(RPDOs, TPDOs) currently valid on the node."""
    od = node.object_dictionary
    rpdos: list[PdoLayout] = []
    tpdos: list[PdoLayout] = []
    for n in range(512):
        rx = od.get_variable(0x1400 + n, 1) is not None
        tx = od.get_variable(0x1800 + n, 1) is not None
        if not (rx or tx):
            break
        if rx and (lay := _layout(node, 0x1400 + n, 0x1600 + n)):
            rpdos.append(lay)
        if tx and (lay := _layout(node, 0x1800 + n, 0x1A00 + n)):
            tpdos.append(lay)
    return rpdos, tpdos
