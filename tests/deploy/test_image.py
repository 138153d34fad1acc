"""deploy/Dockerfile and deploy/compose.yaml agree: every named volume is mounted where the image has a folder
the tessera user owns (no Docker needed: the two files are read)."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def _named_volume_targets(compose: str) -> set[str]:
    """Container paths of the compose file's named volumes (``- name:/path[:ro]``; ``./file:/path`` binds left out)."""
    declared = set(re.findall(r"^  (\w[\w.-]*):", compose.split("\nvolumes:", 1)[1], re.M))
    targets = set()
    for name, path in re.findall(r"^\s*-\s*([\w.-]+):(/[^:\s]*)", compose, re.M):
        if name in declared:
            targets.add(path)
    return targets


def _folders_owned_by_tessera(dockerfile: str) -> set[str]:
    """Folders the image makes with ``install -d -o tessera ...`` (RUN lines joined at their backslashes)."""
    text = dockerfile.replace("\\\n", " ")
    owned = set()
    for args in re.findall(r"install\s+-d\s+([^&\n]*)", text):
        words = args.split()
        if "-o" in words and words[words.index("-o") + 1] == "tessera":
            owned |= {w for w in words if w.startswith("/")}
    return owned


def _unowned_mount_points(dockerfile: str, compose: str) -> set[str]:
    return _named_volume_targets(compose) - _folders_owned_by_tessera(dockerfile)


def test_every_named_volume_is_mounted_on_a_folder_of_the_tessera_user():
    """The image runs as tessera; a named volume mounted where the image has no folder is made root-owned by
    Docker, and neither storage (/data) nor the broker's journal (/var/lib/tessera/broker) could be written."""
    dockerfile = (REPO / "deploy" / "Dockerfile").read_text()
    compose = (REPO / "deploy" / "compose.yaml").read_text()
    assert "USER tessera" in dockerfile
    assert _named_volume_targets(compose) == {"/data", "/var/lib/tessera/broker"}
    assert not _unowned_mount_points(dockerfile, compose)
