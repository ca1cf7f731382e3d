"""A CiA 402 servo drive over CANopen: the backend (:mod:`.drive`), its configuration, the
402 profile's objects, PDO setup, frame I/O and the sample stream, and the emulated drive
(:mod:`.emulated_drive`, its faults and its launcher :mod:`.emulator`).
"""
