"""CiA 402 / CiA 301 facts shared by the CANopen backend and the emulated drive.

Pure tables and functions (no I/O): the 402 power state machine (statusword
decoding for the master, controlword transitions for the drive), controlword
commands, PDO mapping entries, struct codes of the CANopen data types, SDO
abort texts and EMCY code descriptions.

References: CiA 301 v4.2 (communication profile: PDO mapping 0x1600/0x1A00,
heartbeat 0x1016/0x1017, EMCY, SYNC) and CiA 402-2 (drive profile: controlword
0x6040, statusword 0x6041, modes 0x6060/0x6061, cyclic synchronous torque = 10).
"""

from __future__ import annotations

import struct

# ----- objects (CiA 402-2) ------------------------------------------------------------
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
MODES_OF_OPERATION = 0x6060
MODES_DISPLAY = 0x6061
POSITION_ACTUAL = 0x6064
TARGET_TORQUE = 0x6071
MAX_TORQUE = 0x6072
RATED_TORQUE = 0x6076
TORQUE_ACTUAL = 0x6077
POLARITY = 0x607E          # UNSIGNED8; bit 7 position polarity, bit 6 velocity polarity
INTERPOLATION_PERIOD = 0x60C2   # RECORD: sub 1 value (UNSIGNED8), sub 2 index (INTEGER8): value * 10^index s
ERROR_CODE = 0x603F
SUPPORTED_MODES = 0x6502
DEVICE_TYPE = 0x1000
ERROR_REGISTER = 0x1001
CYCLE_PERIOD = 0x1006
SYNC_OVERFLOW = 0x1019     # UNSIGNED8; 0: SYNCs carry no counter, 2..240: they carry one, 1..that value
CONSUMER_HEARTBEAT = 0x1016
PRODUCER_HEARTBEAT = 0x1017
IDENTITY = 0x1018          # sub 1 vendor-ID, 2 product code, 3 revision, 4 serial number

#: Modes of operation 0x6060 and the bit of each in "supported drive modes" 0x6502.
MODE_CST = 10
MODE_BITS = {1: 0, 2: 1, 3: 2, 4: 3, 6: 5, 7: 6, 8: 7, 9: 8, 10: 9}

OBJECT_NAMES = {
    CONTROLWORD: "controlword", STATUSWORD: "statusword", MODES_OF_OPERATION: "modes of operation",
    MODES_DISPLAY: "modes of operation display", POSITION_ACTUAL: "position actual value",
    TARGET_TORQUE: "target torque", MAX_TORQUE: "max torque", RATED_TORQUE: "motor rated torque",
    TORQUE_ACTUAL: "torque actual value", 0x60E4: "additional position actual value",
    CONSUMER_HEARTBEAT: "consumer heartbeat time", PRODUCER_HEARTBEAT: "producer heartbeat time",
    DEVICE_TYPE: "device type", POLARITY: "polarity", SUPPORTED_MODES: "supported drive modes",
    INTERPOLATION_PERIOD: "interpolation time period", CYCLE_PERIOD: "communication cycle period",
    SYNC_OVERFLOW: "synchronous counter overflow value",
}

#: 0x607E bits (CiA 402-2): position polarity reverses position actual, target torque and torque actual
#: together; velocity polarity reverses velocity values (nothing in cyclic synchronous torque).
POLARITY_POSITION = 0x80
POLARITY_VELOCITY = 0x40


def object_label(index: int, subindex: int | None = None) -> str:
    """``0x6077 (torque actual value)`` / ``0x60E4:01 (additional position actual value)``."""
    where = f"0x{index:04X}" if subindex is None else f"0x{index:04X}:{subindex:02X}"
    name = OBJECT_NAMES.get(index)
    if name is None and 0x1400 <= index < 0x1C00:
        kind = {0x14: "RPDO communication", 0x16: "RPDO mapping", 0x18: "TPDO communication",
                0x1A: "TPDO mapping"}.get((index >> 8) & 0xFE)
        if kind:
            name = f"{kind} {(index & 0x1FF) + 1}"
    return f"{where} ({name})" if name else where


# ----- controlword commands (CiA 402-2, table "device control commands") -------------
CW_DISABLE_VOLTAGE = 0x0000
CW_QUICK_STOP = 0x0002
CW_SHUTDOWN = 0x0006
CW_SWITCH_ON = 0x0007
CW_ENABLE_OPERATION = 0x000F
CW_FAULT_RESET = 0x0080

# ----- power states -------------------------------------------------------------------
NOT_READY = "NOT READY TO SWITCH ON"
SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
READY_TO_SWITCH_ON = "READY TO SWITCH ON"
SWITCHED_ON = "SWITCHED ON"
OPERATION_ENABLED = "OPERATION ENABLED"
QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
FAULT_REACTION_ACTIVE = "FAULT REACTION ACTIVE"
FAULT = "FAULT"

#: (mask, value) of the statusword per state, checked in this order.
_SW_PATTERNS = (
    (0x4F, 0x00, NOT_READY),
    (0x4F, 0x40, SWITCH_ON_DISABLED),
    (0x6F, 0x21, READY_TO_SWITCH_ON),
    (0x6F, 0x23, SWITCHED_ON),
    (0x6F, 0x27, OPERATION_ENABLED),
    (0x6F, 0x07, QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, FAULT_REACTION_ACTIVE),
    (0x4F, 0x08, FAULT),
)

SW_VOLTAGE_ENABLED = 0x0010   # statusword bit 4: main voltage at the power stage
SW_REMOTE = 0x0200            # statusword bit 9: the drive follows the bus's controlword
SW_WARNING = 0x0080           # statusword bit 7: a warning (which one: the drive's own objects)
SW_INTERNAL_LIMIT = 0x0800    # statusword bit 11: an internal limit is active (in CST: the torque is limited)

#: Statusword a drive reports in each state: state bits | voltage enabled (bit 4) where
#: the power stage is on | remote (bit 9, the drive follows the controlword).
STATUSWORD_OF = {
    NOT_READY: 0x0000,
    SWITCH_ON_DISABLED: 0x0040 | 0x0200,
    READY_TO_SWITCH_ON: 0x0021 | 0x0010 | 0x0200,
    SWITCHED_ON: 0x0023 | 0x0010 | 0x0200,
    OPERATION_ENABLED: 0x0027 | 0x0010 | 0x0200,
    QUICK_STOP_ACTIVE: 0x0007 | 0x0010 | 0x0200,
    FAULT_REACTION_ACTIVE: 0x000F | 0x0010 | 0x0200,
    FAULT: 0x0008 | 0x0200,
}


def decode_state(statusword: int) -> str:
    """Name of the power state a statusword reports (``"UNKNOWN"`` if none matches)."""
    for mask, value, name in _SW_PATTERNS:
        if statusword & mask == value:
            return name
    return "UNKNOWN"


def command_of(controlword: int) -> str:
    """The device control command encoded in bits 0-3 of a controlword (bit 7 aside)."""
    if not controlword & 0x02:
        return "disable voltage"
    if not controlword & 0x04:
        return "quick stop"
    if not controlword & 0x01:
        return "shutdown"
    if not controlword & 0x08:
        return "switch on"          # also "disable operation" from OPERATION ENABLED
    return "enable operation"


def drive_transition(state: str, controlword: int, previous_controlword: int,
                     quick_stop_option: int = 2) -> str:
    """Next power state of a drive given a new controlword (CiA 402-2 transitions 2-16).

    Automatic transitions (0/1 at power-up, 12 at the end of a quick stop,
    14 at the end of a fault reaction) are the caller's business.
    """
    cmd = command_of(controlword)
    if state == FAULT:
        # 15: fault reset on the rising edge of bit 7
        if controlword & CW_FAULT_RESET and not previous_controlword & CW_FAULT_RESET:
            return SWITCH_ON_DISABLED
        return FAULT
    if state in (NOT_READY, FAULT_REACTION_ACTIVE):
        return state
    if state == SWITCH_ON_DISABLED:
        return READY_TO_SWITCH_ON if cmd == "shutdown" else state                     # 2
    if state == READY_TO_SWITCH_ON:
        if cmd in ("disable voltage", "quick stop"):
            return SWITCH_ON_DISABLED                                                  # 7
        if cmd == "switch on":
            return SWITCHED_ON                                                         # 3
        if cmd == "enable operation":
            return OPERATION_ENABLED                                                   # 3 + 4
        return state
    if state == SWITCHED_ON:
        if cmd in ("disable voltage", "quick stop"):
            return SWITCH_ON_DISABLED                                                  # 10
        if cmd == "shutdown":
            return READY_TO_SWITCH_ON                                                  # 6
        if cmd == "enable operation":
            return OPERATION_ENABLED                                                   # 4
        return state
    if state == OPERATION_ENABLED:
        return {"disable voltage": SWITCH_ON_DISABLED,                                 # 9
                "quick stop": QUICK_STOP_ACTIVE,                                       # 11
                "shutdown": READY_TO_SWITCH_ON,                                        # 8
                "switch on": SWITCHED_ON}.get(cmd, state)                              # 5
    if state == QUICK_STOP_ACTIVE:
        if cmd == "disable voltage":
            return SWITCH_ON_DISABLED                                                  # 12
        if cmd == "enable operation" and quick_stop_option in (5, 6, 7, 8):
            return OPERATION_ENABLED                                                   # 16
        return state
    return state


def enable_blocker(statusword: int) -> tuple[str, str] | None:
    """``(what, fix)`` when a statusword says what keeps a drive from enabling, something waiting longer
    will not change and no setting of the host cures; None when it says nothing of the kind."""
    if not statusword & SW_REMOTE:
        return ("remote (bit 9) is off: the drive reports local control (its panel or the vendor's software) "
                "and ignores the host's controlword", "the drive: hand its control to the bus")
    if decode_state(statusword) == READY_TO_SWITCH_ON and not statusword & SW_VOLTAGE_ENABLED:
        return ("voltage enabled (bit 4) is off: its power stage has no main voltage",
                "the drive: main power on, E-stop and safe torque off released")
    return None


def next_controlword(state: str, previous_controlword: int) -> int:
    """The controlword a master sends to walk a drive from ``state`` towards OPERATION ENABLED."""
    if state == FAULT:
        # a fault reset needs a rising edge of bit 7
        return CW_DISABLE_VOLTAGE if previous_controlword & CW_FAULT_RESET else CW_FAULT_RESET
    return {SWITCH_ON_DISABLED: CW_SHUTDOWN, NOT_READY: CW_SHUTDOWN, READY_TO_SWITCH_ON: CW_SWITCH_ON,
            SWITCHED_ON: CW_ENABLE_OPERATION, OPERATION_ENABLED: CW_ENABLE_OPERATION,
            QUICK_STOP_ACTIVE: CW_DISABLE_VOLTAGE}.get(state, CW_DISABLE_VOLTAGE)


# ----- PDO mapping (CiA 301 7.4.8.4) --------------------------------------------------
PDO_INVALID = 0x80000000   # COB-ID bit 31: PDO does not exist / is not valid
RTR_NOT_ALLOWED = 0x40000000
TRANS_SYNC_EVERY = 1       # transmission type 1: synchronous, every SYNC


def mapping_entry(index: int, subindex: int, bits: int) -> int:
    """A PDO mapping entry: index (16 bit) | subindex (8 bit) | length in bits (8 bit)."""
    return (index << 16) | (subindex << 8) | bits


def split_mapping_entry(entry: int) -> tuple[int, int, int]:
    return (entry >> 16) & 0xFFFF, (entry >> 8) & 0xFF, entry & 0xFF


#: struct codes of the CANopen basic data types (CiA 301 table 44) used in PDOs.
STRUCT_CODE = {0x01: "?", 0x02: "b", 0x03: "h", 0x04: "i", 0x05: "B", 0x06: "H", 0x07: "I",
               0x08: "f", 0x15: "q", 0x1B: "Q"}


def pdo_struct(data_types: list[int]) -> struct.Struct:
    """Little-endian struct packing the given data types back to back (byte-aligned PDOs)."""
    try:
        return struct.Struct("<" + "".join(STRUCT_CODE[t] for t in data_types))
    except KeyError as exc:
        raise ValueError(f"data type 0x{exc.args[0]:04X} cannot be packed into a PDO here") from None


# ----- bus timing (worst-case bit stuffing) -------------------------------------------
def frame_bits(data_bytes: int, extended: bool = False) -> int:
    """Worst-case length of a CAN 2.0 data frame in bits, bit stuffing and 3-bit intermission included.

    Davis, Burns, Bril & Lukkien (2007), Eq. (1): C = g + 8 s + 13 + floor((g + 8 s - 1) / 4)
    with g = 34 (11-bit identifier) or 54 (29-bit), s = data bytes.
    """
    g = 54 if extended else 34
    s = int(data_bytes)
    return g + 8 * s + 13 + (g + 8 * s - 1) // 4


# ----- SDO abort codes and EMCY codes (texts for error messages) ----------------------
SDO_ABORT_TEXT = {
    0x05040000: "SDO protocol timed out",
    0x06010000: "unsupported access to an object",
    0x06010001: "attempt to read a write-only object",
    0x06010002: "attempt to write a read-only object",
    0x06020000: "object does not exist in the object dictionary",
    0x06040041: "object cannot be mapped to the PDO",
    0x06040042: "the number and length of the objects to be mapped would exceed the PDO length",
    0x06070010: "data type does not match, length of service parameter does not match",
    0x06090011: "sub-index does not exist",
    0x06090030: "invalid value for parameter",
    0x08000000: "general error",
    0x08000020: "data cannot be transferred or stored to the application",
    0x08000022: "data cannot be transferred because of the present device state",
}


def abort_text(code: int) -> str:
    return f"SDO abort 0x{code:08X} ({SDO_ABORT_TEXT.get(code, 'unknown abort code')})"


#: CiA 301 "RPDO timeout": no RPDO within its event timer (0x1400:05), so the host was late
EMCY_RPDO_TIMEOUT = 0x8250
#: CiA 301 "life guard error or heartbeat error": the drive's consumer of the host's heartbeat (0x1016) timed out
EMCY_HEARTBEAT = 0x8130

EMCY_TEXT = {
    0x1000: "generic error", 0x2310: "continuous over-current", 0x3210: "DC link over-voltage",
    0x4310: "drive temperature", 0x5000: "device hardware", 0x6000: "device software",
    0x6320: "parameter error",
    0x7305: "incremental sensor 1 fault", 0x8110: "CAN overrun (objects lost)",
    0x8130: "life guard error or heartbeat error", 0x8210: "PDO not processed due to length error",
    0x8240: "unexpected SYNC data length", 0x8250: "RPDO timeout",
    0x8611: "following error", 0x8612: "reference limit", 0xFF00: "device specific",
}


def emcy_text(code: int) -> str:
    text = EMCY_TEXT.get(code) or EMCY_TEXT.get(code & 0xFF00) or EMCY_TEXT.get(code & 0xF000, "")
    return f"EMCY 0x{code:04X}" + (f" ({text})" if text else "")
