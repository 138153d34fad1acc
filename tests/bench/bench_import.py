"""Benchmark of ``tessera import images`` on real fragment collections (issue 16).

Run ``python3 tests/bench/bench_import.py`` (needs ``../shared/data``). Prints, with wall and CPU
time (the machine is shared: CPU time is the figure to compare):

* plain-background masks on RePAIR (``repair-dev``: 2000x2000 RGBA, alpha removed, black
  background) against alpha > 50 %: IoU median and minimum, CPU s per picture;
* ``tessera import images`` of the DAFNE fragments (328 RGBA cut-outs) into a fresh store, then
  the same again (everything already imported: the ledger).
"""

from __future__ import annotations

import glob
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))
DATA = REPO.parent / "shared" / "data"


def _children_cpu() -> float:
    import resource
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def repair_plain_iou() -> None:
    import cv2

    from common.imports.fragments import fragment_from_image
    paths = sorted(glob.glob(str(DATA / "repair-dev" / "*" / "*.png")))
    if not paths:
        print("repair-dev not present: skipped")
        return
    ious, cpu = [], 0.0
    for p in paths:
        rgba = cv2.imread(p, cv2.IMREAD_UNCHANGED)[..., [2, 1, 0, 3]]
        truth = rgba[..., 3] > 127
        t = time.process_time()
        frag = fragment_from_image(rgba[..., :3], dpi=187.2, background="plain")
        cpu += time.process_time() - t
        ious.append((frag.mask & truth).sum() / (frag.mask | truth).sum())
    print(f"repair-dev plain background vs alpha > 50 %: {len(ious)} fragments, IoU median {np.median(ious):.3f}, "
          f"min {np.min(ious):.3f}; {cpu / len(ious):.2f} CPU s per 2000x2000 picture")


def dafne_import() -> None:
    src = DATA / "dafne-adam" / "fragments"
    if not src.is_dir():
        print("dafne-adam not present: skipped")
        return
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-c", "import sys; from services.cli import main; sys.exit(main())",
               "import", "images", str(src), "--dpi", "50", "--store", str(Path(tmp) / "st")]
        for what in ("first import", "again (ledger)"):
            c0, t0 = _children_cpu(), time.monotonic()
            out = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
            wall, cpu = time.monotonic() - t0, _children_cpu() - c0
            summary = out.stdout.strip().splitlines()[-1] if out.stdout.strip() else out.stderr[-300:]
            print(f"DAFNE {what}: {summary}; wall {wall:.1f} s, CPU {cpu:.1f} s")


if __name__ == "__main__":
    repair_plain_iou()
    dafne_import()
