"""ZeroMQ CURVE authentication and encryption between the station's hosts (RFC 26 CurveZMQ, ZAP RFC 27).

Off by default (one machine, loopback). With ``[security] curve = true`` every bus socket is
encrypted and the broker admits only peers whose public key is in its authorised-keys directory:

* the broker's ROUTER and PUB sockets are CURVE servers with the broker's key pair, and a ZAP
  handler (:class:`zmq.auth.thread.ThreadAuthenticator`) checks each connecting peer's public key
  against ``authorized_keys``; an unknown key never completes the handshake, so its frames (job
  submissions, verdicts, worker results, feed subscriptions) never reach the broker; the
  directory is re-read whenever it changes (:class:`AuthorizedKeys`), so a revoked key is
  refused from its next connection on, without a broker restart;
* workers, clients, the scanner and feed subscribers are CURVE clients: they know the broker's
  public key (``broker_public_key``) and present their own key pair (``secret_key``).

Key files are ZeroMQ's certificate format (``<name>.key`` public, ``<name>.key_secret`` both
halves; :func:`zmq.auth.create_certificates`), written by ``tessera keys`` (``docs/security.md``).

Every admitted key has a **role** (:data:`ROLES`), a ``role = "<role>"`` line in the metadata
section of its public key file: the broker lets a key register only as its role's service and
submit only its role's event types (:data:`common.bus.broker.ROLE_SUBMITS`). A key without a
role may connect and read (STATUS, SINCE, the feed) and nothing else.
"""

from __future__ import annotations

import logging
import os
import re
import shutil
import threading
from pathlib import Path
from typing import Mapping

import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

log = logging.getLogger("tessera.security")

DEFAULTS = {
    "curve": False,            # encrypt and authenticate every bus connection
    "broker_secret_key": "",   # broker: its key pair file (<name>.key_secret)
    "authorized_keys": "",     # broker: directory of the public keys (*.key) allowed to connect
    "broker_public_key": "",   # everyone else: the broker's public key file (broker.key)
    "secret_key": "",          # everyone else: this host's key pair file (<name>.key_secret)
}


#: roles a key can have: a stage's workers, the scanner, the web pages, a bench PC running both (one host,
#: one key: its captures and its verdicts), a read-only subscriber, and the lab's own tools (reconcile, imports,
#: re-runs)
ROLES = ("solver", "features", "matcher", "renderer", "scanner", "web", "bench", "subscriber", "admin")
_ROLE_LINE = re.compile(r'^\s*role\s*=\s*"([a-z]+)"\s*$', re.M)


def read_role(path: str | os.PathLike) -> str:
    """The role written in a public key file ("" if it has none)."""
    m = _ROLE_LINE.search(Path(path).read_text(errors="replace"))
    return m.group(1) if m else ""


def set_role(path: str | os.PathLike, role: str) -> None:
    """Write ``role`` into the metadata section of a public key file (replacing any earlier role)."""
    if role not in ROLES:
        raise ValueError(f"role: {role!r} is not one of {', '.join(ROLES)}")
    path = Path(path)
    lines = [ln for ln in path.read_text().splitlines() if not _ROLE_LINE.match(ln)]
    if "metadata" in lines:
        lines.insert(lines.index("metadata") + 1, f'    role = "{role}"')
    else:
        lines += ["metadata", f'    role = "{role}"']
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text("\n".join(lines) + "\n")
    os.replace(tmp, path)


class SecurityError(ValueError):
    """Security is enabled but a key file is missing, unreadable or of the wrong kind."""


def enabled(config: Mapping) -> bool:
    """True when ``[security] curve`` is on."""
    return bool(config.get("security", {}).get("curve", False))


def _setting(config: Mapping, key: str) -> str:
    value = str(config.get("security", {}).get(key, "") or "")
    if not value:
        raise SecurityError(f"security.{key}: required when security.curve is true")
    return value


def _read_pair(path: str, key: str) -> tuple[bytes, bytes]:
    if not os.path.isfile(path):
        raise SecurityError(f"security.{key}: key file {path} does not exist (make one with `tessera keys`)")
    try:
        public, secret = zmq.auth.load_certificate(path)
    except (ValueError, OSError) as exc:
        raise SecurityError(f"security.{key}: {path} is not a ZeroMQ key file ({exc})") from exc
    if secret is None:
        raise SecurityError(f"security.{key}: {path} holds only a public key; give the .key_secret file")
    return public, secret


def _read_public(path: str, key: str) -> bytes:
    if not os.path.isfile(path):
        raise SecurityError(f"security.{key}: key file {path} does not exist (copy it from the broker host)")
    try:
        public, _ = zmq.auth.load_certificate(path)
    except (ValueError, OSError) as exc:
        raise SecurityError(f"security.{key}: {path} is not a ZeroMQ key file ({exc})") from exc
    return public


def check(config: Mapping, role: str) -> None:
    """Validate the key settings for ``role`` (``"broker"`` or ``"client"``) before anything starts."""
    if not enabled(config):
        return
    if role == "broker":
        _read_pair(_setting(config, "broker_secret_key"), "broker_secret_key")
        keys = _setting(config, "authorized_keys")
        if not os.path.isdir(keys):
            raise SecurityError(f"security.authorized_keys: {keys} is not a directory")
    else:
        _read_public(_setting(config, "broker_public_key"), "broker_public_key")
        _read_pair(_setting(config, "secret_key"), "secret_key")


def secure_client_socket(sock: zmq.Socket, config: Mapping) -> zmq.Socket:
    """Make ``sock`` a CURVE client of the broker (before ``connect``); no-op when security is off."""
    if enabled(config):
        public, secret = _read_pair(_setting(config, "secret_key"), "secret_key")
        sock.curve_secretkey = secret
        sock.curve_publickey = public
        sock.curve_serverkey = _read_public(_setting(config, "broker_public_key"), "broker_public_key")
    return sock


def secure_server_socket(sock: zmq.Socket, config: Mapping) -> zmq.Socket:
    """Make ``sock`` a CURVE server with the broker's key pair (before ``bind``); no-op when off."""
    if enabled(config):
        public, secret = _read_pair(_setting(config, "broker_secret_key"), "broker_secret_key")
        sock.curve_secretkey = secret
        sock.curve_publickey = public
        sock.curve_server = True
    return sock


class AuthorizedKeys:
    """The broker's authorised-keys directory as the ZAP handler sees it, re-read whenever it changes.

    A ZAP credentials provider (:meth:`zmq.auth.Authenticator.configure_curve_callback`): on every
    CURVE handshake :meth:`callback` compares the directory listing (name, inode, size, mtime of
    each ``*.key``) with the one it last loaded and re-reads the keys if anything differs, so a
    key copied in (``tessera keys add``) or removed (``tessera keys revoke``) decides the very next
    connection without a broker restart. A connection already established keeps its session
    (CURVE authenticates the handshake only) until it reconnects.

    Fails closed: an unreadable or missing directory admits nobody; a malformed key file is
    skipped (logged) and the others stay valid.
    """

    def __init__(self, directory: str | os.PathLike):
        self.directory = Path(directory)
        self._lock = threading.Lock()
        self._listing: tuple | None = None
        self._keys: dict[bytes, str] = {}   # z85 public key -> file name
        self._roles: dict[bytes, str] = {}  # z85 public key -> role ("" when the file names none)
        self.refresh()

    def _list(self) -> tuple | None:
        try:  # os.scandir, not Path.glob: glob hides an unreadable directory as an empty one
            with os.scandir(self.directory) as it:
                names = sorted(e.name for e in it if e.name.endswith(".key"))
        except OSError as exc:
            log.error("authorised-keys directory %s unreadable (%s): refusing every CURVE client", self.directory, exc)
            return None
        entries = []
        for name in names:
            try:
                st = os.stat(self.directory / name)
                entries.append((name, st.st_ino, st.st_size, st.st_mtime_ns))
            except OSError:  # a dangling symlink, or deleted since the listing: only this entry fails (on loading)
                entries.append((name, 0, 0, 0))
        return tuple(entries)

    def refresh(self) -> bool:
        """Re-read the keys if the directory changed; True if it did."""
        with self._lock:
            listing = self._list()
            if listing == self._listing and listing is not None:
                return False
            keys: dict[bytes, str] = {}
            roles: dict[bytes, str] = {}
            for name, *_ in listing or ():
                try:
                    public, _ = zmq.auth.load_certificate(str(self.directory / name))
                    role = read_role(self.directory / name)
                except Exception as exc:  # any defect of one file (zmq raises IndexError too) skips only it
                    log.warning("authorised key %s skipped: %s: %s", self.directory / name, type(exc).__name__, exc)
                    continue
                if public:
                    keys[public] = name
                    roles[public] = role if role in ROLES else ""
                    if not roles[public]:
                        log.warning("authorised key %s has no role: it may only read (tessera keys role %s ROLE)",
                                    name, name[:-4])
            added = sorted(set(keys.values()) - set(self._keys.values()))
            removed = sorted(set(self._keys.values()) - set(keys.values()))
            if self._listing is not None and (added or removed):
                log.warning("authorised keys changed: %d now (added %s, removed %s)", len(keys),
                            ", ".join(added) or "none", ", ".join(removed) or "none")
            self._listing, self._keys, self._roles = listing, keys, roles
            return True

    def role_of(self, z85_key: bytes) -> str:
        """Role of an admitted key ("" if unknown or without a role)."""
        return self._roles.get(z85_key, "")

    def __contains__(self, z85_key: bytes) -> bool:
        return z85_key in self._keys

    def __len__(self) -> int:
        return len(self._keys)

    def callback(self, domain: str, z85_key: bytes) -> bool:
        """ZAP decision for one handshake: is the client's public key authorised right now?"""
        try:
            self.refresh()
        except Exception:  # refuse this handshake: an exception here would end the ZAP thread, locking out everyone
            log.exception("CURVE client refused: the authorised keys could not be read")
            return False
        if z85_key in self._keys:
            return True
        log.info("CURVE client refused: key %s is not authorised", z85_key[:8].decode(errors="replace") + "…")
        return False


def start_authenticator(context: zmq.Context, config: Mapping) -> ThreadAuthenticator | None:
    """Start the ZAP handler admitting the public keys in ``authorized_keys`` (None when off).

    The directory is watched (:class:`AuthorizedKeys`): adding or removing a key file takes
    effect for the next connection, without restarting the broker.
    """
    if not enabled(config):
        return None
    keys = _setting(config, "authorized_keys")
    if not os.path.isdir(keys):
        raise SecurityError(f"security.authorized_keys: {keys} is not a directory")
    auth = ThreadAuthenticator(context, log=logging.getLogger("tessera.zap"))
    auth.start()
    provider = AuthorizedKeys(keys)
    auth.configure_curve_callback(domain="*", credentials_provider=provider)
    log.info("CURVE on: %d authorised key(s) in %s (re-read when it changes)", len(provider), keys)
    return auth


def reload_keys(auth: ThreadAuthenticator | None, config: Mapping) -> None:
    """Re-read the authorised-keys directory now (it is also re-read on every handshake if changed)."""
    if auth is not None:
        provider = auth.credentials_providers.get("*")
        if isinstance(provider, AuthorizedKeys):
            provider.refresh()
        else:
            auth.configure_curve(domain="*", location=_setting(config, "authorized_keys"))


def check_key_name(name: str) -> None:
    """Raise ValueError unless ``name`` is a key name ``tessera keys`` makes (it names files: no paths)."""
    if not name or not all(c.isalnum() or c in "-_." for c in name) or name.startswith("."):
        raise ValueError(f"name: {name!r} must be letters, digits, '-', '_' or '.' (it names files)")


def generate_keypair(directory: str | os.PathLike, name: str, *, authorize_in: str | os.PathLike | None = None,
                     role: str | None = None) -> tuple[Path, Path]:
    """Write a new CURVE key pair ``<directory>/<name>.key`` and ``<name>.key_secret`` (mode 0600).

    Parameters
    ----------
    directory : path
        Where to write; created if missing.
    name : str
        Key name: letters, digits, ``-``, ``_``, ``.`` (a host or role, e.g. ``lab-gpu1``).
    authorize_in : path, optional
        Also copy the public key into this authorised-keys directory (the broker's).
    role : str, optional
        One of :data:`ROLES`, written into the public key file: what the key may do at the broker.

    Returns
    -------
    (public_path, secret_path)

    Raises
    ------
    ValueError
        If ``name`` is unsafe or the key pair exists already (keys are never overwritten).
    """
    check_key_name(name)
    if role is not None and role not in ROLES:
        raise ValueError(f"role: {role!r} is not one of {', '.join(ROLES)}")
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    public, secret = directory / f"{name}.key", directory / f"{name}.key_secret"
    if public.exists() or secret.exists():
        raise ValueError(f"name: key pair {public} exists already; remove it first to replace it")
    old = os.umask(0o077)
    try:
        pub, sec = zmq.auth.create_certificates(str(directory), name)
    finally:
        os.umask(old)
    os.chmod(sec, 0o600)
    if role is not None:
        set_role(pub, role)
    if authorize_in is not None:
        authorize(public, authorize_in)
    return Path(pub), Path(sec)


def authorize(public_key: str | os.PathLike, directory: str | os.PathLike) -> Path:
    """Copy a public key file into the broker's authorised-keys directory; returns the copy's path."""
    public_key = Path(public_key)
    if "secret-key" in public_key.read_text(errors="replace"):  # never spread a secret
        raise ValueError(f"public_key: {public_key} contains a secret key; give the .key file")
    pub, _ = zmq.auth.load_certificate(str(public_key))  # refuses what is not a key file
    if not pub:
        raise ValueError(f"public_key: {public_key} holds no public key")
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    target = directory / public_key.name
    shutil.copyfile(public_key, target)
    return target
