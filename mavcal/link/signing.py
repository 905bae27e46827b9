"""MAVLink 2 signing on a live link: the key, and telling a signing problem from a lossy link.

The key is derived from a passphrase exactly as MAVProxy's ``signing`` module does
(``MAVProxy/modules/mavproxy_signing.py``, ``passphrase_to_key``: SHA-256 of the ASCII
passphrase, 32 bytes), so one passphrase serves MAVProxy (``signing setup PASSPHRASE``) and
mavcal (``--signing-key PASSPHRASE`` or ``--signing-key-file F`` with the passphrase on its
first line). It is set on the pymavlink connection with ``setup_signing``: every message we
send is signed, and messages from the vehicle are accepted only with a valid signature
(RADIO/RADIO_STATUS excepted, from a telemetry modem, as ArduPilot and MAVProxy do).

Once a key is set up on an ArduPilot vehicle (``SETUP_SIGNING``), it signs what it sends and
drops unsigned messages on every channel except the first (SERIAL0, usually USB;
``GCS_Signing.cpp``, ``accept_unsigned_callback``). Without a key a ground station then hears
the vehicle but gets no answer: to a user that looks like a dead or lossy link.
:func:`signing_problem` and :func:`unsigned_refusal` say what it really is.

The key is never logged, printed or put in a report: :class:`SigningKey` hides it in its
``repr``.
"""
from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

from pymavlink import mavutil

from mavcal.errors import UsageError

__all__ = ["SigningKey", "key_from_passphrase", "key_from_file", "is_signed", "setup_signing",
           "signing_problem", "NEEDS_KEY", "WRONG_KEY", "VEHICLE_UNSIGNED"]

#: incompat_flags bit of a signed MAVLink 2 frame
_IFLAG_SIGNED = 0x01

NEEDS_KEY = ("the vehicle requires MAVLink 2 signing: it signs its messages and ignores our unsigned requests; "
             "give its key with --signing-key PASSPHRASE or --signing-key-file F (nothing was written)")
WRONG_KEY = ("the vehicle's messages are signed with a different key: wrong signing key "
             "(--signing-key / --signing-key-file); nothing was written")
VEHICLE_UNSIGNED = ("a signing key was given but the vehicle's messages are not signed: it does not use "
                    "signing on this link; leave out --signing-key (nothing was written)")


class SigningKey:
    """A 32-byte MAVLink 2 signing key that never shows itself (``repr`` and ``str`` hide it)."""

    __slots__ = ("_key",)

    def __init__(self, key: bytes) -> None:
        if len(key) != 32:
            raise ValueError("a MAVLink 2 signing key has 32 bytes")
        self._key = bytes(key)

    @property
    def secret(self) -> bytes:
        """The key's bytes (for ``setup_signing`` only)."""
        return self._key

    def __repr__(self) -> str:
        return "SigningKey(<hidden>)"

    __str__ = __repr__

    def __eq__(self, other: object) -> bool:
        return isinstance(other, SigningKey) and other._key == self._key

    def __hash__(self) -> int:
        return hash(("SigningKey", self._key))


def key_from_passphrase(passphrase: str) -> SigningKey:
    """MAVProxy's derivation: SHA-256 of the ASCII passphrase (UsageError if empty or not ASCII)."""
    if not passphrase:
        raise UsageError("the signing passphrase is empty")
    try:
        data = passphrase.encode("ascii")
    except UnicodeEncodeError:
        raise UsageError("the signing passphrase must be ASCII (MAVProxy's signing module encodes it so)") from None
    return SigningKey(hashlib.sha256(data).digest())


def key_from_file(path: str | Path) -> SigningKey:
    """The key of the passphrase on the first line of ``path`` (surrounding whitespace removed)."""
    try:
        text = Path(path).read_text(encoding="ascii")
    except UnicodeDecodeError:
        raise UsageError(f"signing key file {path}: the passphrase must be ASCII") from None
    except OSError as exc:
        raise UsageError(f"cannot read the signing key file {path}: {exc.strerror or exc}") from None
    lines = text.splitlines()
    passphrase = lines[0].strip() if lines else ""
    if not passphrase:
        raise UsageError(f"signing key file {path}: no passphrase on its first line")
    return key_from_passphrase(passphrase)


def is_signed(m: Any) -> bool:
    """True if the frame of the received message ``m`` carried a signature (checked or not)."""
    header = getattr(m, "_header", None)
    return bool(header is not None and getattr(header, "incompat_flags", 0) & _IFLAG_SIGNED)


_ALLOWED_UNSIGNED = frozenset(
    getattr(mavutil.mavlink, n) for n in ("MAVLINK_MSG_ID_RADIO", "MAVLINK_MSG_ID_RADIO_STATUS")
    if hasattr(mavutil.mavlink, n))


def _allow_unsigned(_mav: Any, msg_id: int) -> bool:
    return msg_id in _ALLOWED_UNSIGNED


def setup_signing(conn: Any, key: SigningKey) -> None:
    """Sign what ``conn`` sends with ``key`` and accept only validly signed messages."""
    conn.setup_signing(key.secret, sign_outgoing=True, allow_unsigned_callback=_allow_unsigned)


def signing_problem(conn: Any, key: SigningKey | None) -> str | None:
    """Why nothing usable arrived on a link with ``key``, if signing is the reason: frames signed
    with another key, or unsigned frames refused. None when the counters show neither."""
    if key is None:
        return None
    signing = getattr(getattr(conn, "mav", None), "signing", None)
    if signing is None:
        return None
    if getattr(signing, "badsig_count", 0) > 0 and getattr(signing, "goodsig_count", 0) == 0:
        return WRONG_KEY
    if getattr(signing, "reject_count", 0) > 0 and getattr(signing, "sig_count", 0) == 0:
        return VEHICLE_UNSIGNED
    return None
