"""MAVLink links on asyncio: UDP in/out, TCP client/server, serial.

Connection strings are the ones pymavlink and MAVProxy users know:
``udpin:HOST:PORT`` (listen; replies go to whoever sent MAVLink; ``udp:`` and a bare
``HOST:PORT`` mean the same, as in MAVProxy), ``udpout:HOST:PORT`` (send there;
replies come back), ``udpbcast:ADDRESS:PORT`` (send to a broadcast address until
a peer answers, then to that peer), ``tcp:HOST:PORT`` (connect, reconnecting with
back-off when the peer goes away), ``tcpin:HOST:PORT`` (listen for clients), and a
serial device (``/dev/ttyUSB0``, ``/dev/ttyUSB0,57600`` as MAVProxy writes it,
``serial:/dev/ttyACM0:921600``). MAVProxy's other forms (``mcast:``, ``ws:``,
``wsserver:``) are not taken.

Every link hands received bytes, with the peer they came from, to one callback;
the pipeline finds the packets in them (a byte stream's per peer, so that streams
from different peers never interleave inside a packet). A UDP sender becomes a
peer, sent every reply, only once a datagram of its holds a MAVLink packet whose
CRC checks, and while fewer than :data:`UDP_PEERS_MAX` are. Sending never blocks: a
link that cannot send right now (no peer yet, TCP reconnecting, a TCP peer that
leaves :data:`TCP_BACKLOG` bytes unread) drops the packet.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import os
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from mavest.mavlink import framing

log = logging.getLogger("mavest")

Receiver = Callable[["Link", bytes, Any], None]

UDP_PEER_TIMEOUT = 30.0  # s: a udpin peer silent this long gets no more replies
# udpin peers gone silent remembered (to say when one is back): the latest this many
SILENT_PEERS_KEPT = 256
# udpin peers replied to at once, at most: each is sent every reply, so that senders
# without end (a flood from many sockets, spoofed source addresses) would make the
# service a reflector and starve the vehicle it serves
UDP_PEERS_MAX = 32
TCP_MIN_BACKOFF = 0.25  # s: the first wait before connecting again


class LinkError(Exception):
    """A connection that cannot be opened (bad string, port taken, no device)."""


def _reason(endpoint: Endpoint, error: OSError) -> str:
    """An OSError in words: a name that does not resolve says so (socket.gaierror's
    numbers, -2 and the like, are not errno values: os.strerror calls them unknown)."""
    if isinstance(error, socket.gaierror):
        return f"host {endpoint.host!r} not found"
    return os.strerror(error.errno) if error.errno else str(error)


def _cannot_listen(endpoint: Endpoint, error: OSError) -> LinkError:
    # asyncio's server words the error its own way ("error while attempting to bind…")
    reason = _reason(endpoint, error)
    if error.errno == errno.EADDRINUSE:
        reason += f" (another program has port {endpoint.port}: a ground station, another mavest?)"
    return LinkError(f"cannot listen on {endpoint}: {reason}")


@dataclass(frozen=True)
class Endpoint:
    """A parsed connection string."""

    kind: str  # "udpin" | "udpout" | "udpbcast" | "tcp" | "tcpin" | "serial"
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 115200

    def __str__(self) -> str:
        if self.kind == "serial":
            return f"serial:{self.device}:{self.baud}"
        return f"{self.kind}:{self.host}:{self.port}"


_NETWORK_KINDS = {
    "udpin": "udpin",
    "udp": "udpin",
    "udpout": "udpout",
    "udpbcast": "udpbcast",
    "tcp": "tcp",
    "tcpin": "tcpin",
}


def parse_endpoint(text: str, baud: int = 115200) -> Endpoint:
    """Parse a connection string; :class:`LinkError` says what is wrong with it."""
    text = text.strip()
    if text.startswith("/") or text.upper().startswith("COM") or text.startswith("serial:"):
        device = text.removeprefix("serial:")
        for separator in (",", ":"):  # MAVProxy's DEVICE,BAUD and pymavlink's DEVICE:BAUD
            head, _, tail = device.rpartition(separator)
            if head and tail.isdigit():
                device, baud = head, int(tail)
                break
        if baud <= 0:
            raise LinkError(f"serial baud rate {baud} must be positive")
        return Endpoint("serial", device=device, baud=baud)
    kind, _, rest = text.partition(":")
    if kind not in _NETWORK_KINDS:
        if rest.isdigit() and kind:  # MAVProxy's bare HOST:PORT listens there (udpin)
            kind, rest = "udpin", text
        else:
            raise LinkError(
                f"unknown connection {text!r}: use udpin:HOST:PORT (or udp:), udpout:HOST:PORT, "
                "udpbcast:ADDRESS:PORT, tcp:HOST:PORT, tcpin:HOST:PORT or a serial device such as "
                "/dev/ttyUSB0 or /dev/ttyUSB0,57600"
            )
    host, _, port_text = rest.rpartition(":")
    if not host or not port_text.isdigit() or not 0 < int(port_text) < 65536:
        raise LinkError(f"connection {text!r} needs HOST:PORT with a port in 1–65535")
    return Endpoint(_NETWORK_KINDS[kind], host=host, port=int(port_text))


class Link:
    """One MAVLink connection. Subclasses open it in :meth:`start`."""

    def __init__(self, endpoint: Endpoint) -> None:
        self.endpoint = endpoint
        self._receiver: Receiver | None = None

    def __str__(self) -> str:
        return str(self.endpoint)

    async def start(self, receiver: Receiver) -> None:
        self._receiver = receiver

    def send(self, packet: bytes) -> None:
        raise NotImplementedError

    def close(self) -> None:
        """Release the connection (idempotent)."""

    def _deliver(self, data: bytes, peer: Any) -> None:
        if self._receiver is not None:
            self._receiver(self, data, peer)


class _DatagramProtocol(asyncio.DatagramProtocol):
    """asyncio's side of a UDP link: hands each datagram and error to the link's
    handlers (given, so that the link's own methods stay its own)."""

    def __init__(
        self,
        on_datagram: Callable[[bytes, Any], None],
        on_error: Callable[[Exception], None],
    ) -> None:
        self.on_datagram = on_datagram
        self.on_error = on_error

    def datagram_received(self, data: bytes, addr: Any) -> None:
        self.on_datagram(data, addr)

    def error_received(self, exc: Exception) -> None:
        # ICMP "port unreachable" after sending to a peer that is not listening (yet)
        self.on_error(exc)


class UdpLink(Link):
    """``udpin`` listens and replies to every peer heard from recently (a sender of
    MAVLink: :func:`_holds_mavlink`); ``udpout`` sends to one address and listens for
    its replies; ``udpbcast`` sends to a broadcast address until a peer answers with
    MAVLink, then to that peer only (as pymavlink)."""

    def __init__(self, endpoint: Endpoint) -> None:
        super().__init__(endpoint)
        self._transport: asyncio.DatagramTransport | None = None
        self._peers: dict[Any, float] = {}  # udpin: who to reply to → when last heard
        self._silent: dict[Any, float] = {}  # peers dropped for silence → when last heard
        self._said_full = False  # that UDP_PEERS_MAX peers are replied to (said once)
        self._warned_unreachable = False
        # udpbcast: where packets go (the broadcast address, then the peer that answered)
        self._destination: Any = (endpoint.host, endpoint.port)
        self._answered = False

    async def start(self, receiver: Receiver) -> None:
        await super().start(receiver)
        loop = asyncio.get_running_loop()
        address = (self.endpoint.host, self.endpoint.port)

        def protocol() -> _DatagramProtocol:
            return _DatagramProtocol(self._on_datagram, self._on_error)

        try:
            if self.endpoint.kind == "udpin":
                transport, _ = await loop.create_datagram_endpoint(protocol, local_addr=address)
            elif self.endpoint.kind == "udpbcast":
                transport, _ = await loop.create_datagram_endpoint(
                    protocol, local_addr=("0.0.0.0", 0), allow_broadcast=True
                )
            else:
                transport, _ = await loop.create_datagram_endpoint(protocol, remote_addr=address)
        except OSError as error:
            if self.endpoint.kind == "udpin":
                raise _cannot_listen(self.endpoint, error) from None
            raise LinkError(
                f"cannot open {self.endpoint}: {_reason(self.endpoint, error)}"
            ) from None
        self._transport = transport  # type: ignore[assignment]
        sock = transport.get_extra_info("socket")
        if sock is not None:  # a burst of IMU packets must not overflow the kernel's buffer
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)

    def _on_datagram(self, data: bytes, addr: Any) -> None:
        if self.endpoint.kind == "udpin":
            now = time.monotonic()
            if addr in self._peers:
                self._peers[addr] = now
            elif len(self._peers) >= UDP_PEERS_MAX:
                if not self._said_full and _holds_mavlink(data):
                    self._said_full = True
                    log.warning(
                        "%s: %d peers replied to already: %s and any later are not, until "
                        "one falls silent (what they send is still read)",
                        self.endpoint,
                        UDP_PEERS_MAX,
                        _address(addr),
                    )
            elif _holds_mavlink(data):
                self._on_new_peer(addr, now)
                self._peers[addr] = now
        elif self.endpoint.kind == "udpbcast" and not self._answered and _holds_mavlink(data):
            self._answered = True
            self._destination = addr
            log.info("%s: answered by %s; sending to it from now on", self.endpoint, _address(addr))
        self._deliver(data, addr)

    def _on_new_peer(self, addr: Any, now: float) -> None:
        who = _address(addr)
        last_heard = self._silent.pop(addr, None)
        if last_heard is None:
            log.info("%s: hearing from %s", self.endpoint, who)
        else:
            log.info(
                "%s: %s is back after %.0f s of silence; replying again",
                self.endpoint,
                who,
                now - last_heard,
            )

    def _on_error(self, exc: Exception) -> None:
        if not self._warned_unreachable:
            self._warned_unreachable = True
            log.warning("%s: %s (is the peer listening?)", self.endpoint, exc)

    def send(self, packet: bytes) -> None:
        transport = self._transport
        if transport is None or transport.is_closing():
            return
        if self.endpoint.kind == "udpout":
            transport.sendto(packet)
            return
        if self.endpoint.kind == "udpbcast":
            transport.sendto(packet, self._destination)
            return
        now = time.monotonic()
        for addr, seen in list(self._peers.items()):
            if now - seen > UDP_PEER_TIMEOUT:
                del self._peers[addr]
                self._silent[addr] = seen
                if len(self._silent) > SILENT_PEERS_KEPT:  # the one silent longest is forgotten
                    del self._silent[next(iter(self._silent))]
                log.warning(
                    "%s: nothing from %s for %g s; no replies to it until it sends again",
                    self.endpoint,
                    _address(addr),
                    UDP_PEER_TIMEOUT,
                )
                continue
            transport.sendto(packet, addr)

    def close(self) -> None:
        if self._transport is not None:
            self._transport.close()


def _holds_mavlink(datagram: bytes) -> bool:
    """Whether a datagram holds a MAVLink packet (whole, a known message, its CRC valid):
    what makes its sender a peer. Noise from any address (a port scan, a flood from
    spoofed addresses) must not: each peer is sent every reply and remembered."""
    found = framing.find_packets(np.frombuffer(datagram, dtype=np.uint8), whole=True)
    return found.index.shape[1] > 0


def _address(addr: Any) -> str:
    return f"{addr[0]}:{addr[1]}" if isinstance(addr, tuple) and len(addr) >= 2 else str(addr)


class TcpClientLink(Link):
    """``tcp:HOST:PORT``: connects, and reconnects with back-off when the peer goes away.

    A connection that carried data is taken up again at once when it drops; each
    attempt after that which fails (refused, or accepted and closed at once, as a
    peer that is restarting does) waits twice as long as the one before, up to
    ``max_backoff``.
    """

    def __init__(self, endpoint: Endpoint, max_backoff: float = 5.0) -> None:
        super().__init__(endpoint)
        self.max_backoff = max_backoff
        self._writer: asyncio.StreamWriter | None = None
        self._task: asyncio.Task[None] | None = None
        self._dropping: set[asyncio.StreamWriter] = set()  # the connection, if unread

    async def start(self, receiver: Receiver) -> None:
        await super().start(receiver)
        self._task = asyncio.create_task(self._run(), name=f"link {self.endpoint}")

    async def _run(self) -> None:
        backoff = TCP_MIN_BACKOFF
        failures = 0  # attempts in a row that brought no data
        while True:
            try:
                reader, writer = await asyncio.open_connection(
                    self.endpoint.host, self.endpoint.port
                )
            except OSError as error:
                failures += 1
                if failures == 1:
                    log.warning(
                        "%s: %s; retrying with back-off (at most every %g s)",
                        self.endpoint,
                        error.strerror or error.__class__.__name__,
                        self.max_backoff,
                    )
                log.debug("%s: attempt %d failed; next in %g s", self.endpoint, failures, backoff)
                await asyncio.sleep(backoff)
                backoff = min(2.0 * backoff, self.max_backoff)
                continue
            log.info("%s: connected", self.endpoint)
            self._writer = writer
            peer = writer.get_extra_info("peername")
            received = False
            try:
                while data := await reader.read(65536):
                    received = True
                    self._deliver(data, peer)
            except OSError:
                pass
            self._writer = None
            writer.close()
            if received:
                failures, backoff = 0, TCP_MIN_BACKOFF
                log.warning("%s: connection lost; reconnecting", self.endpoint)
                continue
            failures += 1
            if failures == 1:
                log.warning(
                    "%s: the peer closed the connection at once; retrying with back-off",
                    self.endpoint,
                )
            await asyncio.sleep(backoff)
            backoff = min(2.0 * backoff, self.max_backoff)

    def send(self, packet: bytes) -> None:
        writer = self._writer
        if writer is None or writer.is_closing():
            return
        _write_or_drop(writer, packet, self._dropping, self.endpoint)

    def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
        if self._writer is not None:
            self._writer.close()


# Bytes a TCP peer may leave unread before what is sent to it is dropped: a peer that
# never reads (or a link slower than the answers) would otherwise hold every packet
# in memory, for as long as it stays connected.
TCP_BACKLOG = 256 * 1024


def _write_or_drop(
    writer: asyncio.StreamWriter,
    packet: bytes,
    dropping: set[asyncio.StreamWriter],
    endpoint: Any,
) -> None:
    """Send, unless ``TCP_BACKLOG`` bytes already wait for this peer: then drop, as a
    link that cannot send does, said once while it lasts (``dropping``: the peers it
    lasts for)."""
    waiting = writer.transport.get_write_buffer_size()
    if waiting < TCP_BACKLOG:
        if writer in dropping:
            dropping.discard(writer)
            log.info("%s: %s reads again: sending to it again", endpoint, _peer_of(writer))
        writer.write(packet)
    elif writer not in dropping:
        dropping.add(writer)
        log.warning(
            "%s: %s does not read what is sent (%d kB wait): dropping packets to it until it does",
            endpoint,
            _peer_of(writer),
            waiting // 1024,
        )


def _peer_of(writer: asyncio.StreamWriter) -> str:
    """The TCP peer of a connection, for the log (only when a line is said)."""
    return f"peer {_address(writer.get_extra_info('peername'))}"


class TcpServerLink(Link):
    """``tcpin:HOST:PORT``: accepts any number of clients; sends to all of them."""

    def __init__(self, endpoint: Endpoint) -> None:
        super().__init__(endpoint)
        self._server: asyncio.base_events.Server | None = None
        self._clients: set[asyncio.StreamWriter] = set()
        self._dropping: set[asyncio.StreamWriter] = set()  # clients that do not read

    async def start(self, receiver: Receiver) -> None:
        await super().start(receiver)
        try:
            self._server = await asyncio.start_server(
                self._serve, self.endpoint.host, self.endpoint.port
            )
        except OSError as error:
            raise _cannot_listen(self.endpoint, error) from None

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        log.info("%s: client %s connected", self.endpoint, peer)
        self._clients.add(writer)
        try:
            while data := await reader.read(65536):
                self._deliver(data, peer)
        except OSError:
            pass
        finally:
            self._clients.discard(writer)
            self._dropping.discard(writer)
            writer.close()
            log.info("%s: client %s left", self.endpoint, peer)

    def send(self, packet: bytes) -> None:
        for writer in list(self._clients):
            if not writer.is_closing():
                _write_or_drop(writer, packet, self._dropping, self.endpoint)

    def close(self) -> None:
        for writer in list(self._clients):
            writer.close()
        if self._server is not None:
            self._server.close()


class SerialLink(Link):
    """A serial device (pyserial), read through the event loop's file-descriptor watch."""

    def __init__(self, endpoint: Endpoint) -> None:
        super().__init__(endpoint)
        self._port: Any = None

    async def start(self, receiver: Receiver) -> None:
        await super().start(receiver)
        import serial  # pyserial: imported here so that network-only use never needs it

        try:
            self._port = serial.Serial(self.endpoint.device, self.endpoint.baud, timeout=0)
        except (serial.SerialException, OSError) as error:
            raise LinkError(f"cannot open {self.endpoint.device}: {error}") from None
        asyncio.get_running_loop().add_reader(self._port.fileno(), self._on_readable)

    def _on_readable(self) -> None:
        try:
            data = self._port.read(65536)
        except Exception as error:  # the device went away (unplugged)
            log.error("%s: %s", self.endpoint, error)
            self.close()
            return
        if data:
            self._deliver(data, self.endpoint.device)

    def send(self, packet: bytes) -> None:
        if self._port is None or not self._port.is_open:
            return
        with contextlib.suppress(Exception):  # the device went away: dropped, as documented
            self._port.write(packet)

    def close(self) -> None:
        if self._port is not None and self._port.is_open:
            with contextlib.suppress(Exception):
                asyncio.get_running_loop().remove_reader(self._port.fileno())
            self._port.close()


def make_link(endpoint: Endpoint) -> Link:
    if endpoint.kind in ("udpin", "udpout", "udpbcast"):
        return UdpLink(endpoint)
    if endpoint.kind == "tcp":
        return TcpClientLink(endpoint)
    if endpoint.kind == "tcpin":
        return TcpServerLink(endpoint)
    return SerialLink(endpoint)
