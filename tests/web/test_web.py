"""Tests of services/web/ through Flask's test client: access control, bench, review, status."""

from __future__ import annotations

import os
import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from common.config import load_config
from common.messages import unpack
from common.rgbn.image import RGBNImage, save_rgbn
from common.store import Store
from common.web.bench import BenchSession
from services import web

from .conftest import TOKEN, wait_for

BEARER = {"Authorization": f"Bearer {TOKEN}"}


class CountingCapture:
    """Capture/prescan callables that only count calls: to prove refused requests change nothing."""

    def __init__(self):
        self.calls = 0

    def capture(self, fid, operator):
        self.calls += 1
        return {}

    def prescan(self, fid):
        self.calls += 1
        return {"png": b"", "message": ""}


@pytest.fixture
def counting_app(tmp_path):
    counter = CountingCapture()
    bench = BenchSession(capture=counter.capture, deliver=lambda fid, r: {"sent": True}, prescan=counter.prescan)
    app = web.create_app(token=TOKEN, store_root=tmp_path, bench=bench)
    return app, counter


def _write_rules(app):
    return sorted({r.rule for r in app.url_map.iter_rules() if "POST" in r.methods and r.rule.startswith("/api/")})


def _fill(rule):
    return rule.replace("<int:pid>", "1").replace("<fid>", "F1").replace("<view>", "pair-colour")


def test_every_write_endpoint_refuses_requests_without_the_token(counting_app):
    app, counter = counting_app
    rules = _write_rules(app)
    # the pages write through exactly these endpoints; a new one must be added here consciously
    assert rules == ["/api/bench/cancel", "/api/bench/empty-glass", "/api/bench/prescan", "/api/bench/proceed", "/api/bench/scan",
                     "/api/catalogue/<fid>/metadata", "/api/review/verdict", "/api/status/rerun"]
    c = app.test_client()
    body = {"fragment": "F1", "step": 1, "proposal": 1, "verdict": "confirmed", "job": "all"}
    for rule in rules:
        url = _fill(rule)
        assert c.post(url, json=body).status_code == 401, url
        assert c.post(url, json=body, headers={"Authorization": "Bearer wrong-token-0123456789"}).status_code == 401
        assert c.post(url, json=body, headers={"Authorization": f"Bearer {TOKEN[:-1]}"}).status_code == 401
        assert c.post(url, json=body, headers={"X-CSRF-Token": "anything"}).status_code == 401
    assert counter.calls == 0


def test_a_logged_in_browser_needs_the_csrf_header_and_the_same_origin(counting_app):
    app, counter = counting_app
    c = app.test_client()
    r = c.post("/login", data={"token": TOKEN, "next": "/bench"})
    assert r.status_code == 302 and r.headers["Location"].endswith("/bench")
    cookie = r.headers["Set-Cookie"]
    assert "HttpOnly" in cookie and "SameSite=Strict" in cookie
    page = c.get("/bench").get_data(as_text=True)
    csrf = re.search(r'name="csrf-token" content="([^"]+)"', page).group(1)
    # the session cookie alone (what a cross-site form would carry) is not enough
    assert c.post("/api/bench/prescan", json={"fragment": "F1"}).status_code == 401
    assert c.post("/api/bench/prescan", json={"fragment": "F1"}, headers={"X-CSRF-Token": csrf + "x"}).status_code == 401
    assert c.post("/api/bench/prescan", json={"fragment": "F1"},
                  headers={"X-CSRF-Token": csrf, "Origin": "http://evil.example"}).status_code == 403
    assert c.post("/api/bench/prescan", data="fragment=F1", content_type="application/x-www-form-urlencoded",
                  headers={"X-CSRF-Token": csrf}).status_code == 415
    assert counter.calls == 0
    r = c.post("/api/bench/prescan", json={"fragment": "F1"}, headers={"X-CSRF-Token": csrf, "Origin": "http://localhost"})
    assert r.status_code == 200 and counter.calls == 1
    c.post("/logout", headers={"Origin": "http://localhost"})
    assert c.post("/api/bench/prescan", json={"fragment": "F1"}, headers={"X-CSRF-Token": csrf}).status_code == 401



def test_a_step_confirmation_that_names_no_step_is_a_bad_request(counting_app):
    """POST /api/bench/proceed takes {"step": <index>}; null, a list or Infinity raised in int() and answered
    a bare 500."""
    app, counter = counting_app
    c = app.test_client()
    for body in ('{"step": null}', '{"step": [1]}', '{"step": Infinity}', '{"step": "x"}'):
        r = c.post("/api/bench/proceed", data=body, content_type="application/json", headers=BEARER)
        assert r.status_code == 400 and "step must be" in r.json["error"], body
    assert c.post("/api/bench/proceed", json={"step": 1}, headers=BEARER).status_code == 200
    assert counter.calls == 0


def test_behind_a_tls_proxy_the_published_origin_may_write_and_no_other(tmp_path):
    """docs/web.md advises a TLS reverse proxy; it speaks plain HTTP to the pages, so the browser's https origin
    is not the server's own address and every write (login included) was refused as cross-site. The address
    the pages are published under, ``[services.web] public_origin``, is accepted; others still are not."""
    counter = CountingCapture()
    bench = BenchSession(capture=counter.capture, deliver=lambda fid, r: {"sent": True}, prescan=counter.prescan)
    app = web.create_app(token=TOKEN, store_root=tmp_path, bench=bench,
                         settings=web.web_settings({"services": {"web": {"public_origin": "https://tessera.lab.example"}}}))
    c = app.test_client()
    public = {"Origin": "https://tessera.lab.example"}
    assert c.post("/login", data={"token": TOKEN}, headers=public).status_code == 302
    csrf = re.search(r'name="csrf-token" content="([^"]+)"', c.get("/bench").get_data(as_text=True)).group(1)
    for origin, status in (("https://tessera.lab.example", 200), ("https://evil.example", 403),
                           ("http://tessera.lab.example", 403)):
        r = c.post("/api/bench/prescan", json={"fragment": "F1"}, headers={"X-CSRF-Token": csrf, "Origin": origin})
        assert r.status_code == status, origin
    assert counter.calls == 1
    for bad in ("tessera.lab.example", "https://tessera.lab.example/review", "ftp://x"):
        with pytest.raises(web.WebConfigError, match="public_origin"):
            web.web_settings({"services": {"web": {"public_origin": bad}}})


def test_a_wrong_token_at_login_is_refused_and_redirects_stay_local(counting_app):
    app, _ = counting_app
    c = app.test_client()
    r = c.post("/login", data={"token": "not-the-token-at-all"})
    assert r.status_code == 401 and "not this station" in r.get_data(as_text=True)
    for evil in ("//evil.example/x", "http://evil.example/", "/\\evil.example"):
        r = c.post("/login", data={"token": TOKEN, "next": evil})
        assert r.headers["Location"] in ("/", "http://localhost/")


def test_the_page_after_login_is_a_local_path_or_the_start_page():
    """A tab or a newline after the first slash (``/\t/evil.example``) is dropped by browsers and by the URL
    parser, so the redirect went to ``//evil.example``: another site; a newline answered 500."""
    from services.web.auth import _safe_next

    for local in ("/bench", "/review?fragment=F1&step=2", "/catalogue/F1#faces", "/a/b%2F/c"):
        assert _safe_next(local) == local
    for evil in (None, "", "//evil.example", "/\\evil.example", "/\t/evil.example", "/\n/evil.example",
                 "/\r\n/evil.example", "/ /evil.example", "/\x7f/x", "\t//evil.example", "http://evil.example/",
                 "https:evil.example", "bench", "/x\\y", "/bench\nSet-Cookie: a=b"):
        assert _safe_next(evil) == "/", repr(evil)


def test_login_redirects_with_control_characters_stay_local(counting_app):
    app, _ = counting_app
    c = app.test_client()
    for evil in ("/\t/evil.example", "/\n/evil.example", "/\r\n/evil.example", "/ /evil.example"):
        r = c.post("/login", data={"token": TOKEN, "next": evil})
        assert r.status_code == 302 and r.headers["Location"] in ("/", "http://localhost/"), (evil, r.status_code)


class _OneProposal:
    """Stands in for the proposal store: proposal 7, FA-FB, without a pose."""

    def proposal(self, pid):
        return ({"id": 7, "fragment_a": "FA", "fragment_b": "FB", "probability": 0.9, "model_version": "m1"}
                if pid == 7 else None)

    def sent(self, pid, verdict, pose, when):
        """A verdict sent (ReviewData notes it until the matcher records it)."""


class _Outbox:
    """Stands in for the station's bus link: keeps what is submitted."""

    def __init__(self):
        self.sent = []

    def submit(self, msg):
        self.sent.append(msg)
        return True


def test_a_verdict_sent_with_the_token_is_recorded_under_the_name_its_sender_gives(tmp_path):
    """Verdicts sent with ``Authorization: Bearer`` were all recorded as by "web": the token is the station's one
    secret and names nobody, so a script names its sender in ``X-Tessera-Who``, as a person does at login."""
    def send(app, headers, **extra):
        r = app.test_client().post("/api/review/verdict", json={"proposal": 7, "verdict": "confirmed"},
                                   headers=headers, **extra)
        assert r.status_code == 200, r.json
        return r.json["sent"]["by"]

    outbox = _Outbox()
    app = web.create_app(token=TOKEN, store_root=tmp_path, review=_OneProposal(), link=outbox)
    assert send(app, {**BEARER, "X-Tessera-Who": "  M. Rossi "}) == "M. Rossi"
    assert outbox.sent[-1]["type"] == "match.verified" and outbox.sent[-1]["by"] == "M. Rossi"   # the event too
    # sent in UTF-8, as curl and most clients do (a header arrives as ISO-8859-1 text)
    assert send(app, {**BEARER, "X-Tessera-Who": "Niccolò Rossi".encode().decode("latin-1")}) == "Niccolò Rossi"
    assert send(app, {**BEARER, "X-Tessera-Who": "x" * 100}) == "x" * 64
    # no name given: [services.web] operator, else "web", as for a login without a name
    assert send(app, BEARER) == "web"
    named = web.create_app(token=TOKEN, store_root=tmp_path, review=_OneProposal(), link=outbox,
                           settings={"operator": "bench-pc"})
    assert send(named, {**BEARER, "X-Tessera-Who": " "}) == "bench-pc"
    # a logged-in browser is recorded under its login's name; the header does not rename it
    c = app.test_client()
    c.post("/login", data={"token": TOKEN, "who": "A. Conservator"})
    csrf = re.search(r'name="csrf-token" content="([^"]+)"', c.get("/review").get_data(as_text=True)).group(1)
    r = c.post("/api/review/verdict", json={"proposal": 7, "verdict": "rejected"},
               headers={"X-CSRF-Token": csrf, "X-Tessera-Who": "someone else"})
    assert r.status_code == 200 and r.json["sent"]["by"] == "A. Conservator"


def test_an_api_request_over_the_size_limit_is_answered_413_in_json(tmp_path):
    """Request bodies over 64 KiB (MAX_CONTENT_LENGTH) got Flask's HTML page; the JSON API answers in JSON, as its
    other errors, and nothing is sent. A page's form keeps Flask's page."""
    outbox = _Outbox()
    c = web.create_app(token=TOKEN, store_root=tmp_path, review=_OneProposal(), link=outbox).test_client()
    big = {"proposal": 7, "verdict": "confirmed", "note": "x" * (64 * 1024)}
    r = c.post("/api/review/verdict", json=big, headers=BEARER)
    assert r.status_code == 413 and r.is_json and "larger than 64 KiB" in r.json["error"]
    assert r.headers["Cache-Control"] == "no-store" and outbox.sent == []
    r = c.post("/login", data={"token": TOKEN, "who": "x" * (64 * 1024)})
    assert r.status_code == 413 and not r.is_json


def test_every_write_endpoint_refuses_an_oversized_body_before_it_answers_anything_else(counting_app):
    """Some views answered before reading the body (404 for an unknown fragment, 409 with no scanner, 503 with no
    broker), so a body over the limit was not refused as such: now every POST route answers 413 for it."""
    app, counter = counting_app
    c = app.test_client()
    big = {"x": "x" * (64 * 1024)}
    for rule in _write_rules(app) + ["/login", "/logout"]:
        r = c.post(_fill(rule), json=big, headers=BEARER)
        assert r.status_code == 413, (rule, r.status_code)
    assert counter.calls == 0


def test_a_chunked_body_is_refused_by_the_running_server_not_cut_at_the_limit(tmp_path):
    """Werkzeug's server cut a chunked body silently at 64 KiB instead of refusing it, so a 300 KiB verdict was
    accepted and sent; a body without a Content-Length is now refused (411) and nothing is sent. Run through a
    real server: the test client never sends a chunked body."""
    import http.client
    import threading

    from werkzeug.serving import make_server

    outbox = _Outbox()
    app = web.create_app(token=TOKEN, store_root=tmp_path, review=_OneProposal(), link=outbox)
    server = make_server("127.0.0.1", 0, app, threaded=True)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        payload = b'{"proposal": 7, "verdict": "confirmed"}' + b" " * (300 * 1024)
        conn = http.client.HTTPConnection("127.0.0.1", server.server_port, timeout=10)
        conn.putrequest("POST", "/api/review/verdict", skip_host=True, skip_accept_encoding=True)
        for k, v in {**BEARER, "Content-Type": "application/json", "Transfer-Encoding": "chunked",
                     "Host": "localhost"}.items():
            conn.putheader(k, v)
        conn.endheaders()
        for i in range(0, len(payload), 8192):
            chunk = payload[i:i + 8192]
            conn.send(b"%x\r\n" % len(chunk) + chunk + b"\r\n")
        conn.send(b"0\r\n\r\n")
        r = conn.getresponse()
        body = r.read()
        assert r.status == 411 and b"Content-Length" in body
        assert outbox.sent == []
        # the same verdict with its length is taken (the refusal is of the chunking, not of the verdict)
        conn = http.client.HTTPConnection("127.0.0.1", server.server_port, timeout=10)
        conn.request("POST", "/api/review/verdict", body=b'{"proposal": 7, "verdict": "confirmed"}',
                     headers={**BEARER, "Content-Type": "application/json", "Host": "localhost"})
        assert conn.getresponse().status == 200 and len(outbox.sent) == 1
    finally:
        server.shutdown()


def test_pages_use_only_assets_served_by_the_station(counting_app):
    app, _ = counting_app
    c = app.test_client()
    for page in ("/bench", "/review", "/status", "/login"):
        r = c.get(page)
        assert r.status_code == 200
        html = r.get_data(as_text=True)
        refs = re.findall(r'(?:src|href)="([^"]*)"', html)
        assert refs and all(ref.startswith("/") and not ref.startswith("//") for ref in refs), refs
        for ref in refs:
            if ref.startswith("/static/"):
                assert c.get(ref).status_code == 200, ref
        assert "default-src 'self'" in r.headers["Content-Security-Policy"]
    for js in ("tessera.js", "bench.js", "review.js", "status.js"):
        text = c.get(f"/static/{js}").get_data(as_text=True)
        assert "http://" not in text and "https://" not in text, js


def test_static_files_are_versioned_and_cached_for_good(counting_app, tmp_path):
    """A page's scripts and styles carry their content's hash (?v=): a browser keeps them without
    asking again; a changed file gets a new URL; a stale or missing version is not cached for good."""
    import hashlib

    from services import web

    app, _ = counting_app
    c = app.test_client()
    html = c.get("/review").get_data(as_text=True)
    src = re.search(r'src="(/static/tessera\.js\?v=([0-9a-f]+))"', html)
    want = hashlib.sha256((web.HERE / "static" / "tessera.js").read_bytes()).hexdigest()[:12]
    assert src and src.group(2) == want
    r = c.get(src.group(1))
    assert r.status_code == 200 and r.headers["Cache-Control"] == "public, max-age=31536000, immutable"
    for stale in ("/static/tessera.js?v=000000000000", "/static/tessera.js"):
        assert "immutable" not in c.get(stale).headers.get("Cache-Control", ""), stale
    # the version follows the content
    f = tmp_path / "x.js"
    f.write_text("a")
    v1 = web.static_version(f)
    f.write_text("bb")
    assert web.static_version(f) != v1 == hashlib.sha256(b"a").hexdigest()[:12]


def test_listens_on_localhost_unless_config_opens_it():
    assert web.web_settings(load_config())["host"] == "127.0.0.1"
    cfg = load_config(None, {"services.web": {"host": "0.0.0.0", "port": 8090}})
    assert web.web_settings(cfg)["host"] == "0.0.0.0"
    with pytest.raises(web.WebConfigError, match="services.web.colour"):
        web.web_settings(load_config(None, {"services.web": {"colour": "red"}}))
    with pytest.raises(web.WebConfigError, match="services.web.port"):
        web.web_settings(load_config(None, {"services.web": {"port": "80"}}))
    with pytest.raises(web.WebConfigError, match="services.web.token"):
        web.web_settings(load_config(None, {"services.web": {"token": "short"}}))


def test_pages_on_loopback_answer_only_under_a_loopback_name(tmp_path):
    """DNS rebinding: a site whose name the attacker points at 127.0.0.1 could read the open pages from a browser
    on this machine. Pages listening on loopback answer under localhost, 127.0.0.1, [::1] (any port: an SSH
    tunnel's may differ) or the published ``public_origin``'s name; any other Host gets 421. On the lab network
    (``host = "0.0.0.0"``) the names the lab uses are not known: no check."""
    loopback = web.create_app(token=TOKEN, store_root=tmp_path).test_client()
    for host in ("localhost", "127.0.0.1:8080", "[::1]:8080", "localhost:9000", "LocalHost."):
        assert loopback.get("/login", headers={"Host": host}).status_code == 200, host
    for host in ("evil.example", "evil.example:8080", "127.0.0.1.evil.example", "localhost.evil.example:8080"):
        r = loopback.get("/login", headers={"Host": host})
        assert r.status_code == 421 and "localhost, 127.0.0.1" in r.get_data(as_text=True), host
    proxied = web.create_app(token=TOKEN, store_root=tmp_path, settings=web.web_settings(
        {"services": {"web": {"public_origin": "https://tessera.lab.example"}}})).test_client()
    assert proxied.get("/login", headers={"Host": "tessera.lab.example"}).status_code == 200
    assert proxied.get("/login", headers={"Host": "evil.example"}).status_code == 421
    lab = web.create_app(token=TOKEN, store_root=tmp_path, settings=web.web_settings(
        {"services": {"web": {"host": "0.0.0.0"}}})).test_client()
    assert lab.get("/login", headers={"Host": "benchpc.lab:8080"}).status_code == 200


def test_pages_on_the_lab_network_answer_only_under_allowed_hosts_when_set(tmp_path):
    """``[services.web] allowed_hosts`` names the lab's names for this host: with it set, pages listening on the lab
    network answer under those names (any port, any case, a final dot), a loopback name or ``public_origin``'s,
    and any other Host gets 421 naming the setting; empty (the default), no check there, as before."""
    def client(**given):
        return web.create_app(token=TOKEN, store_root=tmp_path, settings=web.web_settings(
            {"services": {"web": given}})).test_client()

    lab = client(host="0.0.0.0", allowed_hosts=["tessera-lab", "Tessera-Lab.example.org", "192.0.2.7", "[fe80:0:0::7]"],
                 public_origin="https://tessera.lab.example")
    for host in ("tessera-lab", "tessera-lab:8080", "TESSERA-LAB.example.org.", "192.0.2.7:8080", "[FE80::7]:8080",
                 "localhost:8080", "127.0.0.1", "[::1]:8080", "tessera.lab.example"):
        assert lab.get("/login", headers={"Host": host}).status_code == 200, host
    for host in ("evil.example", "benchpc.lab:8080", "tessera-lab.evil.example", "192.0.2.8", "[fe80::8]:8080"):
        r = lab.get("/login", headers={"Host": host})
        assert r.status_code == 421 and "allowed_hosts" in r.get_data(as_text=True), host
    # empty: as before, the lab-bound pages answer under any name
    for given in ({"host": "0.0.0.0"}, {"host": "0.0.0.0", "allowed_hosts": []}):
        assert client(**given).get("/login", headers={"Host": "benchpc.lab:8080"}).status_code == 200, given


def test_pages_on_loopback_also_answer_under_allowed_hosts(tmp_path):
    loopback = web.create_app(token=TOKEN, store_root=tmp_path, settings=web.web_settings(
        {"services": {"web": {"allowed_hosts": ["tessera-lab"]}}})).test_client()
    for host in ("tessera-lab:8080", "localhost", "127.0.0.1:8080"):
        assert loopback.get("/login", headers={"Host": host}).status_code == 200, host
    r = loopback.get("/login", headers={"Host": "evil.example"})
    assert r.status_code == 421 and "allowed_hosts" in r.get_data(as_text=True)


@pytest.mark.parametrize("bad", ["tessera-lab", ["tessera-lab:8080"], ["http://tessera-lab"], ["tessera-lab/bench"],
                                 ["tessera lab"], [" tessera-lab"], [""], [3], ["fe80::7"], ["[fe80::7]:8080"],
                                 ["*.lab.example"]])
def test_a_malformed_allowed_hosts_is_refused_at_start_naming_it(bad, capsys):
    with pytest.raises(web.WebConfigError, match=r"services\.web\.allowed_hosts: (expected|entry)"):
        web.web_settings({"services": {"web": {"allowed_hosts": bad}}})
    from services.cli import main

    assert main(["web", "--print-token", "--set", f"services.web.allowed_hosts={bad!r}".replace("'", '"')]) == 2
    out = capsys.readouterr().out
    assert "services.web.allowed_hosts" in out and "unknown setting" not in out


def test_the_host_check_follows_the_address_the_pages_listen_on(station_config, tmp_path, monkeypatch):
    """``tessera web --host`` overrides ``[services.web] host``: the check follows the address bound."""
    import http.client
    import threading

    monkeypatch.setenv("STATE_DIRECTORY", str(tmp_path / "state"))
    station_config.setdefault("services", {}).setdefault("web", {})["host"] = "0.0.0.0"
    stop, urls = threading.Event(), []
    t = threading.Thread(target=web.serve, args=(station_config,),
                         kwargs={"host": "127.0.0.1", "port": 0, "with_scanner": False, "ready": urls.append,
                                 "stop": stop}, daemon=True)
    t.start()
    try:
        wait_for(lambda: urls, 30, "the pages to start")
        port = int(urls[0].rsplit(":", 1)[1])

        def status(host):
            conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
            try:
                conn.request("GET", "/login", headers={"Host": host})
                return conn.getresponse().status
            finally:
                conn.close()
        assert (status(f"127.0.0.1:{port}"), status("evil.example")) == (200, 421)
    finally:
        stop.set()
        t.join(15)


def test_token_is_generated_at_first_start_on_local_disk_and_kept(tmp_path, monkeypatch):
    monkeypatch.setenv("STATE_DIRECTORY", str(tmp_path / "state"))   # as systemd's StateDirectory= sets it
    cfg = load_config(None, {"storage.root": str(tmp_path / "storage")})
    token, path = web.station_token(cfg, web.web_settings(cfg))
    assert path == tmp_path / "state" / "web_token" and len(token) >= 32
    assert path.stat().st_mode & 0o777 == 0o600
    assert not (tmp_path / "storage" / "web" / "web_token").exists()   # nothing on the shared storage
    assert web.station_token(cfg, web.web_settings(cfg))[0] == token


def test_local_state_dir_follows_systemd_root_and_xdg(tmp_path, monkeypatch):
    monkeypatch.delenv("STATE_DIRECTORY", raising=False)
    monkeypatch.setattr(os, "geteuid", lambda: 0)
    assert web.local_state_dir() == Path("/var/lib/tessera")
    monkeypatch.setattr(os, "geteuid", lambda: 1000)
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "xdg"))
    assert web.local_state_dir() == tmp_path / "xdg" / "tessera"
    monkeypatch.delenv("XDG_STATE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert web.local_state_dir() == tmp_path / "home" / ".local" / "state" / "tessera"
    monkeypatch.setenv("STATE_DIRECTORY", str(tmp_path / "unit"))
    assert web.local_state_dir() == tmp_path / "unit"


def test_a_token_on_the_storage_root_is_moved_to_local_disk_once(tmp_path, monkeypatch, caplog):
    monkeypatch.setenv("STATE_DIRECTORY", str(tmp_path / "state"))
    old = tmp_path / "storage" / "web" / "web_token"
    old.parent.mkdir(parents=True)
    old.write_text("an-old-station-token-of-enough-length\n")
    cfg = load_config(None, {"storage.root": str(tmp_path / "storage")})
    with caplog.at_level("WARNING", logger="tessera.web"):
        token, path = web.station_token(cfg, web.web_settings(cfg))
    assert token == "an-old-station-token-of-enough-length"       # the lab's scripts keep working
    assert path == tmp_path / "state" / "web_token" and path.stat().st_mode & 0o777 == 0o600
    assert "moved from the storage root" in caplog.text and str(old) in caplog.text
    # read once: the local file is the token from now on, whatever happens to the old one
    old.write_text("another-token-written-there-later\n")
    caplog.clear()
    with caplog.at_level("WARNING", logger="tessera.web"):
        assert web.station_token(cfg, web.web_settings(cfg))[0] == token
    assert "moved" not in caplog.text


# -- bench on the simulated flatbed ---------------------------------------------------------------
def _bench_app(cfg, scanner, surface_for=None):
    link = web.StationLink(cfg)
    bench = web.build_bench(cfg, link=link, scanner=scanner, surface_for=surface_for)
    return web.create_app(token=TOKEN, store_root=cfg["storage"]["root"], bench=bench, link=link), link


def _wait_bench(c, phases, timeout=120.0):
    def done():
        st = c.get("/api/bench").json["bench"]
        if st["phase"] == "waiting":
            c.post("/api/bench/proceed", json={"step": st["step"]["index"]}, headers=BEARER)
        return st if st["phase"] in phases else None
    return wait_for(done, timeout, f"bench phase in {phases}", interval=0.1)


@pytest.mark.parametrize("fault, words", [("SANE_STATUS_COVER_OPEN", "lid is open"),
                                          ("SANE_STATUS_JAMMED", "jam"),
                                          ("SANE_STATUS_DEVICE_BUSY", "busy")])
def test_scanner_faults_reach_the_operator_in_plain_language(station_config, fault, words):
    from common.acquisition.flatbed_sim import SimulatedFlatbed

    sim = SimulatedFlatbed("sim", seed=2)
    sim.fault = fault
    app, link = _bench_app(station_config, sim)
    c = app.test_client()
    st = c.post("/api/bench/prescan", json={"fragment": "F1"}, headers=BEARER).json["bench"]
    assert st["phase"] == "error" and st["error"]["kind"] == "scanner"
    assert words in st["error"]["message"].lower() and "SANE_STATUS" not in st["error"]["message"]
    link.close()


def test_empty_glass_and_two_fragments_are_explained(station_config):
    from common.acquisition.flatbed_sim import SimulatedFlatbed, demo_surface

    sim = SimulatedFlatbed("sim", seed=4)
    app, link = _bench_app(station_config, sim)
    c = app.test_client()
    st = c.post("/api/bench/empty-glass", json={}, headers=BEARER).json["bench"]
    assert st["phase"] == "idle" and "Empty glass scanned" in st["message"]
    st = c.post("/api/bench/prescan", json={"fragment": "F1"}, headers=BEARER).json["bench"]
    assert st["error"]["kind"] == "no_fragment" and "No fragment found" in st["error"]["message"]
    sim.place(demo_surface(35.0, 100, seed=1), centre_mm=(60, 80), angle_deg=0)
    sim.add(demo_surface(35.0, 100, seed=2), centre_mm=(150, 200), angle_deg=0)
    st = c.post("/api/bench/prescan", json={"fragment": "F1"}, headers=BEARER).json["bench"]
    assert st["error"]["kind"] == "multiple_fragments" and "Leave only one fragment" in st["error"]["message"]
    png = c.get("/api/bench/prescan.png")   # the operator sees where the objects are
    assert png.status_code == 200 and png.data[:4] == b"\x89PNG"
    link.close()


def test_capture_with_the_lab_unreachable_keeps_the_scans_and_sends_them_later(tmp_path):
    """Colour-only capture (one scan per face) on the simulated flatbed, no broker running."""
    from common.acquisition.flatbed_sim import SimulatedFlatbed, demo_surface

    from .conftest import station_overrides

    cfg = load_config(None, station_overrides(tmp_path, **{"scanner.colour_only": True, "scanner.dpi": 100}))
    sim = SimulatedFlatbed("sim", seed=4)
    surface = demo_surface(30.0, 100, seed=5)
    app, link = _bench_app(cfg, sim, surface_for=lambda fid: surface)
    c = app.test_client()
    st = c.post("/api/bench/prescan", json={"fragment": "F0007"}, headers=BEARER).json["bench"]
    assert st["phase"] == "idle" and "Fragment found" in st["message"], st
    png = cv2.imdecode(np.frombuffer(c.get("/api/bench/prescan.png").data, np.uint8), cv2.IMREAD_COLOR)
    assert (np.all(png == [64, 230, 0], axis=2)).sum() > 20   # the green outline (BGR) is drawn
    assert c.post("/api/bench/scan", json={"fragment": "F0007"}, headers=BEARER).status_code == 200
    st = _wait_bench(c, ("done", "error"))
    assert st["phase"] == "done", st
    assert st["delivery"]["sent"] is False and "sent automatically" in st["message"]
    # the scans are on storage, the fragment.ready waits in the outbox
    assert Store(cfg["storage"]["root"]).exists(st["delivery"]["artifact"])
    pending = link.outbox.pending()
    assert len(pending) == 1 and pending[0][1]["type"] == "fragment.ready" and pending[0][1]["fragment"] == "F0007"
    rows = c.get("/api/bench").json["fragments"]
    assert rows[0]["fragment"] == "F0007" and rows[0]["stages"]["scanned"] == "done"
    link.close()


def test_the_bench_shows_normals_not_applicable_for_a_colour_only_scan(tmp_path):
    """A ``--colour-only`` scan's face has no normals: the bench ticked its ``normals`` stage; it says ``n/a``,
    as the catalogue does, and a fragment with normals still says ``done``."""
    from common.web.catalogue import Catalogue

    store = Store(tmp_path / "storage")
    albedo, mask = np.full((40, 50, 3), 0.5, np.float32), np.ones((40, 50), bool)
    normals = np.zeros((40, 50, 3), np.float32)
    normals[..., 2] = 1.0
    for fid, n in (("COL1", None), ("NRM1", normals)):
        store.write(f"fragments/{fid}/scans/scans-1.h5", "tessera.test", 1,
                    lambda f: f.create_dataset("x", data=np.zeros(2)))
        save_rgbn(store, f"fragments/{fid}/rgbn/front-0000000000000001.h5", RGBNImage(albedo, mask, 100.0, normals=n))
    catalogue = Catalogue(tmp_path / "catalogue.sqlite", store)
    assert catalogue.rebuild() == 2
    c = web.create_app(token=TOKEN, store_root=store.root, catalogue=catalogue).test_client()
    rows = {r["fragment"]: r["stages"] for r in c.get("/api/bench", headers=BEARER).json["fragments"]}
    assert rows["COL1"] == {"scanned": "done", "normals": "n/a", "features": "waiting", "matched": "waiting",
                            "rendered": "waiting"}
    assert rows["NRM1"]["normals"] == "done"
    # the page draws n/a with its own mark (not the tick of done, not the ellipsis of waiting)
    js = (web.HERE / "static" / "bench.js").read_text()
    assert '"n/a": "–"' in js


# -- review and status with a real broker ---------------------------------------------------------
def _two_fragments(store: Store, pixel_mm: float):
    """Two RGBN fragments cut from one picture, and the true pose of B in A's frame."""
    h, w = 90, 120
    r, col = np.mgrid[0:h, 0:w].astype(np.float32)
    albedo = np.stack([0.5 + 0.4 * np.sin(col / 9), 0.5 + 0.4 * np.cos(r / 7), 0.4 + 0.3 * np.sin((r + col) / 11)], axis=2)
    normals = np.dstack([0.2 * np.sin(col / 5), 0.2 * np.cos(r / 6), np.ones_like(r)])
    normals /= np.linalg.norm(normals, axis=2, keepdims=True)
    left = col < 60
    dpi = 25.4 / pixel_mm
    save_rgbn(store, "fragments/FA/rgbn/front-aaaa.h5", RGBNImage(albedo, left, dpi, normals=normals))
    # B: the right half, shifted into its own frame by 60 px (pose = +60 px along x)
    shift = np.zeros_like(albedo)
    shift[:, :60] = albedo[:, 60:]
    nshift = np.zeros_like(normals)
    nshift[..., 2] = 1
    nshift[:, :60] = normals[:, 60:]
    save_rgbn(store, "fragments/FB/rgbn/front-bbbb.h5", RGBNImage(shift, col < 60, dpi, normals=nshift))
    return (0.0, 60 * pixel_mm, 0.0)


#: the docking's other candidate poses of the review fixture's FA-FB proposal (FB in FA's frame)
ALTERNATIVES = ((90.0, 3.0, 1.0), (-20.0, 5.0, -2.0))


@pytest.fixture
def review_app(station_config, broker):
    from common.matching.proposals import Proposal, ProposalStore
    from common.web.review import ReviewData

    store = Store(station_config["storage"]["root"])
    pose = _two_fragments(store, 25.4 / 200)
    review = ReviewData.from_config(station_config)
    with ProposalStore(review.db_path) as db:
        db.upsert([Proposal("FA", "FB", 0.91, "m1", angle_deg=pose[0], tx_mm=pose[1], ty_mm=pose[2],
                            alignment={"angle_deg": pose[0], "tx_mm": pose[1], "ty_mm": pose[2],
                                       "alternatives": [dict(zip(("angle_deg", "tx_mm", "ty_mm"), alt))
                                                        for alt in ALTERNATIVES]}),
                   Proposal("FA", "FC", 0.35, "m1")])
    link = web.StationLink(station_config)
    app = web.create_app(token=TOKEN, store_root=store.root, link=link, review=review)
    yield app, review
    link.close()


def test_review_queue_pictures_and_a_verdict_that_becomes_match_verified(review_app, station_config):
    from common.bus.client import BrokerClient

    app, review = review_app
    c = app.test_client()
    queue = c.get("/api/review/queue").json
    assert [p["fragment_b"] for p in queue["proposals"]] == ["FB", "FC"]   # most probable first
    assert queue["counts"]["pending"] == 2
    pid = queue["proposals"][0]["id"]
    for view in ("pair-colour", "pair-relief", "joined-colour", "joined-relief"):
        r = c.get(f"/api/review/picture/{pid}/{view}.png")
        assert r.status_code == 200 and r.headers["Content-Type"] == "image/png", view
    joined = cv2.imdecode(np.frombuffer(c.get(f"/api/review/picture/{pid}/joined-colour.png").data, np.uint8), 1)
    # joined at the true pose the two halves make one 90 x 120 picture (+ margins, outlines)
    fg = np.any(joined != [40, 40, 40], axis=2)
    rows, cols = np.flatnonzero(fg.any(axis=1)), np.flatnonzero(fg.any(axis=0))
    assert abs((rows[-1] - rows[0] + 1) - 90) <= 2 and abs((cols[-1] - cols[0] + 1) - 120) <= 2
    assert c.get(f"/api/review/picture/{queue['proposals'][1]['id']}/joined-colour.png").status_code == 404  # no pose
    assert c.get("/api/review/fragment/FC").json["proposals"][0]["fragment_b"] == "FC"

    r = c.post("/api/review/verdict", json={"proposal": pid, "verdict": "confirmed"}, headers=BEARER)
    assert r.status_code == 200 and r.json["sent"]["delivered"] is True
    with BrokerClient.from_config(station_config) as bus:
        events = [unpack(bytes(b)) for _, b in bus.since(0)["events"]]
    verified = [e for e in events if e["type"] == "match.verified"]
    assert len(verified) == 1
    assert (verified[0]["fragment"], verified[0]["other"], verified[0]["verdict"]) == ("FA", "FB", "confirmed")
    hist = c.get("/api/review/history").json
    assert hist["sent"][0]["fragment_b"] == "FB"
    assert c.post("/api/review/verdict", json={"proposal": pid, "verdict": "maybe"}, headers=BEARER).status_code == 400
    assert c.post("/api/review/verdict", json={"proposal": 999, "verdict": "rejected"}, headers=BEARER).status_code == 404
    # ids no SQLite integer can be (they raised OverflowError: a 500) and a bool are no proposal either
    for pid in (2 ** 70, 1e400, -1, True):
        r = c.post("/api/review/verdict", json={"proposal": pid, "verdict": "rejected"}, headers=BEARER)
        assert r.status_code == 404 and "no proposal" in r.json["error"], pid


def test_a_candidate_pose_is_drawn_small_for_the_strip_at_the_same_pose(review_app):
    """The review page shows the candidate poses side by side as small pictures (``px``): the same join at the same
    pose, drawn smaller; a size outside 64 px to the pictures' own is refused naming the range."""
    app, review = review_app
    c = app.test_client()
    pid = c.get("/api/review/queue").json["proposals"][0]["id"]

    def footprint(url):
        img = cv2.imdecode(np.frombuffer(c.get(url).data, np.uint8), 1)
        fg = np.any(img != [40, 40, 40], axis=2)
        rows, cols = np.flatnonzero(fg.any(axis=1)), np.flatnonzero(fg.any(axis=0))
        return img.shape[:2], (rows[-1] - rows[0] + 1, cols[-1] - cols[0] + 1)

    big_shape, big = footprint(f"/api/review/picture/{pid}/joined-colour.png")
    small_shape, small = footprint(f"/api/review/picture/{pid}/joined-colour.png?px=96")
    assert max(small_shape) <= 96 < max(big_shape)
    # the two halves joined at the true pose: one 90 x 120 piece, drawn smaller with its proportions kept
    assert abs(small[1] / small[0] - big[1] / big[0]) < 0.1 and small[1] < big[1]
    # an alternative's adjustment reaches that pose at either size (the adjustment is in mm)
    alt = c.get(f"/api/review/alternatives/{pid}").json["alternatives"][0]
    q = "&".join(f"{k}={v}" for k, v in alt.items())
    assert c.get(f"/api/review/picture/{pid}/joined-colour.png?{q}&px=96").status_code == 200
    for bad in ("10", "641", "abc", "1e3"):
        r = c.get(f"/api/review/picture/{pid}/joined-colour.png?px={bad}")
        assert r.status_code == 400 and "px must be" in r.json["error"], bad


def test_status_shows_a_parked_failure_and_reruns_it(station_config, broker, noop_worker):
    from common.bus.client import BrokerClient
    from common.messages import new_message

    link = web.StationLink(station_config)
    app = web.create_app(token=TOKEN, store_root=station_config["storage"]["root"], link=link)
    c = app.test_client()
    with BrokerClient.from_config(station_config) as bus:
        bus.submit(new_message("noop.job", fragment="F9", fail=True))
    st = wait_for(lambda: (s := c.get("/api/status").json)["parked"] and s, 30, "the failing job to be parked")
    assert st["reachable"] and st["parked"][0]["fragment"] == "F9"
    assert "asked to fail" in st["parked"][0]["error"]
    assert any(w["service"] == "noop" for ws in st["workers"].values() for w in ws)
    job = st["parked"][0]["job"]
    assert c.post("/api/status/rerun", json={"job": job}).status_code == 401
    # a job that is not a string is refused, not forwarded as its text ("None")
    for bad in (None, 7, [job]):
        r = c.post("/api/status/rerun", json={"job": bad}, headers=BEARER)
        assert r.status_code == 400 and "job must be" in r.json["error"], bad
    r = c.post("/api/status/rerun", json={"job": job}, headers=BEARER)
    assert r.status_code == 200 and r.json["rerun"] == [job]
    link.close()


def test_status_says_plainly_when_the_broker_is_down(station_config):
    link = web.StationLink(station_config)
    app = web.create_app(token=TOKEN, store_root=station_config["storage"]["root"], link=link)
    r = app.test_client().get("/api/status")
    assert r.status_code == 503 and "cannot be reached" in r.json["error"]
    link.close()


def test_a_write_the_bus_cannot_take_is_answered_503_naming_it(tmp_path):
    from werkzeug.exceptions import HTTPException

    from services.web.station import station, submit_or_503

    class RefusingLink:
        def submit(self, msg):
            raise OSError("outbox disk full")

    app = web.create_app(token=TOKEN, store_root=tmp_path)
    with app.test_request_context("/"):
        with pytest.raises(HTTPException) as no_broker:
            submit_or_503({"uid": "0" * 32}, "verdict")
        station().link = RefusingLink()
        with pytest.raises(HTTPException) as refused:
            submit_or_503({"uid": "0" * 32}, "edit")
    assert no_broker.value.response.status_code == 503
    assert no_broker.value.response.get_json()["error"].endswith("the verdict was not sent")
    assert refused.value.response.status_code == 503
    assert refused.value.response.get_json()["error"] == "the edit could not be sent to the broker: outbox disk full"


def test_the_conservator_corrects_the_pose_and_the_verdict_keeps_it(review_app, station_config):
    """The review page's pose controls: B turned about its centre and moved in A's frame; the joined
    picture shows it and the verdict's match.verified carries that pose (docs/web.md, review page)."""
    from common.bus.client import BrokerClient
    from common.matching.pose import adjusted_pose

    app, review = review_app
    c = app.test_client()
    pid = c.get("/api/review/queue").json["proposals"][0]["id"]
    pixel_mm = 25.4 / 200

    def width_px(query=""):
        img = cv2.imdecode(np.frombuffer(c.get(f"/api/review/picture/{pid}/joined-colour.png{query}").data, np.uint8), 1)
        cols = np.flatnonzero(np.any(img != [40, 40, 40], axis=2).any(axis=0))
        return cols[-1] - cols[0] + 1

    # B (the right half) moved 5 mm right: the join is 5 mm (39 px) wider
    assert abs(width_px("?shift_x_mm=5") - width_px() - 5 / pixel_mm) <= 3
    for bad in ("?turn_deg=nan", "?shift_x_mm=abc", "?shift_y_mm=5000"):
        assert c.get(f"/api/review/picture/{pid}/joined-colour.png{bad}").status_code == 400, bad

    adjust = {"turn_deg": 10.0, "shift_x_mm": 2.0, "shift_y_mm": -1.0}
    r = c.post("/api/review/verdict", json={"proposal": pid, "verdict": "confirmed", "adjust": adjust}, headers=BEARER)
    assert r.status_code == 200
    with BrokerClient.from_config(station_config) as bus:
        events = [unpack(bytes(b)) for _, b in bus.since(0)["events"]]
    pose = [e for e in events if e["type"] == "match.verified"][-1]["pose"]
    # B's centre: its mask (columns 0-59 of the 90 x 60 half) in its own frame, mm
    centre = ((60 - 1) / 2 * pixel_mm, (90 - 1) / 2 * pixel_mm)
    expected = adjusted_pose((0.0, 60 * pixel_mm, 0.0), centre, turn_deg=10.0, shift_mm=(2.0, -1.0))
    assert (pose["angle_deg"], pose["tx_mm"], pose["ty_mm"]) == pytest.approx(expected, abs=0.02)
    # a malformed adjustment is refused
    assert c.post("/api/review/verdict", json={"proposal": pid, "verdict": "confirmed", "adjust": [1, 2]},
                  headers=BEARER).status_code == 400


def _verified(station_config) -> list[dict]:
    from common.bus.client import BrokerClient

    with BrokerClient.from_config(station_config) as bus:
        return [e for _, b in bus.since(0)["events"] if (e := unpack(bytes(b)))["type"] == "match.verified"]


def test_confirming_a_confirmed_proposal_again_keeps_its_corrected_pose(review_app, station_config):
    """The RePAIR trial: a confirmed proposal was shown at the matcher's proposed pose, not at the corrected pose
    kept with the confirmation, and pressing C again sent the uncorrected pose (the reconstruction moved a piece
    by ~8 mm). A decided proposal stands at its verdict's pose — shown there, and kept by a verdict without a new
    correction — before the matcher records it (sent) and after (recorded), in this process or another."""
    from common.matching.proposals import ProposalStore
    from common.web.review import ReviewData

    app, review = review_app
    c = app.test_client()
    pid = c.get("/api/review/queue").json["proposals"][0]["id"]
    proposed = {"angle_deg": 0.0, "tx_mm": 60 * 25.4 / 200, "ty_mm": 0.0}
    adjust = {"turn_deg": 2.0, "shift_x_mm": 6.0, "shift_y_mm": -5.0}   # ~8 mm
    assert c.post("/api/review/verdict", json={"proposal": pid, "verdict": "confirmed", "adjust": adjust},
                  headers=BEARER).status_code == 200
    corrected = _verified(station_config)[-1]["pose"]
    assert corrected != pytest.approx(proposed)

    def shown(client):
        (p,) = [p for p in client.get("/api/review/fragment/FB").json["proposals"] if p["id"] == pid]
        return p

    def confirm_again(client):
        assert client.post("/api/review/verdict", json={"proposal": pid, "verdict": "confirmed"},
                           headers=BEARER).status_code == 200
        return _verified(station_config)[-1]["pose"]

    # sent, not yet recorded by the matcher: shown at the corrected pose, and C again keeps it
    assert shown(c)["pose"] == pytest.approx(corrected) and shown(c)["proposed_pose"] == pytest.approx(proposed)
    assert confirm_again(c) == pytest.approx(corrected)
    # the matcher records the verdicts (as services/matcher.py does: the message's time, uid and pose)
    with ProposalStore(review.db_path) as db:
        for e in _verified(station_config):
            db.record_verdict(e["fragment"], e["other"], e["verdict"], by=e["by"], message_uid=e["uid"],
                              when=e["time"], pose=e.get("pose"))
    p = shown(c)
    assert p["status"] == "confirmed" and p["pose"] == p["verdict_pose"] == pytest.approx(corrected)
    assert confirm_again(c) == pytest.approx(corrected)
    # the joined picture without a correction is the one at the corrected pose
    assert c.get(f"/api/review/picture/{pid}/joined-colour.png").data == review.picture(
        pid, "joined-colour", max_side_px=640, pose=corrected)
    # "other pose" offers the way back to the matcher's proposed pose; taking it, the verdict keeps that
    back = c.get(f"/api/review/alternatives/{pid}").json["proposed"]
    assert review.adjusted_pose(pid, back["turn_deg"], (back["shift_x_mm"], back["shift_y_mm"])) == pytest.approx(
        proposed, abs=1e-6)
    # another web process (the review host), which sent none of it, shows and keeps the recorded pose too
    link = web.StationLink(station_config)
    try:
        other = web.create_app(token=TOKEN, store_root=review.store.root, link=link,
                               review=ReviewData(review.db_path, review.store)).test_client()
        assert shown(other)["pose"] == pytest.approx(corrected)
        assert confirm_again(other) == pytest.approx(corrected)
    finally:
        link.close()


def test_the_conservator_steps_through_the_dockings_other_poses(review_app):
    """The review page's "other pose" (P): each of the proposal's alternatives as the adjustment of its
    pose that reaches it, so the joined picture and the verdict show and keep that pose."""
    app, review = review_app
    c = app.test_client()
    queue = c.get("/api/review/queue").json["proposals"]
    pid = queue[0]["id"]
    got = c.get(f"/api/review/alternatives/{pid}").json["alternatives"]
    assert len(got) == len(ALTERNATIVES)
    for adj, alt in zip(got, ALTERNATIVES):
        pose = review.adjusted_pose(pid, adj["turn_deg"], (adj["shift_x_mm"], adj["shift_y_mm"]))
        assert abs((pose["angle_deg"] - alt[0] + 180) % 360 - 180) < 1e-6
        assert (pose["tx_mm"], pose["ty_mm"]) == pytest.approx(alt[1:], abs=1e-6)
        q = "?" + "&".join(f"{k}={v}" for k, v in adj.items())
        assert c.get(f"/api/review/picture/{pid}/joined-colour.png{q}").status_code == 200
    r = c.get(f"/api/review/alternatives/{queue[1]['id']}")   # FA-FC: no pose, so nothing to step from
    assert r.status_code == 404 and "no proposed pose" in r.json["error"]
    assert c.get("/api/review/alternatives/999999").status_code == 404


def test_the_review_queue_is_the_matchers_order_fifty_at_a_time(tmp_path):
    """docs/web.md, review page: the queue lists the pending proposals in the matcher's order (mutual
    proximity, then probability: not simply "most probable first", as the page said), 50 unless
    ``?limit=`` (at most 500) asks for more; a fragment's list its 20 best of any status."""
    from common.matching.proposals import Proposal, ProposalStore
    from common.web.review import ReviewData

    store = Store(tmp_path / "storage")
    db_path = tmp_path / "storage" / "matches" / "proposals.sqlite"
    with ProposalStore(db_path) as db:
        db.upsert([Proposal("A", f"B{i:02d}", 0.5 + i / 200, "m1", mutual=(i + 1) / 100) for i in range(60)]
                  + [Proposal("A", "Z", 0.99, "m1", mutual=0.001)])
    c = web.create_app(token=TOKEN, store_root=store.root, review=ReviewData(db_path, store)).test_client()
    queue = c.get("/api/review/queue").json
    assert queue["counts"]["pending"] == 61 and len(queue["proposals"]) == 50
    assert [p["fragment_b"] for p in queue["proposals"][:2]] == ["B59", "B58"]   # mutual proximity first
    everything = c.get("/api/review/queue?limit=500").json["proposals"]
    assert len(everything) == 61 and everything[-1]["fragment_b"] == "Z"   # the most probable, last
    assert len(c.get("/api/review/fragment/A").json["proposals"]) == 20


def test_the_docs_name_every_blueprint_module_and_api_area():
    """docs/web.md "How the app is built" has a row per blueprint module and "JSON endpoints" every
    area of /api/ (downloads.py and /api/downloads were missing)."""
    doc = (Path(web.__file__).resolve().parents[2] / "docs" / "web.md").read_text()
    built = doc.split("## How the app is built", 1)[1].split("\n## ", 1)[0]
    table = dict(re.findall(r"^\| `(\w+)\.py` \| `(\w+)` \|", built, re.M))
    for bp in web.BLUEPRINTS:
        module = bp.import_name.rsplit(".", 1)[1]
        assert table.get(module) == bp.name, module
    endpoints = doc.split("## JSON endpoints", 1)[1].split("\n## ", 1)[0]
    app = web.create_app(token=TOKEN, store_root=Path("/nonexistent"))
    areas = {"/".join(r.rule.split("/")[:3]) for r in app.url_map.iter_rules() if r.rule.startswith("/api/")}
    for area in sorted(areas):
        assert f"`{area}" in endpoints, area


def test_a_verdict_kept_while_the_broker_was_down_is_sent_by_the_review_host_without_a_scanner(
        station_config, broker, tmp_path, monkeypatch):
    """``tessera web --no-scanner`` (the review host) retried its outbox only when another verdict was given:
    a verdict kept while the broker was down, the session's last, waited there (shown *sent*, never
    recorded) however long the lab was back. The outbox is retried in the background with or without a
    scanner."""
    import threading

    from common.bus.client import BrokerClient
    from common.bus.outbox import Outbox
    from common.messages import new_message

    monkeypatch.setenv("STATE_DIRECTORY", str(tmp_path / "state"))
    verdict = new_message("match.verified", fragment="FA", other="FB", verdict="confirmed", proposal=1,
                          probability=0.5, by="M. Rossi", model_version="m1")
    outbox = Outbox(station_config["scanner"]["spool_dir"])   # given while the broker was away
    outbox.put(verdict)
    outbox.close()
    stop, urls = threading.Event(), []
    t = threading.Thread(target=web.serve, args=(station_config,),
                         kwargs={"port": 0, "with_scanner": False, "ready": urls.append, "stop": stop}, daemon=True)
    t.start()
    try:
        wait_for(lambda: urls, 30, "the pages to start")

        def delivered():
            with BrokerClient.from_config(station_config) as bus:
                return [e for _, b in bus.since(0)["events"] if (e := unpack(bytes(b)))["uid"] == verdict["uid"]]
        wait_for(delivered, 15, "the kept verdict to reach the broker")
    finally:
        stop.set()
        t.join(15)
    outbox = Outbox(station_config["scanner"]["spool_dir"])
    try:
        assert len(outbox) == 0
    finally:
        outbox.close()
