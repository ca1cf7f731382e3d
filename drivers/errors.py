"""Errors raised by backends. All derive from :class:`rt_ident.errors.RtIdentError`."""

from __future__ import annotations

from rt_ident.errors import RtIdentError, ask_realtime


class DriverError(RtIdentError):
    """Root of backend errors. ``cause`` is a short machine-readable tag used in summaries; ``fix`` names
    the setting that cures it, where one does."""

    cause = "driver-error"
    fix: str | None = None

    def __init__(self, *args: object, fix: str | None = None) -> None:
        super().__init__(*args)
        if fix is not None:             # else the class's own (kept across processes in the instance's dict)
            self.fix = fix


class BackendNotFound(DriverError):
    cause = "backend-not-found"


class BackendStateError(DriverError):
    """A method was called in the wrong lifecycle state (e.g. read() before activate())."""

    cause = "lifecycle"


class DeviceConnectionError(DriverError):
    """The device cannot be reached: no answer from the node, missing port, no permission."""

    cause = "no-connection"


class DeviceTimeout(DriverError):
    """The device stopped answering within the configured time."""

    cause = "timeout"


class DriveNotReady(DriverError):
    """The device says what keeps it from enabling, and it is on the device (its power, its control), not in
    a setting; ``fix`` says what to do there."""

    cause = "not-ready"


class ProtocolError(DriverError):
    """Malformed traffic beyond what resynchronization can absorb (CRC storm, wrong EDS)."""

    cause = "protocol"


class DeviceFault(DriverError):
    """The device reported a fault (EMCY, fault state, heartbeat lost)."""

    cause = "device-fault"


class RpdoTimeout(DeviceFault):
    """The drive got no torque write within its RPDO deadline (EMCY 0x8250): the host was late, not the axis."""

    fix = ask_realtime("the drive got no torque write within its RPDO deadline", "a longer backend.rpdo_deadline_ms")


class HeartbeatLost(DeviceFault):
    """The drive heard no heartbeat from this host within its consumer time (EMCY 0x8130). The EMCY itself came
    over the bus, so the bus carries frames: the host sent its heartbeat late."""

    fix = ask_realtime("the drive heard no heartbeat from this host within its consumer time",
                       "a longer backend.heartbeat_consumer_ms")


class SafetyTrip(DriverError):
    """A host-side safety check tripped (position window, watchdog, torque)."""

    cause = "safety-trip"


class WatchdogTrip(SafetyTrip):
    """No fresh feedback for the configured number of ticks, or a motor encoder that did not move under torque
    (:func:`stuck_encoder_fix`). Where it is raised says the fix (``fix=``), if a setting is one."""

    cause = "watchdog"


#: the fix of the host's watchdog on a device whose samples stopped coming
STALE_FEEDBACK_FIX = ("the device's link (its cable, power and bus) and its sample rate; a larger "
                      "safety.watchdog_ticks only for a device that sends less often than the loop ticks")


def stuck_encoder_fix(torque_setting: str) -> str:
    """The fix of a watchdog trip on a motor encoder that did not move while torque was commanded;
    ``torque_setting``: the setting of the torque above which a motor at rest counts as stuck."""
    return (f"the motor encoder (its cable, supply and counts per revolution); or {torque_setting} at the axis's "
            "breakaway torque, where friction holds the motor at rest under a small torque")


class TravelLimitTrip(SafetyTrip):
    """The table would leave its window (position or predicted stopping distance)."""

    cause = "travel-limit"
    fix = ("the start position and the path's extent ([reference], excitation.peak) inside safety.window; a wider "
           "safety.window only as far as the table really travels")


class SpeedTrip(SafetyTrip):
    """The table moves faster than ``[safety] max_speed_m_s``."""

    cause = "speed-limit"
    fix = ("a slower path ([reference]) or a smaller excitation.peak; a higher safety.max_speed_m_s only as fast as "
           "the axis may move")


class SignTrip(SafetyTrip):
    """The axis accelerates against the torque commanded to it: a wrong torque or encoder sign makes the
    host's position loop positive feedback."""

    cause = "sign"
    fix = "backend.torque_sign, motor_encoder_sign or scale_sign: rt-ident commission finds which"
