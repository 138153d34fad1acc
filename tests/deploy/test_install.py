"""deploy/install.sh: the README's two commands on a new Debian lab machine.

The installer makes a virtual environment (Debian's python3 refuses pip installs into itself,
PEP 668), installs Tessera into it and links /usr/local/bin/tessera to it. The slow test re-runs it
the way a new lab machine does, PATH limited to the system directories so that Debian's own
python3 is the one found, then runs ``tessera station --demo 2``; it re-uses the environment the
README's test command runs in (re-running is an update in place, seconds rather than minutes).
"""

from __future__ import annotations

import os
import re
import shutil
import stat
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "deploy" / "install.sh"
SYSTEM_PATH = "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"
VENV = Path(os.environ.get("TESSERA_VENV", "/opt/tessera/venv"))
LINK = Path("/usr/local/bin/tessera")

debian = pytest.mark.skipif(shutil.which("dpkg-query") is None or shutil.which("apt-get") is None,
                            reason="the installer is for Debian (dpkg-query and apt-get not found)")


def _readme_commands() -> list[str]:
    text = (REPO / "README.md").read_text()
    section = text.split("## Two commands", 1)[1].split("\n## ", 1)[0]
    block = re.search(r"```sh\n(.*?)```", section, re.S).group(1)
    return [line for line in block.splitlines() if line.strip() and not line.lstrip().startswith("#")]


def _lstat(path: Path):
    try:
        st = path.lstat()
    except FileNotFoundError:
        return None
    return st.st_ino, st.st_mode, st.st_mtime_ns, os.readlink(path) if path.is_symlink() else None


def _tree(path: Path) -> list[str]:
    return sorted(str(p.relative_to(path)) for p in path.rglob("*"))


def _fake_checkout(tmp_path: Path) -> Path:
    """deploy/install.sh and pyproject.toml in a directory any user can read (a clone under /root
    cannot be read by `nobody`)."""
    checkout = tmp_path / "checkout"
    (checkout / "deploy").mkdir(parents=True)
    shutil.copy2(SCRIPT, checkout / "deploy" / "install.sh")
    shutil.copy2(REPO / "pyproject.toml", checkout / "pyproject.toml")
    for d in (tmp_path, checkout, checkout / "deploy"):
        d.chmod(0o755)
    return checkout


@pytest.fixture
def open_tmp():
    """A temporary directory every user can traverse (pytest's own is private to its user)."""
    d = Path(tempfile.mkdtemp(prefix="tessera-install-"))
    d.chmod(0o755)
    yield d
    for p in [d, *d.rglob("*")]:
        if p.is_dir() and not p.is_symlink():
            p.chmod(0o755)
    shutil.rmtree(d)


def test_readme_commands_are_what_ci_runs():
    readme = _readme_commands()
    assert len(readme) == 2 and all(line.startswith("bash deploy/install.sh && ") for line in readme), readme
    ci = [line for line in (REPO / ".ci" / "run").read_text().splitlines()
          if line.strip() and not line.lstrip().startswith("#")]
    runs = [line for line in ci if "install.sh" in line or "pytest" in line or line.startswith("tessera")]
    assert runs == readme


def test_unknown_argument_is_refused_by_name():
    r = subprocess.run(["bash", str(SCRIPT), "--bogus"], capture_output=True, text=True, stdin=subprocess.DEVNULL,
                       timeout=30)
    assert r.returncode == 2
    assert "'--bogus'" in r.stderr


@debian
def test_without_root_it_lists_what_it_needs_and_changes_nothing(open_tmp):
    checkout = _fake_checkout(open_tmp)
    target = open_tmp / "target"
    target.mkdir(mode=0o555)
    target.chmod(0o555)  # not writable by an ordinary user (root runs the script as `nobody`)
    venv = target / "tessera" / "venv"
    cmd = ["bash", str(checkout / "deploy" / "install.sh")]
    if os.geteuid() == 0:
        if shutil.which("setpriv") is None:
            pytest.skip("running as root and setpriv (util-linux) is not installed to drop to `nobody`")
        cmd = ["setpriv", "--reuid=nobody", "--regid=nogroup", "--clear-groups", *cmd]
    before = _lstat(LINK)
    r = subprocess.run(cmd, capture_output=True, text=True, stdin=subprocess.DEVNULL, timeout=60,
                       env={"PATH": SYSTEM_PATH, "TESSERA_VENV": str(venv), "HOME": "/"})
    assert r.returncode == 1, r.stdout + r.stderr
    assert "needs root" in r.stderr and "nothing was changed" in r.stderr
    assert f"create or update the virtual environment {venv}" in r.stderr
    if not os.access(LINK.parent, os.W_OK) or os.geteuid() == 0:
        assert f"link {LINK} to {venv}/bin/tessera" in r.stderr
    assert f"sudo bash {checkout}/deploy/install.sh" in r.stderr
    assert _tree(target) == []
    assert _lstat(LINK) == before
    assert "[install]" not in r.stdout  # no step was started


@debian
def test_python_older_than_3_11_first_on_path_is_refused_before_anything(tmp_path):
    checkout = _fake_checkout(tmp_path)
    fakebin = tmp_path / "bin"
    fakebin.mkdir()
    fake = fakebin / "python3"
    fake.write_text("#!/bin/sh\necho 3.9.2\n")  # answers the installer's version probe as Python 3.9.2 would
    fake.chmod(fake.stat().st_mode | stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH)
    venv = tmp_path / "target" / "venv"
    before = _lstat(LINK)
    r = subprocess.run(["bash", str(checkout / "deploy" / "install.sh")], capture_output=True, text=True,
                       stdin=subprocess.DEVNULL, timeout=60,
                       env={"PATH": f"{fakebin}:{SYSTEM_PATH}", "TESSERA_VENV": str(venv), "HOME": "/"})
    assert r.returncode == 1, r.stdout + r.stderr
    assert f"{fake} (the first python3 on PATH) is Python 3.9.2" in r.stderr
    assert "3.11 or newer" in r.stderr
    assert not (tmp_path / "target").exists()
    assert _lstat(LINK) == before


@debian
def test_failed_first_install_leaves_no_environment_and_no_link(tmp_path):
    if os.geteuid() != 0:
        pytest.skip("the installer needs root (it would stop before making the environment)")
    checkout = _fake_checkout(tmp_path)
    (checkout / "pyproject.toml").write_text("[project\nname = \n")  # pip cannot read it: the install fails
    venv = tmp_path / "target" / "venv"
    before = _lstat(LINK)
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH", "PYTHONHOME")}
    r = subprocess.run(["bash", str(checkout / "deploy" / "install.sh")], capture_output=True, text=True,
                       stdin=subprocess.DEVNULL, timeout=600, env=env | {"PATH": SYSTEM_PATH, "TESSERA_VENV": str(venv)})
    assert r.returncode != 0, r.stdout + r.stderr
    assert f"[install] creating {venv}" in r.stdout, r.stdout  # it got as far as making the environment
    assert f"removed the unfinished {venv}" in r.stderr, r.stderr
    assert not venv.exists()
    assert _lstat(LINK) == before


@debian
@pytest.mark.slow
@pytest.mark.timeout(1500)
def test_installer_on_the_system_path_then_station_demo(tmp_path):
    if os.geteuid() != 0:
        pytest.skip("the installer needs root (Debian packages, /opt/tessera, /usr/local/bin)")
    if Path(sys.prefix).resolve() != VENV.resolve():
        pytest.skip(f"runs only under the README's test command ({VENV}/bin/python -m pytest): it re-runs "
                    f"the installer on the environment the tests run in (this Python is {sys.prefix})")
    env = {k: v for k, v in os.environ.items()
           if k not in ("TESSERA_CONFIG", "VIRTUAL_ENV", "PYTHONPATH", "PYTHONHOME")} | {"PATH": SYSTEM_PATH}
    assert shutil.which("python3", path=SYSTEM_PATH) is not None, "no python3 in the system directories"

    r = subprocess.run(["bash", str(SCRIPT)], cwd=REPO, env=env, stdin=subprocess.DEVNULL,
                       capture_output=True, text=True, timeout=1200)
    assert r.returncode == 0, r.stdout + r.stderr
    assert f"[install] updating {VENV}" in r.stdout, r.stdout  # re-used, not made again
    assert os.readlink(LINK) == f"{VENV}/bin/tessera"
    assert Path(shutil.which("tessera", path=SYSTEM_PATH)).resolve() == (VENV / "bin" / "tessera").resolve()

    d = subprocess.run(["tessera", "station", "--demo", "2"], cwd=tmp_path, env=env, stdin=subprocess.DEVNULL,
                       capture_output=True, text=True, timeout=900)
    out = d.stdout + d.stderr
    assert d.returncode == 0, out
    assert "2 of 2 fragments captured; every stage done" in out, out
