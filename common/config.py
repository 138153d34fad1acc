"""Station configuration: TOML files over built-in defaults.

Every setting has a default (:data:`DEFAULTS`); a TOML file only states what differs. Loading
checks every key and type and fails at start with a :class:`ConfigError` naming the bad key
(``broker.port: expected an integer, got 'abc'``), so a typo never surfaces hours later.

Sections
--------
``[storage]``   artifact store root (local directory or NFS mount) and HDF5 file locking.
``[broker]``    addresses, journal directory (local disk!), heartbeat interval/liveness,
                attempts before a job is parked, feed history kept for catching up.
``[worker]``    reconnect back-off and how long a stopping worker may finish its job.
``[client]``    request timeout and retries of the bus client.
``[routing]``   event type -> list of services that receive it as a job.
``[scanner]``   device (``simulated`` or ``sane``), local spool/outbox directory, capture settings.
``[station]``   which stage workers ``tessera station`` starts.
``[services.<name>]`` free-form settings of one stage, passed to it as ``ctx.config``.

The embedded default is ``configs/station.toml`` (one machine); ``configs/lab.toml`` shows a
broker host, several worker hosts and storage on NFS.
"""

from __future__ import annotations

import copy
import os
import tomllib
from pathlib import Path
from typing import Any, Mapping

from common.messages import EVENT_TYPES


class ConfigError(ValueError):
    """A configuration file or setting is invalid; the message names the key."""


DEFAULTS: dict[str, dict[str, Any]] = {
    "storage": {
        "root": "tessera-data",          # storage root: local dir or an NFS/SMB mount
        "file_locking": False,           # HDF5 file locking (off: NFS often lacks it)
        "create_root": True,             # create the root if missing (False for a mount point)
    },
    "broker": {
        "host": "127.0.0.1",             # where clients and workers connect
        "bind": "127.0.0.1",             # interface the broker binds: loopback (one machine); "*" opens it
                                         # to the network, where CURVE should be on (docs/security.md)
        "port": 5555,                    # ROUTER: workers and clients
        "feed_port": 5556,               # PUB: the event feed
        "journal_dir": "tessera-data/broker",  # LOCAL disk, never NFS
        "heartbeat_interval_s": 1.0,
        "heartbeat_liveness": 3,         # missed heartbeats before a peer is declared dead
        "max_attempts": 3,               # failures before a job is parked
        "feed_history": 100000,          # events kept for subscribers catching up
        "compact_interval_s": 60.0,      # journal compaction period
        "batch_max": 2000,               # messages handled per poll-loop batch (one fsync)
        "refusal_event_interval_s": 60.0,  # refused frames: at most one input.rejected summary per this
        "nice": -10,                     # broker's CPU priority (latency first; below 0 needs root or LimitNICE)
    },
    "worker": {
        "reconnect_min_s": 0.25,
        "reconnect_max_s": 8.0,
        "shutdown_grace_s": 30.0,        # SIGTERM: finish the job within this, else hand it back
        "storage_retry_min_s": 1.0,      # storage full/read-only/away: first wait before retrying the job here
        "storage_retry_max_s": 30.0,     # ... doubling up to this
        "storage_retry_budget_s": 600.0,  # ... for at most this long, then one failed attempt is reported
    },
    "client": {
        "timeout_s": 2.5,
        "retries": 3,
    },
    "routing": {
        "fragment.ready": ["solver"],
        "rgbn.ready": ["features", "renderer"],
        "features.ready": ["matcher"],
        "match.ranked": ["matcher"],
        "match.verified": ["matcher"],
        "match.refitted": ["matcher"],
        "match.reranked": ["matcher"],
    },
    "scanner": {
        "device": "simulated",           # "simulated" or "sane"
        "sane_device": "",               # SANE device name, e.g. "epson2:libusb:001:004"
        "spool_dir": "tessera-data/spool",  # LOCAL disk at the bench: spool + outbox
        "dpi": 300,
        "prescan_dpi": 25,               # 1 mm pixels find a fragment; the simulated bed scans fast
        "depth": 16,
        "colour_only": False,
        "margin_mm": 5.0,
        "seed": 1,                       # synthetic fresco seed (simulated device)
        "fragments": 4,                  # synthetic fragments per run when not given
        "wall_dpi": 300,                 # synthetic fresco resolution (as fine as the scans: the solver registers on texture)
        "drain_interval_s": 2.0,         # how often the outbox retries the broker/storage
    },
    "station": {
        "stages": ["solver", "features", "matcher", "renderer"],
        "demo_timeout_s": 900.0,
    },
    "services": {},
    "security": {                        # ZeroMQ CURVE between hosts (common/bus/security.py, docs/security.md)
        "curve": False,                  # encrypt + authenticate every bus connection
        "broker_secret_key": "",         # broker: its key pair file (broker.key_secret)
        "authorized_keys": "",           # broker: directory of public keys (*.key) allowed to connect
        "broker_public_key": "",         # others: the broker's public key file (broker.key)
        "secret_key": "",                # others: this host's key pair file (<name>.key_secret)
    },
}

# sections whose keys are free-form (checked by shape, not by name)
FREE_FORM_SECTIONS = {"routing", "services"}


def _check_value(key: str, default: Any, value: Any) -> Any:
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true or false, got {value!r}")
        return value
    if isinstance(default, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
        return value
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{key}: expected a number, got {value!r}")
        return float(value)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string, got {value!r}")
        return value
    if isinstance(default, list):
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            raise ConfigError(f"{key}: expected a list of strings, got {value!r}")
        return list(value)
    return value


def _merge(base: dict, over: Mapping, where: str = "") -> None:
    for section, values in over.items():
        name = f"{where}{section}"
        if section not in base:
            raise ConfigError(f"{name}: unknown section (known: {', '.join(sorted(base))})")
        if not isinstance(values, Mapping):
            raise ConfigError(f"{name}: expected a table [{name}], got {values!r}")
        if section in FREE_FORM_SECTIONS:
            for k, v in values.items():
                base[section][k] = copy.deepcopy(dict(v)) if isinstance(v, Mapping) else copy.deepcopy(v)
            continue
        for k, v in values.items():
            if k not in base[section]:
                raise ConfigError(f"{name}.{k}: unknown setting (known: {', '.join(sorted(base[section]))})")
            base[section][k] = _check_value(f"{name}.{k}", DEFAULTS[section][k], v)


def validate_config(cfg: dict) -> dict:
    """Check ranges and cross-field rules of a merged configuration; return it."""
    b = cfg["broker"]
    for key in ("port", "feed_port"):
        if not 1 <= b[key] <= 65535:
            raise ConfigError(f"broker.{key}: expected a TCP port 1-65535, got {b[key]}")
    if b["port"] == b["feed_port"]:
        raise ConfigError("broker.feed_port: must differ from broker.port")
    for key in ("heartbeat_interval_s", "compact_interval_s"):
        if b[key] <= 0:
            raise ConfigError(f"broker.{key}: must be positive, got {b[key]}")
    for key in ("heartbeat_liveness", "max_attempts", "feed_history", "batch_max"):
        if b[key] < 1:
            raise ConfigError(f"broker.{key}: must be at least 1, got {b[key]}")
    if not -20 <= b["nice"] <= 19:
        raise ConfigError(f"broker.nice: expected a nice value -20..19, got {b['nice']}")
    w = cfg["worker"]
    if not 0 < w["reconnect_min_s"] <= w["reconnect_max_s"]:
        raise ConfigError("worker.reconnect_min_s: must be positive and not above worker.reconnect_max_s")
    if cfg["client"]["timeout_s"] <= 0 or cfg["client"]["retries"] < 1:
        raise ConfigError("client.timeout_s / client.retries: must be positive")
    for event_type, services in cfg["routing"].items():
        if event_type not in EVENT_TYPES:
            raise ConfigError(f"routing.{event_type}: unknown event type (known: {', '.join(sorted(EVENT_TYPES))})")
        if not isinstance(services, list) or not all(isinstance(s, str) and s for s in services):
            raise ConfigError(f"routing.{event_type}: expected a list of service names, got {services!r}")
    for name, section in cfg["services"].items():
        if not isinstance(section, Mapping):
            raise ConfigError(f"services.{name}: expected a table [services.{name}], got {section!r}")
    s = cfg["scanner"]
    if s["device"] not in ("simulated", "sane"):
        raise ConfigError(f"scanner.device: expected 'simulated' or 'sane', got {s['device']!r}")
    if s["depth"] not in (8, 16):
        raise ConfigError(f"scanner.depth: expected 8 or 16, got {s['depth']}")
    for key in ("dpi", "prescan_dpi", "wall_dpi"):
        if s[key] <= 0:
            raise ConfigError(f"scanner.{key}: must be positive, got {s[key]}")
    return cfg


def _set_dotted(cfg: dict, key: str, value: Any) -> None:
    parts = key.split(".")
    if parts[0] in FREE_FORM_SECTIONS:
        node = cfg
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = value
        return
    if len(parts) != 2 or parts[0] not in cfg or parts[1] not in cfg[parts[0]]:
        raise ConfigError(f"{key}: unknown setting")
    cfg[parts[0]][parts[1]] = _check_value(key, DEFAULTS[parts[0]][parts[1]], value)


def default_config_path() -> Path:
    """``configs/station.toml`` of the checkout: the embedded one-machine default."""
    return Path(__file__).resolve().parents[1] / "configs" / "station.toml"


def load_config(path: str | os.PathLike | None = None, overrides: Mapping[str, Any] | None = None) -> dict:
    """Load a station configuration.

    Parameters
    ----------
    path : path, optional
        TOML file. Without it, ``$TESSERA_CONFIG`` if set, else the built-in defaults (which are
        what ``configs/station.toml`` states).
    overrides : mapping, optional
        Dotted keys applied last, e.g. ``{"broker.port": 6000, "services.noop.sleep_s": 0.5}``.

    Returns
    -------
    dict
        Every section with every setting filled in.

    Raises
    ------
    ConfigError
        Unreadable file, TOML syntax error, unknown key or section, wrong type or range; the
        message names the file and the key.
    """
    cfg = copy.deepcopy(DEFAULTS)
    if path is None and os.environ.get("TESSERA_CONFIG"):
        path = os.environ["TESSERA_CONFIG"]
    if path is not None:
        p = Path(path)
        try:
            text = p.read_text()
        except OSError as exc:
            raise ConfigError(f"config file {p}: cannot read ({exc.strerror or exc})") from exc
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"config file {p}: TOML syntax error: {exc}") from exc
        try:
            # a file replaces the routing table as a whole: it is one decision, not per-key tweaks
            if "routing" in data:
                cfg["routing"] = {}
            _merge(cfg, data)
        except ConfigError as exc:
            raise ConfigError(f"config file {p}: {exc}") from exc
    for key, value in (overrides or {}).items():
        _set_dotted(cfg, key, value)
    return validate_config(cfg)


def broker_endpoint(cfg: Mapping) -> str:
    """tcp endpoint where workers and clients reach the broker."""
    return f"tcp://{cfg['broker']['host']}:{cfg['broker']['port']}"


def feed_endpoint(cfg: Mapping) -> str:
    """tcp endpoint of the broker's event feed (PUB)."""
    return f"tcp://{cfg['broker']['host']}:{cfg['broker']['feed_port']}"


def service_config(cfg: Mapping, service: str) -> dict:
    """The free-form ``[services.<service>]`` section (empty if absent)."""
    return dict(cfg.get("services", {}).get(service, {}))


def add_config_arguments(parser) -> None:
    """Add ``--config PATH`` and repeatable ``--set KEY=VALUE`` to an argparse parser."""
    parser.add_argument("--config", metavar="PATH", help="station TOML (default: $TESSERA_CONFIG or the built-in one-machine station)")
    parser.add_argument("--set", metavar="KEY=VALUE", action="append", default=[],
                        help="override one setting, TOML value syntax, e.g. --set broker.port=6000")


def config_from_arguments(args) -> dict:
    """Load the configuration named by :func:`add_config_arguments`'s options."""
    overrides = {}
    for item in getattr(args, "set", []) or []:
        key, sep, raw = item.partition("=")
        if not sep:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE")
        try:
            value = tomllib.loads(f"v = {raw}")["v"]
        except tomllib.TOMLDecodeError:
            value = raw  # a bare word is a string
        overrides[key.strip()] = value
    return load_config(getattr(args, "config", None), overrides)
