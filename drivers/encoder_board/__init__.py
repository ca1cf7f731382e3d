"""The serial encoder board: the backend (:mod:`.board`), its configuration, the wire protocol
(``docs/serial-protocol.md``) and the emulated board on a pseudo-terminal (:mod:`.emulator`).
"""
