"""docs/storage.md against the code: every artifact reader refuses a file of a newer schema version
with an error naming it, and the schemas and versions the doc lists are the code's."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import numpy as np
import pytest

from common.store import ArtifactError, Store

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "storage.md"


def _readers():
    """(name, schema module, path the reader accepts, call(store, ref)) of every artifact reader."""
    from common.acquisition import calibration, capture
    from common.features import table
    from common.matching import models
    from common.render import artifact
    from common.rgbn import image
    from common.synth import groundtruth
    from common.web import relight, tiles
    rgbn = "fragments/F1/rgbn/front-0123456789abcdef.h5"
    return [
        ("load_rendering", artifact, "fragments/F1/render/front-k.h5", lambda s, r: artifact.load_rendering(s, r)),
        ("load_rgbn", image, rgbn, lambda s, r: image.load_rgbn(s, r)),
        ("load_features", table, "fragments/F1/features/front-k.h5", lambda s, r: table.load_features(s, r)),
        ("read_scans", capture, "fragments/F1/scans/scans-k.h5", lambda s, r: capture.read_scans(s, r)),
        ("load_calibration", calibration, "calibration/sim/x.h5", lambda s, r: calibration.load_calibration(s, r)),
        ("load_model", models, "models/matcher/m.h5", lambda s, r: models.load_model(s, r)),
        ("load_groundtruth", groundtruth, "synth/wall.h5", lambda s, r: groundtruth.load_groundtruth(s, r)),
        ("tiles.cut_source", image, rgbn, lambda s, r: tiles.cut_source(s, r.path)),
        ("tiles.face_thumbnail", image, rgbn, lambda s, r: tiles.face_thumbnail(s, r.path)),
        ("RelightCache.open_artifact", image, rgbn,
         lambda s, r: relight.RelightCache(s, r.path).open_artifact().__enter__()),
    ]


@pytest.mark.parametrize("name", [r[0] for r in _readers()])
def test_a_file_of_a_newer_schema_version_is_refused_naming_the_versions(tmp_path, name):
    """A newer writer's file was read as if it had this reader's layout (no reader passed its
    version to Store.open): a layout change would be misread or fail with a KeyError."""
    _, module, relpath, read = next(r for r in _readers() if r[0] == name)
    store = Store(tmp_path)
    newer = module.SCHEMA_VERSION + 1
    ref = store.write(relpath, module.SCHEMA, newer, lambda f: f.create_dataset("x", data=np.zeros(3)))
    with pytest.raises(ArtifactError, match=rf"\({re.escape(module.SCHEMA)}\) has schema version {newer}; "
                                            rf"this reader understands up to {module.SCHEMA_VERSION}"):
        read(store, ref)


def test_the_renderer_refuses_a_newer_rgbn_file(tmp_path):
    import logging

    from common.bus.worker import StageContext
    from common.messages import new_message
    from common.rgbn import image
    import services.renderer as renderer
    store = Store(tmp_path)
    ref = store.write("fragments/F1/rgbn/front-k.h5", image.SCHEMA, image.SCHEMA_VERSION + 1,
                      lambda f: f.create_dataset("x", data=np.zeros(3)))
    ctx = StageContext(store=store, config={"archive_tiles": False}, log=logging.getLogger("test"),
                       progress=lambda f, t: None, service="renderer")
    with pytest.raises(ArtifactError, match=f"schema version {image.SCHEMA_VERSION + 1}"):
        renderer.handle(new_message("rgbn.ready", fragment="F1", face="front", artifact=ref), ctx)


# files whose reader cannot be changed yet: keep the list short (empty since load_rendering checks too)
_NO_VERSION_YET: set = set()


def test_every_reader_that_checks_a_schema_also_checks_its_version():
    """``Store.open(ref, schema=...)`` without ``version=`` accepts any newer file: name both."""
    missing = []
    for path in sorted([*(ROOT / "common").rglob("*.py"), *(ROOT / "services").rglob("*.py")]):
        rel = path.relative_to(ROOT).as_posix()
        for node in ast.walk(ast.parse(path.read_text(), rel)):
            if (isinstance(node, ast.Call) and getattr(node.func, "attr", None) == "open"
                    and {k.arg for k in node.keywords} >= {"schema"} and "version" not in {k.arg for k in node.keywords}):
                if rel not in _NO_VERSION_YET:
                    missing.append(f"{rel}:{node.lineno}")
    assert not missing, f"Store.open with a schema but no version: {missing}"


# (file, function) that may open an HDF5 file with h5py.File itself, and why: keep the list short
_PLAIN_H5PY_ALLOWED = {
    ("common/store.py", "write"): "the store itself: its atomic writer",
    ("common/store.py", "open"): "the store itself: the schema and version check",
    ("common/imports/export.py", "_created"): "the root 'created' attribute, to order a face's files by age",
    ("services/cli/render.py", "_load_input"): "a CLI tool opening a file the user names (checks its schema)",
    ("services/cli/features.py", "_read_rgbn_file"): "a CLI tool opening a file the user names",
}


def _plain_h5py_opens(tree: ast.AST):
    """(line, enclosing function or "<module>") of every ``h5py.File(...)`` call and ``from h5py import File``."""
    out = []

    def visit(node, fn):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            fn = node.name
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "File"
                and isinstance(node.func.value, ast.Name) and node.func.value.id == "h5py"):
            out.append((node.lineno, fn))
        if isinstance(node, ast.ImportFrom) and node.module == "h5py" and any(a.name == "File" for a in node.names):
            out.append((node.lineno, "from h5py import File"))
        for child in ast.iter_child_nodes(node):
            visit(child, fn)

    visit(tree, "<module>")
    return out


def test_no_reader_opens_an_artifact_with_a_plain_h5py_file():
    """docs/storage.md: every reader opens a file with its schema and the highest version it understands.
    The catalogue (a face's size, dpi and metadata) and the tile list (a face's normals, a render's recipe)
    read with a plain h5py.File, so a file written by a newer Tessera was read as if understood. Readers go
    through ``Store.open(rel, schema=..., version=...)``; the exceptions are named in _PLAIN_H5PY_ALLOWED."""
    found, seen = [], set()
    for path in sorted([*(ROOT / "common").rglob("*.py"), *(ROOT / "services").rglob("*.py")]):
        rel = path.relative_to(ROOT).as_posix()
        for line, fn in _plain_h5py_opens(ast.parse(path.read_text(), rel)):
            if (rel, fn) in _PLAIN_H5PY_ALLOWED:
                seen.add((rel, fn))
            else:
                found.append(f"{rel}:{line} ({fn})")
    assert not found, f"h5py.File outside Store.open (open through the store with schema and version): {found}"
    assert seen == set(_PLAIN_H5PY_ALLOWED), f"allowed but gone (drop them): {set(_PLAIN_H5PY_ALLOWED) - seen}"


def test_the_schema_table_lists_the_codes_schemas_and_versions():
    from common.acquisition import calibration, capture
    from common.features import table
    from common.matching import models
    from common.render import artifact
    from common.rgbn import image
    from common.synth import groundtruth
    doc = DOC.read_text()
    rows = dict(re.findall(r"^\| `(tessera\.[a-z]+)` \| (\d+) \|", doc, re.M))
    code = {m.SCHEMA: str(m.SCHEMA_VERSION) for m in (calibration, capture, table, models, artifact, image, groundtruth)}
    code["tessera.noop"] = "1"
    assert rows == code
    # the tree at the top names the same schemas
    tree = re.search(r"```\n<root>/\n(.*?)```", doc, re.S).group(1)
    assert set(re.findall(r"tessera\.[a-z]+", tree)) >= set(code) - {"tessera.groundtruth", "tessera.noop"}


def test_the_rgbn_and_scans_layouts_in_the_doc_are_what_the_writers_write(tmp_path):
    """Datasets and attributes named in the schema table's rows are the ones written."""
    from common.acquisition.capture import CaptureResult, Scan, write_scans
    from common.rgbn.image import RGBNImage, save_rgbn
    doc = DOC.read_text()
    store = Store(tmp_path)
    img = RGBNImage(albedo=np.full((4, 5, 3), 0.5), mask=np.ones((4, 5), bool), dpi=300.0,
                    normals=np.dstack([np.zeros((4, 5)), np.zeros((4, 5)), np.ones((4, 5))]),
                    confidence=np.ones((4, 5)), discontinuity=np.zeros((4, 5, 2)), height_mm=np.zeros((4, 5)))
    ref = save_rgbn(store, "fragments/F1/rgbn/front-k.h5", img)
    row = re.search(r"^\| `tessera\.rgbn` .*$", doc, re.M).group(0)
    with store.open(ref) as f:
        for name, ds in f.items():
            assert f"`{name}` ({', '.join(map(str, ('H', 'W') + ds.shape[2:]))})" in row, name
            assert str(ds.dtype) in row, (name, ds.dtype)
        for attr in ("dpi", "pixel_mm", "normal_convention"):
            assert attr in f.attrs and f"`{attr}`" in row
    scans = CaptureResult("F1", "sim", {"front": [Scan(np.zeros((4, 5, 3), np.uint16), 300.0, 0, (0, 0, 1, 1), 16)]},
                          colour_only=True)
    ref = write_scans(store, "F1", scans)
    row = re.search(r"^\| `tessera\.scans` .*$", doc, re.M).group(0)
    with store.open(ref) as f:
        for attr in ("fragment", "device", "calibration", "colour_only"):
            assert attr in f.attrs and f"`{attr}`" in row
        d = f["front"]["scan_0"]
        for attr in d.attrs:
            assert f"`{attr}`" in row, attr
        assert set(f) == {"front", "back"}


def test_the_sane_ranges_the_doc_states_are_common_limits():
    from common import limits
    m = re.search(r"must be ([\d,]+)…([\d,]+) dpi, each image at most (\d+) Mpx, and no side longer than (\d+) m\b",
                  DOC.read_text())
    assert m, "docs/storage.md no longer states the sane ranges in the expected words"
    lo, hi, mpx, metres = (float(g.replace(",", "")) for g in m.groups())
    assert (lo, hi) == limits.DPI_RANGE
    assert mpx * 1e6 == limits.MAX_IMAGE_PIXELS and metres * 1000 == limits.MAX_EXTENT_MM


def test_the_features_artifact_layout_in_docs_features_is_what_save_features_writes(tmp_path):
    from common.features.table import FeatureTable, save_features
    n, m = 3, 5
    t = FeatureTable(values={"a": 1.0}, patch_names=["p"], patch_values=np.zeros((n, 1)),
                     patch_centers_mm=np.zeros((n, 2)), patch_normals=np.zeros((n, 2)), patch_arc_mm=np.zeros(n),
                     patch_kind=np.array(["p10"] * n), patch_coverage=np.ones(n), patch_contour_mm=np.zeros((n, 2)),
                     contour_mm=np.zeros((m, 2)), contour_normals=np.zeros((m, 2)), dpi=300.0, face="front",
                     fragment="F1", work_pixel_mm=0.1, missing_data=[], boundary_names=["b"],
                     boundary_profile=np.zeros((4, 1)), boundary_step_mm=1.0)
    store = Store(tmp_path)
    ref = save_features(store, "fragments/F1/features/front-k.h5", t)
    text = (ROOT / "docs" / "features.md").read_text()
    section = re.search(r"## Artifact `tessera\.features`.*?\n\n(.*?)\n\n", text, re.S).group(1)
    named = set(re.findall(r"`([a-z_]+)", section))
    with store.open(ref) as f:
        assert "faces" in f.attrs and "faces" in named
        g = f["front"]
        written = set(g) | set(g.attrs)
    assert written <= named, f"written but not in docs/features.md: {sorted(written - named)}"
    assert f"schema version {table_version()}" in text


def table_version():
    from common.features.table import SCHEMA_VERSION
    return SCHEMA_VERSION


@pytest.mark.parametrize("table", ["dockings", "dock_hubness"])
def test_the_proposal_store_tables_in_the_doc_are_the_stores(tmp_path, table):
    """The columns and SQLite types docs/storage.md tabulates for the proposal store's ``table`` are, in
    order, those a new store creates."""
    import sqlite3

    from common.matching.proposals import ProposalStore

    text = DOC.read_text()
    section = text[text.index(f"### `{table}`"):]
    section = section[:section.index("\n#", 1)]
    documented = []
    for line in section.splitlines():
        m = re.match(r"\|\s*((?:`\w+`(?:,\s*)?)+)\s*\|\s*(\w+)\s*\|", line)
        if m:
            documented += [(name, m.group(2)) for name in re.findall(r"`(\w+)`", m.group(1))]
    ProposalStore(tmp_path / "p.sqlite").close()
    with sqlite3.connect(tmp_path / "p.sqlite") as db:
        actual = [(r[1], r[2]) for r in db.execute(f"PRAGMA table_info({table})")]
    assert documented == actual
