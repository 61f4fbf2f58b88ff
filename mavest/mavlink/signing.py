"""MAVLink 2 message signing: the key, signing what mavest sends, checking what it hears.

pymavlink does the cryptography (the 48-bit SHA-256 signature over key and
packet, and the per-stream timestamp check against replays); this module gives
it a key in the formats autopilots and ground stations use, a timestamp on
MAVLink's signing clock, and mavest's policy for incoming packets:

- a signed packet whose signature fails, or whose timestamp is not newer than
  the last one of its stream (a replay), or is more than a minute behind our
  clock for a stream never heard before, is dropped and counted, always;
- an unsigned packet (MAVLink 1 included) is dropped and counted when
  ``require_signed`` is set, and accepted otherwise.

Keys (:func:`key_from_file`, :func:`key_from_text`):

- 32 bytes that are not text: the raw key, as ArduPilot stores it and
  SETUP_SIGNING carries it;
- 64 hexadecimal digits (whitespace ignored): the raw key written out;
- any other text: a passphrase, and the key is SHA-256 of it (leading and
  trailing whitespace removed), as MAVProxy's ``signing setup PASSPHRASE`` derives it.

A 32-byte file of printable text is read as text (hex or passphrase), not as
a raw key: 32 random key bytes are all printable text or whitespace with a
chance below 1e-11, while a 31-character passphrase and its newline are
exactly 32 bytes.
"""

from __future__ import annotations

import hashlib
import logging
import string
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavest.estimator.config import ConfigError

log = logging.getLogger("mavest")

KEY_LENGTH = 32  # bytes
KEY_ENVIRONMENT_VARIABLE = "MAVEST_SIGNING_KEY"

# Signing timestamps count 10 µs since 2015-01-01 00:00:00 UTC.
SIGNING_EPOCH_S = 1_420_070_400
_TICK_NS = 10_000

# The link id mavest signs with. One, fixed: every packet mavest sends is packed
# (and signed) once and the same bytes go out on every link, so they are one
# signed stream; a receiver that hears a packet over two routes must see the
# second copy as the replay it is, which a per-link id would hide. 0 is the
# first (here the only) channel of a sender, as in ArduPilot and pymavlink.
# Receivers key their replay check by (link id, system, component), so this
# never collides with the autopilot's own streams: mavest's component id differs.
LINK_ID = 0

_HEX_DIGITS = frozenset(string.hexdigits)


class SigningKeyError(ConfigError):
    """A key that cannot be read or is not one (the message says why, in one line)."""


@dataclass(frozen=True)
class Signing:
    """What a live run signs and accepts. The key never appears in a repr or a log."""

    key: bytes = field(repr=False)
    sign_outgoing: bool = True
    require_signed: bool = False
    source: str = ""  # where the key came from: a path or the environment variable
    kind: str = ""  # "raw", "hex" or "passphrase", for the log

    def __post_init__(self) -> None:
        if len(self.key) != KEY_LENGTH:
            raise SigningKeyError(f"a signing key is {KEY_LENGTH} bytes, not {len(self.key)}")

    def describe(self) -> str:
        """One line for the log: what is signed, what is accepted, which key (not its value)."""
        outgoing = "signing what it sends, " if self.sign_outgoing else ""
        incoming = "unsigned input dropped" if self.require_signed else "unsigned input accepted"
        return (
            f"MAVLink signing: {outgoing}verifying signed input, {incoming} "
            f"(key: {self.kind} from {self.source})"
        )


def signing_timestamp(unix_ns: int | None = None) -> int:
    """A time on MAVLink's signing clock (10 µs units since 2015-01-01 UTC); now by default."""
    ns = time.time_ns() if unix_ns is None else unix_ns
    return max(0, ns // _TICK_NS - SIGNING_EPOCH_S * (1_000_000_000 // _TICK_NS))


def key_from_text(text: str, source: str) -> tuple[bytes, str]:
    """The key in ``text``: 64 hex digits (whitespace ignored), else a passphrase.

    Returns the key and its kind ("hex" or "passphrase"). Text of 32 or more hex
    digits that are not 64 is refused rather than taken as a passphrase: it is
    far more likely a hex key with a digit lost or added in copying.
    """
    compact = "".join(text.split())
    if not compact:
        raise SigningKeyError(f"{source}: empty, no signing key in it")
    if set(compact) <= _HEX_DIGITS:
        if len(compact) == 2 * KEY_LENGTH:
            return _checked(bytes.fromhex(compact), source), "hex"
        if len(compact) >= KEY_LENGTH:
            raise SigningKeyError(
                f"{source}: {len(compact)} hexadecimal digits; a hex key has {2 * KEY_LENGTH}"
            )
    passphrase = text.strip()
    if not passphrase.isprintable():
        raise SigningKeyError(f"{source}: a passphrase must be one line of printable text")
    return _checked(hashlib.sha256(passphrase.encode("utf-8")).digest(), source), "passphrase"


def key_from_bytes(data: bytes, source: str) -> tuple[bytes, str]:
    """The key in a file's bytes: text is hex or a passphrase; anything else must be
    exactly the 32 raw bytes. Returns the key and its kind ("raw", "hex", "passphrase")."""
    text = _as_text(data)
    if text is not None:
        return key_from_text(text, source)
    if len(data) != KEY_LENGTH:
        raise SigningKeyError(
            f"{source}: {len(data)} bytes of binary data; a raw signing key is exactly "
            f"{KEY_LENGTH} bytes (or write 64 hex digits, or a passphrase)"
        )
    return _checked(bytes(data), source), "raw"


def _as_text(data: bytes) -> str | None:
    """``data`` as text if it is UTF-8 of printable characters and whitespace only."""
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        return None
    return text if "".join(text.split()).isprintable() else None


def key_from_file(path: str | Path) -> tuple[bytes, str]:
    """The key in a file (see the module's description of the formats)."""
    path = Path(path).expanduser()
    if path.is_dir():
        raise SigningKeyError(f"{path}: is a directory, not a signing key file")
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise SigningKeyError(f"{path}: no such file (the signing key)") from None
    except OSError as error:
        raise SigningKeyError(f"cannot read the signing key {path}: {error.strerror}") from None
    return key_from_bytes(data, str(path))


def _checked(key: bytes, source: str) -> bytes:
    if not any(key):  # SETUP_SIGNING with an all-zero key means "signing off"
        raise SigningKeyError(f"{source}: an all-zero key turns signing off on the autopilot")
    return key


def enable_outgoing(mav: Any, key: bytes) -> None:
    """Make a pymavlink MAVLink object sign every packet it packs, as mavutil's
    ``setup_signing`` does, with mavest's fixed link id and the clock at now."""
    state = mav.signing
    state.secret_key = key
    state.link_id = LINK_ID
    state.sign_outgoing = True
    state.timestamp = signing_timestamp()


def advance_clock(state: Any) -> None:
    """Bring a signing state's timestamp up to now (never back).

    pymavlink only adds one per packet signed: a few thousand ticks per second
    against the clock's 100 000, so a long run would fall minutes behind real
    time, and a receiver that starts listening late rejects a new stream more
    than a minute behind its own clock. Keeping it at now also keeps it
    monotonic across a restart of mavest.
    """
    now = signing_timestamp()
    if now > state.timestamp:
        state.timestamp = now


class _CheckingParser(mavlink2.MAVLink):
    """A robust pymavlink parser that remembers whether the packet it decodes is signed.

    pymavlink asks ``allow_unsigned_callback`` both about an unsigned packet and
    about a signed one whose signature failed, without saying which: the
    callback needs this to accept the first (when allowed) and never the second.

    It also undoes one thing pymavlink does with a refused packet: it records a
    stream's timestamp before it compares the signature, so a forged packet
    naming the vehicle's stream with a far-future timestamp would make every
    genuine packet after it look like a replay (anyone could lock the vehicle out
    without the key). The C library compares the signature first.
    """

    def __init__(self, verifier: Verifier) -> None:
        super().__init__(None)
        self.robust_parsing = True
        self.signing = verifier.state  # shared by every peer's parser
        self.packet_signed = False
        self.packet_source = (0, 0)
        self.refused = False  # set by the verifier's callback

    def decode(self, msgbuf: bytearray) -> Any:
        self.packet_signed = False
        self.refused = False
        if msgbuf[0] == mavlink2.PROTOCOL_MARKER_V2 and len(msgbuf) > 6:
            self.packet_signed = bool(msgbuf[2] & mavlink2.MAVLINK_IFLAG_SIGNED)
            self.packet_source = (msgbuf[5], msgbuf[6])
        elif len(msgbuf) > 4:
            self.packet_source = (msgbuf[3], msgbuf[4])
        if not self.packet_signed or len(msgbuf) < 10 + mavlink2.MAVLINK_SIGNATURE_BLOCK_LEN:
            return super().decode(msgbuf)
        advance_clock(self.signing)  # a new stream's one-minute window counts from now
        stream = (msgbuf[-mavlink2.MAVLINK_SIGNATURE_BLOCK_LEN], *self.packet_source)
        timestamps = self.signing.stream_timestamps
        last = timestamps.get(stream)
        try:
            return super().decode(msgbuf)
        finally:
            if self.refused:
                if last is None:
                    timestamps.pop(stream, None)
                else:
                    timestamps[stream] = last


class Verifier:
    """Checks the signature of everything mavest hears, from every peer, with one key.

    Every peer's parser shares one pymavlink signing state, so the replay check
    (a stream's timestamps must rise) spans peers and links: a packet recorded
    from one address and sent again from another is still a replay.
    Dropped packets come out of the parser as BAD_DATA; :attr:`dropped` counts them.
    """

    def __init__(self, signing: Signing) -> None:
        self.require_signed = signing.require_signed
        state = mavlink2.MAVLinkSigning()
        state.secret_key = signing.key
        state.link_id = LINK_ID
        state.timestamp = signing_timestamp()
        state.allow_unsigned_callback = self._allow
        self.state = state
        self.bad_signatures = 0  # signed, but the signature or its timestamp failed
        self.unsigned_dropped = 0  # unsigned with require_signed

    @property
    def verified(self) -> int:
        """Signed packets whose signature held."""
        return int(self.state.goodsig_count)

    @property
    def dropped(self) -> int:
        return self.bad_signatures + self.unsigned_dropped

    def parser(self) -> Any:
        """A new decoder that checks signatures (the pipeline's one: its replay check
        spans peers and links)."""
        return _CheckingParser(self)

    def _allow(self, parser: _CheckingParser, message_id: int) -> bool:
        system, component = parser.packet_source
        if parser.packet_signed:
            parser.refused = True
            self.bad_signatures += 1
            if self.bad_signatures == 1:
                log.warning(
                    "dropped %s from %d/%d: bad signature (another key?) or an old timestamp "
                    "(a replay, or the sender's signing clock over a minute behind ours); "
                    "further drops are counted in the status and summary",
                    _name(message_id),
                    system,
                    component,
                )
            return False
        if self.require_signed:
            self.unsigned_dropped += 1
            if self.unsigned_dropped == 1:
                log.warning(
                    "dropped unsigned %s from %d/%d (signed input required); further drops "
                    "are counted in the status and summary",
                    _name(message_id),
                    system,
                    component,
                )
            return False
        return True

    def describe(self) -> str:
        return (
            f"{self.verified} signed messages verified, {self.bad_signatures} dropped "
            f"(bad signature or replayed), {self.unsigned_dropped} unsigned dropped"
        )


def _name(message_id: int) -> str:
    message_class: Any = mavlink2.mavlink_map.get(message_id)
    return getattr(message_class, "msgname", f"message {message_id}")
