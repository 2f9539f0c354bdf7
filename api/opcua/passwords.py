"""Password hashes of the OPC UA users: scrypt, stored as ``scrypt$N$r$p$SALT$HASH`` (base64), never in clear.

Standard library only (no asyncua), so ``autotuner password-hash`` and the
config check work without the ``opcua`` extra. A hash costs about 16 MiB and
tens of milliseconds: cheap for one login, expensive for guessing.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import secrets

# scrypt cost: N (CPU/memory), r (block size), p (parallelism); 2**14 · 8 · 128 B = 16 MiB per hash.
SCRYPT_N, SCRYPT_R, SCRYPT_P = 2**14, 8, 1
SALT_BYTES = 16
HASH_BYTES = 32


def _scrypt(password: str, salt: bytes, n: int, r: int, p: int) -> bytes:
    return hashlib.scrypt(password.encode("utf-8"), salt=salt, n=n, r=r, p=p, maxmem=2 * 128 * n * r * p + 2**20,
                          dklen=HASH_BYTES)


def hash_password(password: str) -> str:
    """A new salted scrypt hash of ``password`` in the config's format."""
    salt = secrets.token_bytes(SALT_BYTES)
    digest = _scrypt(password, salt, SCRYPT_N, SCRYPT_R, SCRYPT_P)
    b64 = base64.b64encode
    return f"scrypt${SCRYPT_N}${SCRYPT_R}${SCRYPT_P}${b64(salt).decode()}${b64(digest).decode()}"


def verify_password(password: str, stored: str) -> bool:
    """Whether ``password`` matches the hash ``stored`` (constant-time comparison); False for a malformed hash."""
    try:
        scheme, n, r, p, salt, digest = stored.split("$")
        if scheme != "scrypt":
            return False
        expected = base64.b64decode(digest)
        actual = _scrypt(password, base64.b64decode(salt), int(n), int(r), int(p))
    except (ValueError, TypeError, OverflowError, MemoryError):  # malformed or too costly: no match, no crash
        return False
    return hmac.compare_digest(actual, expected)
