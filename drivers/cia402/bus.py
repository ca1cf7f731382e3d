"""Opening the CAN bus: python-can, with ``udp_multicast`` confined to this host unless asked otherwise.

python-can's ``udp_multicast`` interface binds its socket to every interface (0.0.0.0), joins the
group on the default interface and sends with a hop limit of 1: any host on the LAN (or a datagram
to this host's own address) can put frames on "the bus" - an EMCY, or fake position data that the
safety monitor would believe - and our frames leave the host. The emulated drive is a process on
this host, so by default the bus is confined to the loopback interface:

* the socket is bound to the *group* address (a unicast datagram to any address of this host does
  not reach it) and joins the group on 127.0.0.1 only;
* multicast goes out through 127.0.0.1 with a hop limit (TTL) of 0, looped back to this host;
* :class:`drivers.cia402.frames.FrameIO` also drops any datagram whose source is not a loopback
  address (counted as ``foreign``);
* as on CAN, a node does not receive its own frames (python-can's ``receive_own_messages=False``):
  each bus sends from a socket of its own bound to 127.0.0.1 and an ephemeral port, and drops the
  datagrams whose source is that address (multicast loopback would hand them back).

A bus that really spans hosts needs ``bus_options = { allow_network = true }`` (then python-can's
own socket and the configured ``hop_limit`` are used, and the user has said so).
"""

from __future__ import annotations

import errno
import socket
import struct
from collections.abc import Mapping
from typing import Any

import can
from can import CanProtocol
from can.interfaces.udp_multicast.bus import GeneralPurposeUdpMulticastBus, UdpMulticastBus

from rt_ident.errors import ConfigError

LOOPBACK = "127.0.0.1"
_SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)


def confined(bus_kwargs: Mapping[str, Any]) -> bool:
    """True when a ``udp_multicast`` bus is to stay on this host (the default)."""
    return bus_kwargs.get("interface") == "udp_multicast" and not bus_kwargs.get("allow_network", False)


def check_interface(interface: str) -> None:
    """Refuse ``socketcan`` on a host whose kernel has no CAN support (one line, before anything opens)."""
    if interface != "socketcan":
        return
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except (AttributeError, OSError) as exc:
        why = getattr(exc, "strerror", None) or str(exc)
        raise ConfigError("backend.interface", f"no SocketCAN on this host ({why}); use interface = "
                          '"udp_multicast" (with emulate = true for the emulated drive) or "virtual", or load '
                          "the kernel's CAN modules (modprobe can_raw)") from None


def bus_error_hint(code: int | None, interface: str, channel: str, bitrate: int) -> str:
    """What an errno from sending on a SocketCAN interface means on a bench ("" for others)."""
    if interface != "socketcan":
        return ""
    if code == errno.ENETDOWN:
        return f"the interface is down: bring it up (sudo ip link set {channel} up type can bitrate {bitrate})"
    if code == errno.ENOBUFS:
        return (f"its transmit queue is full: no node acknowledges this host's frames (a drive without power or "
                f"off the bus, a bitrate other than {bitrate}, a missing terminator), or the controller is "
                f"bus-off (ip -details -statistics link show {channel})")
    return ""


def error_code(exc: BaseException) -> int | None:
    """The errno a python-can error carries (``error_code``), or an ``OSError``'s."""
    code = getattr(exc, "error_code", None)
    if not isinstance(code, int):
        code = getattr(exc, "errno", None)
    return code if isinstance(code, int) else None


def open_bus(bus_kwargs: Mapping[str, Any]) -> can.BusABC:
    """``can.Bus(**bus_kwargs)``, or the loopback-confined ``udp_multicast`` bus (see the module)."""
    kw = dict(bus_kwargs)
    network = bool(kw.pop("allow_network", False))
    if kw.get("interface") != "udp_multicast" or network:
        return can.Bus(**kw)
    return LoopbackUdpMulticastBus(channel=str(kw.get("channel") or UdpMulticastBus.DEFAULT_GROUP_IPv4),
                                   port=int(kw.get("port") or 43113), fd=bool(kw.get("fd", True)))


class _LoopbackMulticast(GeneralPurposeUdpMulticastBus):
    """python-can's multicast handler with a socket bound to the group on the loopback interface, and a
    send socket of its own whose address (:attr:`own_address`) marks this bus's frames: they are dropped
    on receipt (a CAN controller does not receive what it sends)."""

    def __init__(self, group: str, port: int, hop_limit: int, *args: Any, **kwargs: Any) -> None:
        super().__init__(group, port, hop_limit, *args, **kwargs)
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, struct.pack("@I", 0))
            tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
            tx.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(LOOPBACK))
            tx.bind((LOOPBACK, 0))
        except OSError:
            tx.close()
            self._socket.close()
            raise
        self.tx = tx
        self.own_address: tuple[str, int] = tx.getsockname()

    def send(self, data: bytes, timeout: float | None = None) -> None:
        try:
            self.tx.sendto(data, self._send_destination)
        except OSError as error:
            raise can.CanOperationError("failed to send via socket") from error

    def recv(self, timeout: float | None = None) -> Any:
        result = super().recv(timeout)
        if result is not None and tuple(result[1][:2]) == self.own_address:
            return None                 # our own frame (BusABC.recv keeps waiting until its timeout)
        return result

    def shutdown(self) -> None:
        super().shutdown()
        self.tx.close()

    def _create_socket(self, address_family: socket.AddressFamily) -> socket.socket:
        if address_family != socket.AF_INET:
            raise OSError(errno.EAFNOSUPPORT, "the loopback-confined bus needs an IPv4 multicast group")
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, struct.pack("@I", 0))
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(LOOPBACK))
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if hasattr(socket, "SO_REUSEPORT"):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
            try:
                sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
                self.timestamp_nanosecond = True
            except OSError:
                self.timestamp_nanosecond = False
            sock.bind((self.group, self.port))
            mreq = socket.inet_aton(self.group) + socket.inet_aton(LOOPBACK)
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreq)
            return sock
        except OSError:
            sock.close()
            raise


class LoopbackUdpMulticastBus(UdpMulticastBus):
    """python-can's ``udp_multicast`` bus (same wire format), confined to this host."""

    def __init__(self, channel: str = UdpMulticastBus.DEFAULT_GROUP_IPv4, port: int = 43113, fd: bool = True,
                 **kwargs: Any) -> None:
        try:
            socket.inet_aton(channel)
        except OSError:
            raise ConfigError("backend.channel", f"{channel!r}: the loopback-confined udp_multicast bus needs an "
                              "IPv4 multicast group (or bus_options.allow_network = true)") from None
        can.BusABC.__init__(self, channel, **kwargs)
        self._loopback = _LoopbackMulticast(channel, port, 0)
        self._multicast = self._loopback
        self._can_protocol = CanProtocol.CAN_FD if fd else CanProtocol.CAN_20

    @property
    def own_address(self) -> tuple[str, int]:
        """Source address of this bus's datagrams (its frames carry it; receivers here drop them)."""
        return self._loopback.own_address

    def tx_fileno(self) -> int:
        """File descriptor of the send socket."""
        return self._loopback.tx.fileno()
