"""A lab in network namespaces (deploy/multihost.sh): broker on one host, workers on two others, the
scanner on a fourth, storage shared as on NFS, CURVE keys per host; fragments flow end to end over
the veth network, and a program on a lab host without a key is not let in."""

from __future__ import annotations

import collections
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.bus.conftest import wait_for

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "deploy" / "multihost.sh"
pytestmark = pytest.mark.timeout(240)


def _namespaces_usable() -> str:
    if os.geteuid() != 0:
        return "needs root (network namespaces)"
    for tool in ("ip", "unshare", "mount"):
        if shutil.which(tool) is None:
            return f"{tool} not installed"
    probe = f"tsprobe{os.getpid() % 10000}"
    r = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if r.returncode != 0:
        return f"ip netns unavailable: {r.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return ""


class Lab:
    def __init__(self, state: Path):
        self.state = state
        self.opts = ["--prefix", f"t{os.getpid() % 10000}", "--state", str(state), "--net", str(100 + os.getpid() % 150)]
        self.procs: list[subprocess.Popen] = []
        self.env = dict(os.environ, PYTHON=sys.executable)

    def run(self, *args, check=True, timeout=60) -> subprocess.CompletedProcess:
        r = subprocess.run(["bash", str(SCRIPT), *args, *self.opts], capture_output=True, text=True,
                           timeout=timeout, env=self.env)
        if check and r.returncode != 0:
            raise AssertionError(f"multihost.sh {' '.join(args)} failed ({r.returncode}):\n{r.stdout}\n{r.stderr}")
        return r

    def start(self, host: str, *args) -> subprocess.Popen:
        log = open(self.state / f"{host}-{args[0]}-{len(self.procs)}.log", "wb")
        p = subprocess.Popen(["bash", str(SCRIPT), "tessera", host, *args, *self.opts], stdout=log,
                             stderr=subprocess.STDOUT, env=self.env)
        p.log_path = log.name
        self.procs.append(p)
        return p

    def status(self, host: str = "scanner") -> dict | None:
        r = self.run("tessera", host, "status", "--json", check=False, timeout=30)
        return json.loads(r.stdout) if r.returncode == 0 else None

    def python(self, host: str, code: str) -> str:
        return self.run("exec", host, sys.executable, "-c", code).stdout

    def logs(self) -> str:
        return "\n".join(f"--- {Path(p.log_path).name} ---\n{Path(p.log_path).read_text(errors='replace')[-2500:]}"
                         for p in self.procs)


@pytest.fixture
def lab(tmp_path):
    why = _namespaces_usable()
    if why:
        pytest.skip(f"multi-host test skipped: {why}")
    lab = Lab(tmp_path / "lab")
    lab.state.mkdir()
    lab.run("up", "--curve")
    try:
        yield lab
    finally:
        for p in lab.procs:
            if p.poll() is None:
                p.terminate()
        for p in lab.procs:
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                p.kill()
        lab.run("down")
        prefix = lab.opts[1] + "-"
        left = [n for n in os.listdir("/run/netns") if n.startswith(prefix)] if os.path.isdir("/run/netns") else []
        assert not left, f"multihost.sh down left namespaces behind: {left}"


EVENTS_SINCE = """
import json, sys
sys.path.insert(0, {repo!r})
from common.bus.client import BrokerClient
from common.config import load_config
from common.messages import unpack
out, after = [], 0
with BrokerClient.from_config(load_config({cfg!r})) as c:
    while (r := c.since(after, 5000))["events"]:
        out += [unpack(b) for _, b in r["events"]]
        after = r["events"][-1][0]
print(json.dumps(out))
"""


def test_fragments_flow_from_the_bench_through_workers_on_two_hosts(lab):
    cfg = str(lab.state / "hosts" / "scanner" / "lab.toml")  # the bench's own config, with its key
    share = lab.state / "mnt" / "tessera"
    lab.start("broker", "broker")
    wait_for(lambda: lab.status("w1") is not None, 40, "the broker to answer from host w1", interval=0.5)
    # the hosts are separate: the broker is not on w1's loopback, only across the veth network
    probe = lab.python("w1", "import socket; s = socket.socket(); s.settimeout(2); "
                             "print(s.connect_ex(('127.0.0.1', 5555)))")
    assert probe.strip() != "0", "the broker must not be reachable on a worker host's own loopback"
    keyless = lab.run("exec", "w1", "env", f"PYTHONPATH={REPO}", sys.executable, "-c",
                      "import sys; from services.cli import main; sys.exit(main())", "status",
                      "--config", str(lab.state / "lab.toml"), "--set", "client.timeout_s=0.5", check=False)
    assert keyless.returncode != 0 and "did not answer" in keyless.stderr + keyless.stdout, \
        "a program on a lab host without a CURVE key gets no answer"
    for service in ("solver", "features"):
        lab.start("w1", "worker", service)
    for service in ("solver", "renderer", "matcher"):
        lab.start("w2", "worker", service)

    def both_hosts():
        s = lab.status()
        return s if s and len(s["workers"]) == 2 and sum(map(len, s["workers"].values())) == 5 else None
    status = wait_for(both_hosts, 60, "five workers on two hosts", interval=0.5)
    assert set(status["workers"]) == {lab.opts[1] + "-w1", lab.opts[1] + "-w2"}, status["workers"]
    scanner = lab.start("scanner", "scanner", "--count", "2", "--set", "scanner.fragments=2")
    assert scanner.wait(120) == 0, "the bench captured and delivered both fragments\n" + lab.logs()

    def idle():
        s = lab.status()
        # per fragment: 1 solver job, then per face 1 features + 1 renderer + 1 matcher job
        return s and not s["in_flight"] and not any(s["queues"].values()) and s["completed"] >= 2 * (1 + 2 * 3)
    wait_for(idle, 120, "the station to finish both fragments", interval=1.0)
    events = json.loads(lab.python("scanner", EVENTS_SINCE.format(repo=str(REPO), cfg=cfg)))
    seen = collections.defaultdict(collections.Counter)
    for e in events:
        if "fragment" in e:
            seen[e["fragment"]][e["type"]] += 1
    frags = [f for f in seen if seen[f]["fragment.ready"]]
    assert len(frags) == 2, seen
    for f in frags:
        c = seen[f]
        assert c["fragment.ready"] == 1 and c["rgbn.ready"] == 2 and c["features.ready"] == 2 \
            and c["render.ready"] == 2, f"{f}: {dict(c)}"
        assert not c["stage.failed"] and not c["input.rejected"], f"{f}: {dict(c)}\n{lab.logs()}"
    for e in events:  # every announced artifact is on the share, at the size announced
        if "artifact" in e:
            assert (share / e["artifact"]["path"]).stat().st_size == e["artifact"]["bytes"]
    leftovers = [p for p in share.rglob("*") if p.is_file() and (p.name.startswith(".") or ".tmp" in p.name)]
    assert not leftovers, f"temporary files left on the share: {leftovers}"
    assert all(p.poll() is None for p in lab.procs if p is not scanner), lab.logs()
