"""Who sent a worker's message: an HMAC under the key of the offer it answers.

The Zenoh binding does not tell a subscriber who published a sample (``Sample.source_info`` is
empty unless the publisher sets it, and then it says whatever the publisher chose), so a report,
an event or a result chunk cannot be checked by its sender's Zenoh identity. Instead the
dispatcher draws a secret ``offer_key`` for every offer and sends it only to the assigned worker,
in the JobSpec on ``Keys.worker_job(worker, job)``; the worker signs every JobEvent and the
ReportEnvelope it publishes (the HMAC-SHA256 of the payload, hex, as the sample's attachment) and
every ResultChunk (``ResultChunk.mac``, over the chunk's key fields and SHA-256). The dispatcher
takes a message only when its MAC verifies under the current offer's key.

With access control on, the worker role is bound to its identity (``access_control_dict``: the
identity ``w1`` may receive only ``workers/w1/**`` and declare only ``alive/workers/w1``), so only
the identity the worker announced with ever holds the key. With access control off, any peer can
subscribe to ``workers/*/jobs/*`` and read the key (docs/safety.md, the threat table).
"""

from __future__ import annotations

import hashlib
import hmac
import secrets

__all__ = ["chunk_mac", "new_offer_key", "sign", "verify"]

#: bytes of an offer key (hex doubles it)
KEY_BYTES = 32


def new_offer_key() -> str:
    """A fresh secret for one offer (hex)."""
    return secrets.token_hex(KEY_BYTES)


def sign(key_hex: str, payload: bytes | bytearray) -> str:
    """The HMAC-SHA256 (hex) of ``payload`` under the offer key."""
    return hmac.new(bytes.fromhex(key_hex), bytes(payload), hashlib.sha256).hexdigest()


def verify(key_hex: str, payload: bytes | bytearray, mac: bytes | bytearray | str | None) -> bool:
    """Whether ``mac`` (hex, str or bytes) is the payload's HMAC under the offer key."""
    if not key_hex or mac is None:
        return False
    if isinstance(mac, bytes | bytearray):
        try:
            mac = bytes(mac).decode("ascii")
        except UnicodeDecodeError:
            return False
    return hmac.compare_digest(sign(key_hex, payload), mac.strip())


def chunk_mac(key_hex: str, job_id: str, attempt: int, index: int, chunks: int, sha256: str) -> str:
    """A result chunk's MAC: over what names the chunk and the SHA-256 of its bytes."""
    return sign(key_hex, f"{job_id}\n{attempt}\n{index}\n{chunks}\n{sha256}".encode())
