"""HTTP digest authentication as RWS 1.0 speaks it (RFC 2617: MD5, ``qop=auth``), no I/O.

The RWS client answers the controller's challenge and the controller simulator checks the answer
with the same functions, so the two cannot drift apart (aiohttp has no digest client or server).
"""

from __future__ import annotations

import hashlib
import re

__all__ = ["digest_response", "md5_hex", "parse_auth_params"]

_AUTH_PARAM_RE = re.compile(r'(\w+)\s*=\s*(?:"((?:[^"\\]|\\.)*)"|([^,\s]+))')


def md5_hex(text: str) -> str:
    """The MD5 of ``text`` (UTF-8) as 32 lowercase hex digits (RFC 2617's ``H``)."""
    return hashlib.md5(text.encode()).hexdigest()


def parse_auth_params(header_value: str) -> dict[str, str]:
    """Parse the ``key=value`` / ``key="value"`` pairs of a Digest challenge or response header
    (without its ``Digest`` scheme word); keys lowercased."""
    return {
        m.group(1).lower(): m.group(2) if m.group(2) is not None else m.group(3)
        for m in _AUTH_PARAM_RE.finditer(header_value)
    }


def digest_response(
    *, username: str, realm: str, password: str, method: str, uri: str, nonce: str, nc: str, cnonce: str
) -> str:
    """The ``response`` value of RFC 2617 with ``qop=auth`` and MD5 (``nc``: 8 hex digits)."""
    ha1 = md5_hex(f"{username}:{realm}:{password}")
    ha2 = md5_hex(f"{method}:{uri}")
    return md5_hex(f"{ha1}:{nonce}:{nc}:{cnonce}:auth:{ha2}")
