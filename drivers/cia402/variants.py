"""Drive variants: how a real vendor's CiA 402 drive differs from the generic EDS, for the emulated drive.

A :class:`DriveProfile` changes the emulated drive's own object dictionary (the host keeps
reading its EDS, as it would a generic one) and a few behaviours, the way drives on the market
differ:

* ``absent``: objects the drive does not have (an SDO access is aborted with 0x06020000,
  mapping one with 0x06020000 too);
* ``max_mapped``: mapping entries per PDO (the mapping records end there: writing a further
  entry is aborted with 0x06090011, a count above it with 0x06040042);
* ``not_mappable``: objects the drive refuses in a PDO (abort 0x06040041);
* ``read_only``: objects the drive does not let a master write (abort 0x06010002);
* ``interpolation_period``: the drive has 0x60C2 (interpolation time period: sub 1 the value,
  UNSIGNED8; sub 2 the power of ten, INTEGER8, -6..0 accepted, else abort 0x06090030) and
  will not enable a cyclic synchronous mode while it is 0 (FAULT, EMCY 0x6320);
* ``polarity``: 0x607E at power-up;
* ``sync_overflow``: 0x1019 at power-up (SYNCs must carry a counter; one without is ignored, EMCY
  0x8240).

:data:`PROFILES` names the variants; ``generic`` is the drive as the EDS describes it.
"""

from __future__ import annotations

from dataclasses import dataclass

import canopen
from canopen.objectdictionary import ODRecord, ODVariable

from drivers.cia402 import profile as p402

INTERPOLATION_PERIOD = p402.INTERPOLATION_PERIOD
PARAMETER_ERROR = 0x6320           # EMCY: software parameter error (CiA 301 error code table)


@dataclass(frozen=True)
class DriveProfile:
    """How one drive variant differs from the generic EDS (see the module)."""

    name: str
    summary: str
    absent: tuple[int, ...] = ()
    max_mapped: int | None = None
    not_mappable: tuple[int, ...] = ()
    read_only: tuple[int, ...] = ()
    interpolation_period: bool = False
    polarity: int | None = None
    sync_overflow: int = 0

    def apply(self, od: canopen.ObjectDictionary) -> None:
        """Change a drive's object dictionary (imported from the EDS) into this variant's."""
        for index in self.absent:
            if index in od:
                del od[index]
        for index in self.not_mappable:
            for var in _variables(od, index):
                var.pdo_mappable = False
        for index in self.read_only:
            for var in _variables(od, index):
                var.access_type = "ro" if var.access_type != "const" else var.access_type
        if self.max_mapped is not None:
            for base in (0x1600, 0x1A00):
                n = 0
                while base + n in od:
                    record = od[base + n]
                    assert isinstance(record, ODRecord)
                    for sub in [s for s in record.subindices if s > self.max_mapped]:
                        del record[sub]
                    record[0].max = self.max_mapped
                    n += 1
        if self.interpolation_period and INTERPOLATION_PERIOD not in od:
            od.add_object(_interpolation_period_record())


def _variables(od: canopen.ObjectDictionary, index: int) -> list[ODVariable]:
    if index not in od:
        return []
    obj = od[index]
    if isinstance(obj, ODVariable):
        return [obj]
    return [v for v in obj.values() if v.subindex > 0]


def _interpolation_period_record() -> ODRecord:
    record = ODRecord("Interpolation time period", INTERPOLATION_PERIOD)
    for sub, name, code, default in ((0, "Highest sub-index supported", canopen.objectdictionary.UNSIGNED8, 2),
                                     (1, "Interpolation time period value", canopen.objectdictionary.UNSIGNED8, 0),
                                     (2, "Interpolation time index", canopen.objectdictionary.INTEGER8, -3)):
        var = ODVariable(name, INTERPOLATION_PERIOD, sub)
        var.data_type = code
        var.access_type = "ro" if sub == 0 else "rw"
        var.default = default
        var.pdo_mappable = False
        record.add_member(var)
    return record


PROFILES: dict[str, DriveProfile] = {p.name: p for p in (
    DriveProfile("generic", "as the EDS describes it"),
    DriveProfile("no-additional-position", "no 0x60E4: the drive has no second encoder input object",
                 absent=(0x60E4,)),
    DriveProfile("four-objects-per-pdo", "at most 4 objects mapped per PDO", max_mapped=4),
    DriveProfile("two-objects-per-pdo", "at most 2 objects mapped per PDO", max_mapped=2),
    DriveProfile("torque-actual-not-mappable", "0x6077 only by SDO, not in a PDO", not_mappable=(p402.TORQUE_ACTUAL,)),
    DriveProfile("interpolation-period", "cyclic synchronous modes need 0x60C2 set; 0x1006 read-only",
                 read_only=(p402.CYCLE_PERIOD,), interpolation_period=True),
    DriveProfile("polarity-set", "0x607E = 0x80 at power-up (position polarity)", polarity=p402.POLARITY_POSITION),
    DriveProfile("sync-counter", "0x1019 = 4 at power-up: SYNCs must carry a counter 1..4", sync_overflow=4),
)}


def drive_profile(name: str | DriveProfile) -> DriveProfile:
    """The named profile (one of :data:`PROFILES`), or the profile given."""
    if isinstance(name, DriveProfile):
        return name
    try:
        return PROFILES[name]
    except KeyError:
        raise ValueError(f"unknown drive profile {name!r}; one of {', '.join(PROFILES)}") from None


def interpolation_period(seconds: float) -> tuple[int, int]:
    """0x60C2 (value, index) for a period: value * 10**index s, the value an integer 1..255 (the finest
    coarsest index that gives it exactly, else the closest rounding)."""
    best: tuple[float, int, int] | None = None
    for index in range(0, -7, -1):
        value = seconds / 10.0 ** index
        n = round(value)
        if 1 <= n <= 255:
            err = abs(value - n) / value
            if err < 1e-9:
                return n, index
            if best is None or err < best[0]:
                best = (err, n, index)
    if best is None:
        raise ValueError(f"{seconds!r} s is outside what 0x60C2 can express (1e-6 .. 255 s)")
    return best[1], best[2]
