"""docs/security.md's role table and docs/messages.md's refusal kinds against the broker's tables
(no processes: the CURVE end-to-end checks are in test_security.py)."""

from __future__ import annotations

import logging
import re
from pathlib import Path

from common.bus import broker
from common.bus.security import ROLES, AuthorizedKeys, generate_keypair
from common.messages import EVENT_TYPES

DOCS = Path(__file__).resolve().parents[2] / "docs"


def _role_rows() -> list[tuple[list[str], str, str, str]]:
    text = (DOCS / "security.md").read_text()
    table = re.search(r"^\| role \| may register as a worker of \| may submit \| may `RERUN` \|\n\|[-| ]+\|\n((?:\|.*\n)+)",
                      text, re.M)
    assert table, "docs/security.md has no role table"
    rows = []
    for line in table.group(1).splitlines():
        role, serves, submits, rerun = [c.strip() for c in line.strip("|").split("|")]
        rows.append((re.findall(r"`([a-z]+)`", re.sub(r"\(.*?\)", "", role)), serves, submits, rerun))
    return rows


def test_the_role_table_is_what_the_broker_enforces():
    documented = set()
    for roles, serves, submits, rerun in _role_rows():
        for r in roles:
            documented.add(r)
            may_serve = broker.ROLE_SERVES.get(r, frozenset())
            if serves == "that stage only":
                assert may_serve == {r}, r
            elif serves == "any stage":
                assert may_serve == {"*"}, r
            else:
                assert serves == "—" and not may_serve, (r, serves, may_serve)
            may_submit = broker.ROLE_SUBMITS.get(r, frozenset())
            if submits == "nothing":
                assert not may_submit, (r, may_submit)
            elif submits == "any type":
                assert may_submit == set(EVENT_TYPES), r
            else:
                assert may_submit == set(re.findall(r"`([a-z.]+)`", submits)), (r, submits, may_submit)
            assert (rerun == "yes") == (r in broker.ROLE_RERUNS), (r, rerun)
    assert documented == set(ROLES), "every role `tessera keys add --role` accepts is in the table, and only those"


def test_a_key_without_a_role_may_only_read_and_is_named_in_a_warning(tmp_path, caplog):
    """docs/security.md: a key without a role line may only read, and the broker logs a warning naming it."""
    d = tmp_path / "authorized"
    d.mkdir()
    generate_keypair(tmp_path / "hosts", "old-desk", authorize_in=d)   # no role: made before roles existed
    generate_keypair(tmp_path / "hosts", "bench", authorize_in=d, role="scanner")
    import zmq.auth
    old, _ = zmq.auth.load_certificate(str(tmp_path / "hosts" / "old-desk.key"))
    with caplog.at_level(logging.WARNING, logger="tessera"):
        provider = AuthorizedKeys(d)
    assert provider.callback("*", old), "it is admitted (it may connect and read)"
    role = provider.role_of(old)
    assert role == ""
    assert not broker.ROLE_SUBMITS.get(role) and not broker.ROLE_SERVES.get(role) and role not in broker.ROLE_RERUNS
    assert any("old-desk.key has no role" in r.getMessage() and "tessera keys role old-desk" in r.getMessage()
               for r in caplog.records), [r.getMessage() for r in caplog.records]


def test_the_refusal_kinds_in_status_are_the_documented_ones():
    doc = (DOCS / "messages.md").read_text()
    m = re.search(r"count per reason kind — (.*?)[;)]", doc)
    assert m, "docs/messages.md does not list STATUS refused kinds"
    documented = set(re.findall(r"`([a-z-]+)`", m.group(1)))
    code = set(re.findall(r'_refuse\([^,]+, "([a-z-]+)"', Path(broker.__file__).read_text()))
    assert code == documented


def _bad_key_settings(tmp_path, keys):
    return ["--set", "security.curve=true",
            "--set", f'security.broker_public_key="{keys / "broker.key"}"',
            "--set", f'security.secret_key="{keys / "hosts" / "nobody.key_secret"}"',
            "--set", f'security.broker_secret_key="{keys / "missing.key_secret"}"',
            "--set", f'security.authorized_keys="{keys / "authorized"}"',
            "--set", f'storage.root="{tmp_path / "storage"}"', "--set", f'broker.journal_dir="{tmp_path / "journal"}"',
            "--set", "client.timeout_s=0.3", "--set", "client.retries=1"]


def test_a_missing_key_file_stops_a_client_at_start_naming_the_setting_and_the_file(tmp_path, capsys):
    """docs/security.md: "A missing or wrong key file stops the process at start with a SecurityError
    naming the setting and the file" — it did, as a Python traceback (exit 1); now one line, exit 2."""
    from services.cli import main as tessera
    keys = tmp_path / "keys"
    assert tessera(["keys", "init", str(keys)]) == 0
    capsys.readouterr()
    assert tessera(["status", *_bad_key_settings(tmp_path, keys)]) == 2
    err = capsys.readouterr().err
    assert "security.secret_key" in err and "nobody.key_secret" in err and "Traceback" not in err, err


def test_a_missing_broker_key_stops_the_broker_at_start_naming_it(tmp_path):
    import subprocess
    import sys
    from services.cli import main as tessera
    from tests.conftest import free_port
    keys = tmp_path / "keys"
    assert tessera(["keys", "init", str(keys)]) == 0
    r = subprocess.run([sys.executable, "-c", "import sys; from services.cli import main; sys.exit(main())", "broker", *_bad_key_settings(tmp_path, keys),
                        "--set", f"broker.port={free_port()}", "--set", f"broker.feed_port={free_port()}"],
                       capture_output=True, text=True, timeout=60, cwd=Path(__file__).resolve().parents[2])
    assert r.returncode == 2, r.stderr
    assert "security.broker_secret_key" in r.stderr and "missing.key_secret" in r.stderr
    assert "Traceback" not in r.stderr, r.stderr


def test_a_bad_setting_is_one_line_not_a_traceback(capsys):
    from services.cli import main as tessera
    assert tessera(["status", "--set", "broker.port=abc"]) == 2
    err = capsys.readouterr().err
    assert "broker.port" in err and "Traceback" not in err


def test_a_one_machine_station_listens_on_loopback_only(tmp_path):
    """docs/security.md: "On one machine the bus listens on loopback and nothing else can reach it".
    The embedded default bound every interface (`bind = "*"`), with CURVE off: anyone on the
    network could submit jobs and verdicts or read the feed."""
    import zmq

    from common.bus.broker import Broker
    from common.config import load_config
    from tests.conftest import free_port
    cfg = load_config(None, {"broker.port": free_port(), "broker.feed_port": free_port(),
                             "broker.journal_dir": str(tmp_path / "journal"), "storage.root": str(tmp_path / "s")})
    assert cfg["broker"]["bind"] == "127.0.0.1" and not cfg["security"]["curve"]
    b = Broker(cfg)
    b.bind()
    try:
        for sock in (b.router, b.feed):
            assert sock.getsockopt(zmq.LAST_ENDPOINT).decode().startswith("tcp://127.0.0.1:")
    finally:
        b.close()
    lab = load_config(Path(__file__).resolve().parents[2] / "configs" / "lab.toml")
    assert lab["broker"]["bind"] == "*", "the lab layout listens on the network (and says to turn CURVE on)"
