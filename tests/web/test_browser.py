"""The pages in a real browser against a real station on the simulated scanner.

Processes as the station runs them (broker, stage workers, ``tessera web``), Chromium driven by
Playwright: the operator captures a fragment end to end, the conservator confirms a proposal and
sees it recorded, a failure shows on the status page. Screenshots of each page go to a temporary
folder, or to ``docs/web/`` (the pictures in ``docs/web.md``) with ``TESSERA_WEB_SCREENSHOTS=1``:

    TESSERA_WEB_SCREENSHOTS=1 python -m pytest tests/web/test_browser.py

Needs the pip package ``playwright`` and Debian's ``chromium`` (``apt-get install -y chromium``;
never ``playwright install``); skipped, saying which is missing, otherwise.
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import time
from pathlib import Path

import cv2
import pytest

from common.config import default_config_path, load_config

from .conftest import TOKEN, free_port
from .viewer_support import CHROMIUM, CHROMIUM_ARGS, children, require_browser, wait_for_web

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
DOCS = REPO / "docs" / "web"
SHOTS: Path | None = None   # set by the ``live`` fixture
# the bench and review pages draw no WebGL: no software GL needed
BENCH_CHROMIUM_ARGS = [*CHROMIUM_ARGS, "--disable-gpu"]
STAGES = ("solver", "features", "matcher", "renderer")
MAX_PNG_BYTES = 300_000


def _shot(page, name: str) -> None:
    """Screenshot into <SHOTS>/<name>.png, shrunk until it is under ~300 KB."""
    SHOTS.mkdir(parents=True, exist_ok=True)
    path = SHOTS / f"{name}.png"
    page.screenshot(path=str(path), full_page=True)
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    scale = 1.0
    while path.stat().st_size > MAX_PNG_BYTES and scale > 0.3:
        scale *= 0.8
        small = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(path), small, [cv2.IMWRITE_PNG_COMPRESSION, 9])


def _seed_review(cfg) -> list[tuple[str, str]]:
    """RGBN images of a synthetic fresco's fragments and join proposals among them (true poses from
    the generator's ground truth, plus one non-neighbour pair), as the matcher would leave them."""
    from common.matching.proposals import Proposal, ProposalStore, ordered_pair
    from common.rgbn.image import save_rgbn
    from common.store import Store
    from common.synth import generate_wall
    from common.web.compose import relative_pose

    store = Store(cfg["storage"]["root"])
    wall = generate_wall(6, 11, dpi=100)
    frags = {f.id: f for f in wall.fragments}
    for f in wall.fragments:
        save_rgbn(store, f"fragments/{f.id}/rgbn/front-groundtruth.h5", f.rgbn)
    proposals, pairs = [], []
    for k, (a, b, shared) in enumerate(sorted(wall.adjacency, key=lambda x: -x[2])[:3]):
        a, b = ordered_pair(a, b)
        angle, tx, ty = relative_pose(frags[a].pose, frags[b].pose)
        # the first offers two other candidate poses, as the docking's stage 3 does (the review's P)
        alternatives = [{"angle_deg": angle + 90.0, "tx_mm": tx + 4.0, "ty_mm": ty},
                        {"angle_deg": angle - 30.0, "tx_mm": tx, "ty_mm": ty - 3.0}] if k == 0 else []
        proposals.append(Proposal(a, b, 0.93 - 0.1 * k, "groundtruth", angle_deg=angle, tx_mm=tx, ty_mm=ty,
                                  alignment={"alternatives": alternatives} if alternatives else None))
        pairs.append((a, b))
    adjacent = {ordered_pair(a, b) for a, b, _ in wall.adjacency}
    ids = sorted(frags)
    wrong = next(ordered_pair(a, b) for a in ids for b in ids if a < b and ordered_pair(a, b) not in adjacent)
    proposals.append(Proposal(*wrong, 0.21, "groundtruth", angle_deg=40.0, tx_mm=25.0, ty_mm=-10.0))
    db_path = Path(cfg["storage"]["root"]) / "matches" / "proposals.sqlite"
    with ProposalStore(db_path) as db:
        db.upsert(proposals)
    return pairs


class LiveStation:
    """Broker, stage workers and ``tessera web`` as separate processes on loopback."""

    def __init__(self, root: Path):
        self.root = root
        self.web_port = free_port()
        self.stages = [s for s in STAGES if importlib.util.find_spec(f"services.{s}") is not None]
        # the station's own routing table (a config file replaces it whole), and the noop failure's
        routing = {**load_config(default_config_path())["routing"], "noop.job": ["noop"]}
        routing_lines = "\n".join(f'"{event}" = {json.dumps(services)}' for event, services in routing.items())
        text = f"""
[storage]
root = "{root / 'storage'}"
[broker]
host = "127.0.0.1"
bind = "127.0.0.1"
port = {free_port()}
feed_port = {free_port()}
journal_dir = "{root / 'journal'}"
heartbeat_interval_s = 0.5
max_attempts = 2
[client]
timeout_s = 1.0
retries = 2
[routing]
{routing_lines}
[scanner]
device = "simulated"
spool_dir = "{root / 'bench'}"
dpi = 100
prescan_dpi = 50
wall_dpi = 100
fragments = 4
seed = 1
drain_interval_s = 0.5
[services.matcher]
bootstrap_fragments = 12
[services.web]
port = {self.web_port}
token = "{TOKEN}"
long_poll_s = 2.0
"""
        self.config_path = root / "station.toml"
        self.config_path.write_text(text)
        self.config = load_config(self.config_path)
        self.children = children(self.config_path, root)
        self.url = f"http://127.0.0.1:{self.web_port}"

    def start(self) -> None:
        self.children.start("broker", "broker")
        for stage in ["noop", *self.stages]:
            self.children.start(stage, "worker", stage)
        wait_for_web(self.children.start("web", "web"), self.url, self.root / "web.log")

    def stop(self) -> None:
        self.children.stop(grace_s=10.0)

    def logs(self) -> str:
        return "\n".join(f"--- {f.name}\n{f.read_text()[-1500:]}" for f in sorted(self.root.glob("*.log")))


def test_the_live_station_routes_every_event_as_the_station_does(tmp_path):
    """The test station's routing is the configured station's (configs/station.toml), plus the noop job the
    failure test sends: a message type routed at the station (match.refitted, match.reranked) runs here too."""
    routing = LiveStation(tmp_path).config["routing"]
    assert routing == {**load_config(default_config_path())["routing"], "noop.job": ["noop"]}
    assert routing["match.refitted"] == routing["match.reranked"] == ["matcher"]


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    require_browser()
    global SHOTS
    station = LiveStation(tmp_path_factory.mktemp("station"))
    SHOTS = DOCS if os.environ.get("TESSERA_WEB_SCREENSHOTS") == "1" else station.root / "screenshots"
    pairs = _seed_review(station.config)
    station.start()
    station.pairs = pairs
    yield station
    station.stop()


@pytest.fixture(scope="module")
def browser():
    require_browser()
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=BENCH_CHROMIUM_ARGS)
        yield b
        b.close()


def _login(browser, live, who="Test Operator", next_path="/bench"):
    """A new browser context signed in as ``who``, its page on ``next_path`` (path and query)."""
    import urllib.parse

    ctx = browser.new_context(viewport={"width": 1280, "height": 860})
    page = ctx.new_page()
    page.goto(f"{live.url}/login?next={urllib.parse.quote(next_path, safe='/')}")
    page.fill("#token", TOKEN)
    page.fill("#who", who)
    page.click("#login-submit")
    page.wait_for_url(f"{live.url}{next_path}")
    return ctx, page


def _stalled(page, live, step: str, console: list[str]) -> None:
    """Fail saying what the page, its console and the station each say (the page shows ``step``)."""
    import urllib.request

    try:
        with urllib.request.urlopen(f"{live.url}/api/bench", timeout=10) as r:
            server = json.load(r)["bench"]
        server = {k: server.get(k) for k in ("phase", "step", "seq", "message", "busy")}
    except Exception as exc:   # the web process itself is stuck
        server = f"no answer: {exc}"
    shown = page.evaluate("""() => ({active: document.activeElement && document.activeElement.id,
                                     message: document.getElementById('bench-message').textContent,
                                     proceedDisabled: document.getElementById('proceed-button').disabled})""")
    pytest.fail(f"the capture stalled: the page shows {step} (page {shown}); the station says {server}; "
                f"the page's console: {console}\n{live.logs()}")


def _free_the_scanner(live) -> None:
    """Cancel a capture a failed test left waiting for a step (nothing if none is), so the tests after
    it find the scanner free instead of failing too."""
    import urllib.request

    req = urllib.request.Request(f"{live.url}/api/bench/cancel", data=b"{}", method="POST",
                                 headers={"Authorization": f"Bearer {TOKEN}", "Content-Type": "application/json"})
    urllib.request.urlopen(req, timeout=10).close()


def test_operator_captures_a_fragment_end_to_end(browser, live):
    ctx, page = _login(browser, live)
    console: list[str] = []
    page.on("pageerror", lambda exc: console.append(f"uncaught: {exc}"))
    page.on("console", lambda m: console.append(f"{m.type}: {m.text}") if m.type in ("error", "warning") else None)
    try:
        page.fill("#fragment-id", "F0001")
        page.click("#prescan-button")
        page.wait_for_function("() => /Fragment found/.test(document.getElementById('bench-message').textContent) || "
                               "!document.getElementById('bench-error').hidden", timeout=60_000)
        assert "Fragment found" in page.inner_text("#bench-message"), page.inner_text("#bench-error")
        page.wait_for_selector("#prescan:not([hidden])", timeout=10_000)
        _shot(page, "bench-prescan")
        page.click("#scan-button")
        seen_steps, shot = [], False
        state_js = """() => {
            const err = document.getElementById('bench-error');
            if (!err.hidden) return 'error';
            if (/captured/.test(document.getElementById('bench-message').textContent)) return 'done';
            const step = document.getElementById('step');
            return step.hidden ? '' : 'step:' + document.getElementById('step-count').textContent;
        }"""
        deadline = time.monotonic() + 240   # inside pytest's own 300 s, so a stall says where it stalled
        pressed_at = time.monotonic()
        while time.monotonic() < deadline:
            state = page.wait_for_function(state_js, timeout=120_000).json_value()
            if not state.startswith("step:"):
                break
            count = state[5:]
            if count not in seen_steps:
                seen_steps.append(count)
                if count.startswith("Step 2 ") and not shot:
                    _shot(page, "bench-step")
                    shot = True
                page.keyboard.press("Enter")   # the operator has done the step (once: the page must take it)
                pressed_at = time.monotonic()
            elif time.monotonic() - pressed_at > 60:   # a scan at 100 dpi takes a second or two
                _stalled(page, live, count, console)
            page.wait_for_timeout(150)
        else:
            _stalled(page, live, seen_steps[-1] if seen_steps else "before step 1", console)
        error = page.inner_text("#bench-error-text") if page.is_visible("#bench-error") else ""
        assert not error, f"capture failed: {error}\n{live.logs()}"
        assert seen_steps == [f"Step {i} of 8" for i in range(1, 9)], seen_steps
        assert "F0001 is captured and sent to the lab" in page.inner_text("#bench-message")
        row = 'tr[data-fragment="F0001"]'
        page.wait_for_selector(f'{row} td[data-stage="scanned"][data-state="done"]', timeout=30_000)
        if "solver" in live.stages:   # the live list follows the pipeline without a reload
            cell = page.wait_for_selector(f'{row} td[data-stage="normals"]:not([data-state="waiting"])',
                                          timeout=180_000)
            assert cell.get_attribute("data-state") in ("done", "failed")   # failed: parked, see Status
        _shot(page, "bench")
    finally:
        ctx.close()
        _free_the_scanner(live)


def test_the_bench_page_keeps_following_the_station_after_a_bad_answer(browser, live):
    """One live-poll answer the page cannot draw (a broken reply) and one that fails outright must
    not stop the page: a pre-scan started from another browser still shows on it."""
    ctx, page = _login(browser, live)
    other_ctx, other = _login(browser, live, who="Second Operator")
    try:
        page.wait_for_function("() => document.getElementById('prescan-button').disabled === false", timeout=30_000)
        answers = []

        def broken(route):
            answers.append(route.request.url)
            if len(answers) == 1:
                route.fulfill(status=200, content_type="application/json", body='{"bench": null}')
            elif len(answers) == 2:
                route.abort()
            else:
                route.continue_()

        page.route("**/api/bench?after=*", broken)
        page.wait_for_function("() => true")   # the route is in place before the next poll
        deadline = time.monotonic() + 30
        while len(answers) < 3 and time.monotonic() < deadline:
            page.wait_for_timeout(200)
        assert len(answers) >= 3, f"the page stopped polling after {len(answers)} answer(s)"
        other.fill("#fragment-id", "F0002")
        other.click("#prescan-button")
        page.wait_for_function("() => /Fragment found/.test(document.getElementById('bench-message').textContent)",
                               timeout=60_000)
    finally:
        other_ctx.close()
        ctx.close()


def test_a_late_live_poll_answer_does_not_take_the_page_back_from_a_step(browser, live):
    """Answers can arrive out of order: the scan's answer (the capture already waiting at step 1) before
    the long poll's, read a moment earlier (it lists today's fragments too). The page must not draw that
    older state over the step: there the operator's Enter was not taken, the station waited for step 1
    for good and the end-to-end capture stalled at "Step 1" in CI. Every bench answer here is the test's,
    in the order it chooses; a state of another session (the station restarted) is still drawn."""
    ctx, page = _login(browser, live, next_path="/status")   # no bench page polls before the route is in place
    step1 = {"index": 1, "total": 8, "face": "front", "rotation": 0.0,
             "instruction": "Place the fragment face down (front face, scan 1 of 8)"}

    def state(seq, phase, message="", step=None, session="before"):
        return {"phase": phase, "fragment": None if phase == "idle" else "F0009", "step": step,
                "scans_done": 1 if step else 0, "scans_total": 8 if step else 0, "message": message,
                "error": None, "delivery": None, "seq": seq, "session": session, "busy": phase != "idle",
                "history": []}

    held, proceeds = [], []   # long polls not answered yet; the steps confirmed

    def answer(route, st):
        route.fulfill(status=200, content_type="application/json",
                      body=json.dumps({"bench": st, "fragments": [], "time": time.time()}))

    def bench_api(route):
        path = route.request.url[len(live.url):]
        if path == "/api/bench":
            answer(route, state(4, "idle", "Fragment found. Press Scan to capture it."))
        elif path.startswith("/api/bench?after="):
            held.append(route)
        elif path == "/api/bench/scan":
            answer(route, state(6, "waiting", step=step1))
        elif path == "/api/bench/proceed":
            proceeds.append(route.request.post_data_json)
            answer(route, state(6, "waiting", step=step1))
        else:
            route.abort()

    def wait_until(condition, what):
        deadline = time.monotonic() + 10
        while not condition():
            assert time.monotonic() < deadline, f"the page never {what}"
            page.wait_for_timeout(50)   # lets the routes run

    shown = "() => document.getElementById('step').hidden ? document.getElementById('bench-message').textContent " \
            ": document.getElementById('step-count').textContent"
    try:
        page.route(re.compile(r"/api/bench(\?|/|$)"), bench_api)
        page.goto(f"{live.url}/bench")
        wait_until(lambda: len(held) == 1, "started its long poll")
        page.fill("#fragment-id", "F0009")
        page.click("#scan-button")
        page.wait_for_function("() => !document.getElementById('step').hidden", timeout=10_000)
        answer(held[0], state(5, "scanning", "Starting the capture…"))   # the long poll's older answer, late
        wait_until(lambda: len(held) == 2, "polled again after the late answer")
        assert page.evaluate(shown) == "Step 1 of 8", "the late answer took the page back from the step"
        page.keyboard.press("Enter")
        wait_until(lambda: proceeds, "sent the step the operator confirmed")
        assert proceeds == [{"step": 1}]
        # the station restarted: its seq start again, and the page follows it
        answer(held[1], state(1, "idle", "The scanner is ready.", session="after"))
        page.wait_for_function(f"() => ({shown})() === 'The scanner is ready.'", timeout=10_000)
    finally:
        ctx.close()


def test_conservator_confirms_a_proposal_and_sees_it_recorded(browser, live):
    from common.bus.client import BrokerClient
    from common.messages import unpack

    ctx, page = _login(browser, live, who="A. Conservator")
    try:
        page.goto(f"{live.url}/review")
        page.wait_for_selector("#queue li.current", timeout=30_000)
        first = live.pairs[0]
        assert page.inner_text("#proposal-title") == f"{first[0]} ↔ {first[1]}"
        probs = [float(re.match(r"([\d.]+)%", t).group(1)) for t in page.locator("#queue .prob").all_inner_texts()]
        assert probs == sorted(probs, reverse=True)   # most probable first
        for view in ("joined-colour", "joined-relief", "pair-colour", "pair-relief"):
            page.wait_for_function(f"() => document.getElementById('{view}').complete && "
                                   f"document.getElementById('{view}').naturalWidth > 0", timeout=60_000)
        # the conservator corrects the pose: B turned 1° clockwise ("]" twice) and moved 0.5 mm right
        import json
        import urllib.request

        with urllib.request.urlopen(f"{live.url}/api/review/queue") as r:
            current = next(p for p in json.load(r)["proposals"] if (p["fragment_a"], p["fragment_b"]) == first)
        proposed = current["pose"]
        # P steps to the docking's next candidate pose (as an adjustment of the proposed one), 0 back
        with urllib.request.urlopen(f"{live.url}/api/review/alternatives/{current['id']}") as r:
            alternatives = json.load(r)["alternatives"]
        page.keyboard.press("p")
        if alternatives:
            page.wait_for_selector(f"#pose-adjust:has-text('candidate pose 2 of {len(alternatives) + 1}')", timeout=5_000)
            assert f"turn_deg={alternatives[0]['turn_deg']:.3f}" in page.get_attribute("#joined-colour", "src")
        else:
            page.wait_for_selector("#pose-adjust:has-text('no other candidate pose')", timeout=5_000)
        # the strip shows every candidate pose at once, small; a click shows one above, as P would
        n = len(alternatives) + 1
        assert n == 3, "the fixture's first proposal offers two other poses"
        page.wait_for_function(f"() => [...document.querySelectorAll('#pose-candidates img')].filter("
                               f"i => i.complete && i.naturalWidth > 0 && i.naturalWidth <= 160).length === {n}",
                               timeout=30_000)
        assert page.locator("#pose-candidates button.current").count() == 1   # P's candidate 2, outlined
        page.locator("#pose-candidates button").nth(2).click()
        page.wait_for_selector(f"#pose-adjust:has-text('candidate pose 3 of {n}')", timeout=5_000)
        assert f"turn_deg={alternatives[1]['turn_deg']:.3f}" in page.get_attribute("#joined-colour", "src")
        assert "px=160" in page.locator("#pose-candidates img").nth(2).get_attribute("src")
        assert page.locator("#pose-candidates button").nth(2).get_attribute("class") == "current"
        page.keyboard.press("0")
        page.wait_for_function("() => !document.querySelector('#pose-candidates button:nth-child(3).current')"
                               " && document.querySelector('#pose-candidates button:nth-child(1).current')",
                               timeout=5_000)
        page.keyboard.press("]")
        page.keyboard.press("]")
        page.keyboard.press("Shift+ArrowRight")
        page.wait_for_selector("#pose-adjust:has-text('turned 1.0°, moved (0.5, 0.0) mm')", timeout=5_000)
        assert page.inner_text("#proposal-title") == f"{first[0]} ↔ {first[1]}"   # shift+arrow did not move the queue
        # X makes a step coarser (0.5 → 2 → 5 → 0.5, mm and degrees): there and back, to the same pose
        page.keyboard.press("x")
        page.keyboard.press("Shift+ArrowDown")
        page.wait_for_selector("#pose-adjust:has-text('turned 1.0°, moved (0.5, 2.0) mm')", timeout=5_000)
        page.keyboard.press("Shift+ArrowUp")
        page.keyboard.press("x")
        assert page.inner_text("#pose-step") == "step 5"
        page.keyboard.press("]")
        page.wait_for_selector("#pose-adjust:has-text('turned 6.0°, moved (0.5, 0.0) mm')", timeout=5_000)
        page.keyboard.press("[")
        page.keyboard.press("x")
        assert page.inner_text("#pose-step") == "step 0.5"
        page.wait_for_selector("#pose-adjust:has-text('turned 1.0°, moved (0.5, 0.0) mm')", timeout=5_000)
        src = page.get_attribute("#joined-colour", "src")
        assert "turn_deg=1.000" in src and "shift_x_mm=0.500" in src
        page.wait_for_function("() => document.getElementById('joined-colour').complete && "
                               "document.getElementById('joined-colour').naturalWidth > 0", timeout=60_000)
        _shot(page, "review")
        page.keyboard.press("c")   # confirm, from the keyboard
        page.wait_for_selector("#review-message:has-text('Confirmed')", timeout=15_000)
        page.wait_for_selector(f"#history tr:has-text('{first[0]} ↔ {first[1]}'):has-text('confirmed')", timeout=15_000)
        with BrokerClient.from_config(live.config) as bus:
            events = [unpack(bytes(b)) for _, b in bus.since(0, 10000)["events"]]
        verified = [e for e in events if e["type"] == "match.verified"]
        assert [(e["fragment"], e["other"], e["verdict"], e["by"]) for e in verified] == \
            [(first[0], first[1], "confirmed", "A. Conservator")]
        assert verified[0]["pose"]["angle_deg"] == pytest.approx(proposed["angle_deg"] + 1.0, abs=1e-6)
        if "matcher" in live.stages:   # the matcher records it; the page shows the stored history
            recorded = f"#history tr[data-state='recorded']:has-text('{first[0]} ↔ {first[1]}')"
            try:
                page.wait_for_selector(recorded, timeout=120_000)
            except Exception:
                with BrokerClient.from_config(live.config) as bus:
                    parked = [j for j in bus.status()["parked"] if j["service"] == "matcher"]
                raise AssertionError(f"the matcher did not record the verdict; its parked jobs: {parked}")
        # the next pending proposal is up (the matcher may have re-ranked): skip it with S, reject the next with R
        second = page.inner_text("#proposal-title")
        assert second != f"{first[0]} ↔ {first[1]}"
        page.keyboard.press("s")
        assert page.inner_text("#proposal-title") != second
        page.keyboard.press("r")
        page.wait_for_selector("#review-message:has-text('Rejected')", timeout=15_000)
        _shot(page, "review-history")
    finally:
        ctx.close()


def test_status_page_shows_a_failure_and_reruns_it(browser, live):
    from common.bus.client import BrokerClient
    from common.messages import new_message

    with BrokerClient.from_config(live.config) as bus:
        bus.submit(new_message("noop.job", fragment="F0666", fail=True))
    ctx, page = _login(browser, live)
    try:
        page.goto(f"{live.url}/status")
        row = page.wait_for_selector("#parked tr:has-text('F0666')", timeout=60_000)
        assert "asked to fail" in row.inner_text()
        page.wait_for_selector("#services tr[data-service='noop']")
        assert page.locator("#hosts tbody tr").count() >= 1 + len(live.stages)
        _shot(page, "status")
        row.query_selector("button.rerun").click()
        page.wait_for_selector("#status-message:has-text('Re-queued 1 job')", timeout=15_000)
    finally:
        ctx.close()


def test_a_browser_without_the_token_cannot_change_anything(browser, live):
    ctx = browser.new_context()
    page = ctx.new_page()
    try:
        page.goto(f"{live.url}/bench")
        # bench.js shows the notice once it has drawn the page: wait for it, then check both
        page.wait_for_selector("#login-needed", state="visible", timeout=10_000)
        assert page.is_disabled("#scan-button") and page.is_visible("#login-needed")
        codes = page.evaluate("""async () => {
            const out = [];
            for (const [url, body] of [["/api/bench/scan", {fragment: "F0002"}],
                                       ["/api/review/verdict", {proposal: 1, verdict: "confirmed"}],
                                       ["/api/status/rerun", {job: "all"}]]) {
                const r = await fetch(url, {method: "POST", headers: {"Content-Type": "application/json"},
                                            body: JSON.stringify(body)});
                out.push(r.status);
            }
            return out;
        }""")
        assert codes == [401, 401, 401]
    finally:
        ctx.close()


def test_archivist_finds_a_fragment_and_edits_its_metadata_through_the_bus(browser, live):
    from common.bus.client import BrokerClient
    from common.messages import unpack

    target = sorted({a for pair in live.pairs for a in pair})[0]
    ctx, page = _login(browser, live, who="R. Archivist")
    try:
        page.goto(f"{live.url}/fragments")
        # the catalogue is built from storage in the background at start: wait for the seeded fresco
        row = f'#fragments tr[data-fragment="{target}"]'
        page.wait_for_selector(row, timeout=120_000)
        page.wait_for_function(f"() => document.querySelector('{row} img.thumb') && "
                               f"document.querySelector('{row} img.thumb').naturalWidth > 0", timeout=30_000)
        assert page.inner_text(f"{row} td:nth-child(8)").endswith("pending")
        page.click(row)
        page.wait_for_selector(f"#detail-title:has-text('{target}')")
        page.fill("#field-find_spot", "Room 7, east wall")
        page.fill("#field-notes", "blue border, joins the cornice")
        page.click("#save")
        page.wait_for_selector("#history tr[data-state='recorded']:has-text('Room 7, east wall')", timeout=30_000)
        assert "R. Archivist" in page.inner_text("#history")
        with BrokerClient.from_config(live.config) as bus:
            events = [unpack(bytes(b)) for _, b in bus.since(0, 10000)["events"]]
        edits = [e for e in events if e["type"] == "fragment.annotated"]
        assert [(e["fragment"], e["changes"], e["by"]) for e in edits] == [
            (target, {"find_spot": "Room 7, east wall", "notes": "blue border, joins the cornice"}, "R. Archivist")]
        # the search finds it by the new find-spot, and only it
        page.fill("#q", "east wall")
        page.click("#search button[type=submit]")
        page.wait_for_function("() => document.querySelectorAll('#fragments tbody tr').length === 1", timeout=15_000)
        assert page.get_attribute("#fragments tbody tr", "data-fragment") == target
        page.fill("#q", "")
        page.click("#search button[type=submit]")
        page.wait_for_function("() => document.querySelectorAll('#fragments tbody tr').length > 1", timeout=15_000)
        page.click(row)
        page.wait_for_selector("#history tr[data-state='recorded']")
        _shot(page, "catalogue")
    finally:
        ctx.close()
    # without the token the edit is refused and nothing reaches the broker
    ctx = browser.new_context()
    page = ctx.new_page()
    try:
        page.goto(f"{live.url}/fragments")
        code = page.evaluate(f"""async () => (await fetch("/api/catalogue/{target}/metadata", {{method: "POST",
            headers: {{"Content-Type": "application/json"}}, body: JSON.stringify({{changes: {{notes: "x"}}}})}})).status""")
        assert code == 401
    finally:
        ctx.close()


def test_a_confirmed_join_is_shown_and_confirmed_again_at_its_corrected_pose(browser, tmp_path):
    """The RePAIR trial, in Chromium against ``tessera web`` (no broker: verdicts wait in the outbox): a confirmed
    proposal opens at the corrected pose kept with its verdict, C keeps that pose; a new correction confirmed is
    then the pose it stands at, the pose controls start again from zero, and C once more keeps it (the correction
    not applied a second time)."""
    import urllib.parse

    from common.matching.proposals import Proposal, ProposalStore
    from common.store import Store

    from .test_web import _two_fragments
    from .viewer_support import WebProcess

    pixel_mm = 25.4 / 200
    proposed = _two_fragments(Store(tmp_path / "storage"), pixel_mm)
    corrected = {"angle_deg": 3.0, "tx_mm": proposed[1] + 6.0, "ty_mm": -5.0}   # the conservator moved B ~8 mm
    with ProposalStore(tmp_path / "storage" / "matches" / "proposals.sqlite") as db:
        (prop,) = db.upsert([Proposal("FA", "FB", 0.9, "m1", angle_deg=proposed[0], tx_mm=proposed[1], ty_mm=proposed[2])])
        db.record_verdict("FA", "FB", "confirmed", by="A. Conservator", pose=corrected, when=time.time() - 60)
    web = WebProcess(tmp_path).start()
    try:
        ctx, page = _login(browser, web, "A. Conservator", "/review?fragment=FB")
        try:
            page.wait_for_selector(f"#queue li.current[data-proposal='{prop.id}']", timeout=30_000)
            assert "kept with the confirmed verdict" in page.inner_text("#proposal-meta")
            # a fragment's list holds decided proposals too, and says so; its order is not the % shown
            assert page.inner_text("#queue-title") == "Proposals of FB"
            assert "mutual proximity" in page.inner_text("#queue-order")
            assert page.get_attribute(f"#queue li[data-proposal='{prop.id}']", "title").startswith("confirmed · probability 90%")

            def joined_src() -> str:
                return urllib.parse.unquote(page.get_attribute("#joined-colour", "src"))

            assert f"at={corrected['angle_deg']:.4f},{corrected['tx_mm']:.4f}" in joined_src()

            def confirm() -> dict:
                """C; the pose the verdict kept, once the page shows the proposal again (at that pose, afresh)."""
                page.wait_for_function("() => !document.getElementById('confirm-button').disabled", timeout=15_000)
                with page.expect_response("**/api/review/verdict") as answer:
                    page.keyboard.press("c")
                page.wait_for_selector("#proposal[aria-busy='false']", timeout=15_000)
                pose = answer.value.json()["sent"]["pose"]
                assert f"at={pose['angle_deg']:.4f},{pose['tx_mm']:.4f},{pose['ty_mm']:.4f}" in joined_src()
                return pose

            assert confirm() == pytest.approx(corrected)   # was the proposed pose: the correction undone
            page.keyboard.press("]")                        # a new correction: B turned 1° more
            page.keyboard.press("]")
            page.wait_for_selector("#pose-adjust:has-text('turned 1.0°')", timeout=5_000)
            again = confirm()
            assert again["angle_deg"] == pytest.approx(corrected["angle_deg"] + 1.0, abs=1e-6)
            page.wait_for_function("() => document.getElementById('pose-adjust').textContent === ''", timeout=5_000)
            assert f"at={again['angle_deg']:.4f}" in joined_src() and "turn_deg=" not in joined_src()
            assert confirm() == pytest.approx(again)       # not turned a second time
        finally:
            ctx.close()
    finally:
        web.stop()


def test_keys_pressed_while_a_verdict_is_sent_apply_in_order_to_the_proposal_then_on_screen(browser, tmp_path):
    """Against ``tessera web`` (no broker: verdicts wait in the outbox), the first verdict's POST held back: the
    conservator turns B 0.5°, presses Y, then S and N before the answer. Once it comes, S skips the proposal the
    queue moved on to, and N rejects the proposal that was on screen when it was pressed (the first, at the pose
    shown: its correction not applied a second time), never the one the page shows by then."""
    from common.matching.proposals import Proposal, ProposalStore
    from common.rgbn.image import load_rgbn, save_rgbn
    from common.store import Store

    from .test_web import _two_fragments
    from .viewer_support import WebProcess

    store = Store(tmp_path / "storage")
    proposed = _two_fragments(store, 25.4 / 200)
    for fid, src in (("FC", "FA"), ("FD", "FB")):   # two more pieces: copies are enough to be reviewed
        rgbn = load_rgbn(store, f"fragments/{src}/rgbn/front-{src[1].lower() * 4}.h5")
        save_rgbn(store, f"fragments/{fid}/rgbn/front-{fid[1].lower() * 4}.h5", rgbn)
    with ProposalStore(tmp_path / "storage" / "matches" / "proposals.sqlite") as db:
        db.upsert([Proposal("FA", "FB", 0.9, "m1", angle_deg=proposed[0], tx_mm=proposed[1], ty_mm=proposed[2]),
                   Proposal("FA", "FC", 0.8, "m1", angle_deg=10.0, tx_mm=5.0, ty_mm=1.0),
                   Proposal("FB", "FD", 0.7, "m1", angle_deg=-10.0, tx_mm=4.0, ty_mm=-1.0)])
    web = WebProcess(tmp_path).start()
    try:
        ctx, page = _login(browser, web, "A. Conservator", "/review")
        try:
            page.wait_for_selector("#queue li.current", timeout=30_000)
            order = [(li.get_attribute("data-proposal"), li.inner_text().split("\n")[0])
                     for li in page.locator("#queue li").all()]
            assert len(order) == 3 and page.inner_text("#proposal-title") == order[0][1]
            first, third = int(order[0][0]), order[2][1]

            held, sent, answers = [], [], []

            def hold_first(route):
                sent.append(route.request.post_data_json)
                if len(sent) == 1:
                    held.append(route)   # answered below, after the keys
                else:
                    route.continue_()

            page.route("**/api/review/verdict", hold_first)
            page.on("response", lambda r: answers.append(r.json()) if r.url.endswith("/api/review/verdict") else None)

            def until(cond, what: str, timeout_s: float = 15.0) -> None:
                deadline = time.monotonic() + timeout_s
                while not cond():
                    assert time.monotonic() < deadline, f"timed out waiting for {what}: sent {sent}"
                    page.wait_for_timeout(50)

            page.keyboard.press("]")
            page.wait_for_selector("#pose-adjust:has-text('turned 0.5°')", timeout=5_000)
            page.wait_for_function("() => !document.getElementById('confirm-button').disabled", timeout=15_000)
            page.keyboard.press("y")
            until(lambda: held, "the first verdict's request")
            page.keyboard.press("s")
            page.keyboard.press("n")
            page.wait_for_timeout(500)               # time for the page to act on them, were it to act at once
            assert len(sent) == 1
            held[0].continue_()
            until(lambda: len(answers) == 2, "both verdicts' answers")
            page.wait_for_selector("#proposal[aria-busy='false']", timeout=15_000)
            page.wait_for_timeout(500)               # nothing more is sent
            assert [(s["proposal"], s["verdict"]) for s in sent] == [(first, "confirmed"), (first, "rejected")]
            poses = [a["sent"]["pose"] for a in answers]
            assert poses[0]["angle_deg"] == pytest.approx(proposed[0] + 0.5, abs=1e-6)   # the correction shown
            assert poses[1] == pytest.approx(poses[0])   # N kept the pose on screen: not turned a second time
            page.wait_for_function(f"() => document.getElementById('proposal-title').textContent === {json.dumps(third)}",
                                   timeout=15_000)   # Y moved on to the second, S skipped it; N's verdict left it there
        finally:
            ctx.close()
    finally:
        web.stop()
