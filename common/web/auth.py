"""Access tokens for the station's web pages.

Reading pages is open (on 127.0.0.1 by default); every action that writes (scan, verdict,
re-run) needs the station's access token. The token comes from config (``[web] token``) or is
generated at first start and kept in a file only its owner can read. A browser proves it holds
the token once, at the login form, and then carries a signed session cookie (HttpOnly,
SameSite=Strict) plus a per-session CSRF value that the page sends back in a header; a script
sends the token itself in ``Authorization: Bearer <token>``. Every comparison is constant-time.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets
import time
from pathlib import Path

TOKEN_BYTES = 32
MIN_TOKEN_CHARS = 16
FAILED_ATTEMPT_DELAY_S = 0.5   # a wrong token (login form or Bearer header) is answered this late


def generate_token() -> str:
    """A fresh random access token (URL-safe text, 256 bits of entropy)."""
    return secrets.token_urlsafe(TOKEN_BYTES)


def load_or_create_token(path: str | os.PathLike) -> str:
    """The token kept at ``path``; generated and written there (mode 0600) at first start.

    Parameters
    ----------
    path : path
        Token file, e.g. ``<state dir>/web_token``.

    Returns
    -------
    token : str

    Raises
    ------
    ValueError
        If the file exists but holds a token shorter than ``MIN_TOKEN_CHARS`` (a truncated or
        hand-edited file must not silently weaken access control).
    """
    path = Path(path)
    if path.is_file():
        token = path.read_text().strip()
        if len(token) < MIN_TOKEN_CHARS:
            raise ValueError(f"token file {path} holds a token shorter than {MIN_TOKEN_CHARS} characters; "
                             "delete it to generate a new one")
        return token
    token = generate_token()
    if not save_token(path, token):  # another process created it first: keep theirs
        return load_or_create_token(path)
    return token


def save_token(path: str | os.PathLike, token: str) -> bool:
    """Write ``token`` to ``path`` (mode 0600, fsynced) unless the file exists; True if written.

    Parameters
    ----------
    path : path
        Token file; its directory is created (mode 0700) if missing.
    token : str
    """
    path = Path(path)
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(token + "\n")
        fh.flush()
        os.fsync(fh.fileno())
    try:
        os.link(tmp, path)  # fails if another process created it first
    except FileExistsError:
        return False
    finally:
        os.unlink(tmp)
    return True


def token_matches(given: str | bytes | None, expected: str) -> bool:
    """Constant-time check that ``given`` equals ``expected`` (False for None or empty)."""
    if not given or not expected:
        return False
    if isinstance(given, str):
        given = given.encode("utf-8", "surrogatepass")
    return hmac.compare_digest(given, expected.encode("utf-8"))


def check_token_slowly(given: str | bytes | None, expected: str) -> bool:
    """:func:`token_matches`, but a wrong token costs ``FAILED_ATTEMPT_DELAY_S`` (slows guessing;
    the token's 256 bits do the real work). Use it wherever a request presents a token."""
    if token_matches(given, expected):
        return True
    time.sleep(FAILED_ATTEMPT_DELAY_S)
    return False


def bearer_token(authorization: str | None) -> str | None:
    """The token of an ``Authorization: Bearer <token>`` header, or None."""
    if not authorization:
        return None
    scheme, _, value = authorization.strip().partition(" ")
    if scheme.lower() != "bearer" or not value.strip():
        return None
    return value.strip()


def session_secret(token: str) -> bytes:
    """Key that signs session cookies, derived from the access token.

    Changing the token therefore logs every browser out.
    """
    return hashlib.sha256(b"tessera-web-session\0" + token.encode()).digest()


def new_csrf_value() -> str:
    """A per-session anti-CSRF value (the page echoes it in the ``X-CSRF-Token`` header)."""
    return secrets.token_urlsafe(24)
