"""A fragment's faces as files other tools read: normal map, albedo, renders, metadata.

For each face of a fragment on storage (the newest ``tessera.rgbn`` artifact of that face) the
folder ``<out>/<fragment id>/`` receives

* ``<face>-normals.png`` -- 16-bit RGBA PNG, **OpenGL convention**: ``R, G, B = (n + 1) / 2 * 65535``
  with x to the right, y **up** (green grows towards the top of the image), z towards the viewer;
  alpha 65535 on the fragment, 0 elsewhere (and RGB 0). DirectX tools flip green. Only for faces
  with normals (not colour-only ones);
* ``<face>-albedo.png`` -- RGBA PNG, sRGB-encoded albedo (8 or 16 bit), alpha = mask;
* ``<face>-render-<recipe>-<key8>.png`` -- every illustration of the face on storage (bits as drawn);
  ``<key8>``: the first 8 hex digits of the render artifact's key (``renders/<face>-<key>.h5``), so two
  renders of one recipe (other options) do not collide;
* ``metadata.json`` -- id, per face: dpi, pixel size, size, mask area, source artifact (path,
  sha256), the importer's metadata (inventory, find-spot, ...), provenance; the conventions; and, given
  the station's confirmed joins, the fragment's own (:func:`joins_of`: each other fragment's pose in this
  one's frame, who confirmed it and when), so a fragment folder alone keeps the conservator's work.

Every file is encoded in memory first and the free space of ``<out>``'s file system is checked
against their sizes (:func:`common.store.check_free_space`: the sum plus a margin) before anything
is written: a disk too small refuses the export with :class:`~common.store.StorageFull`, naming the
bytes needed and available, and ``<out>`` is left as it was. The folder is then written under a
temporary name and renamed into place, so it is complete or absent.

An export of many fragments (``tessera export --all``) is sized whole first (:func:`size_export`: every
fragment's files encoded, the sum checked the same way) so that a disk too small refuses it before any
fragment is written, instead of part way; the files encoded then are kept in memory up to
:data:`KEEP_ENCODED_BYTES` and written as they are, the others are encoded again when their turn comes.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import os
import secrets
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from common import __version__
from common.store import ArtifactError, Store, check_free_space, storage_error

#: encoded files :func:`size_export` keeps for the writing, so that an export this small is encoded once (larger: the
#: rest twice, to keep the memory an export takes bounded)
KEEP_ENCODED_BYTES = 128 << 20

NORMAL_MAP_CONVENTION = ("16-bit RGBA PNG, OpenGL convention: RGB = (n + 1) / 2 * 65535, x right, y up (green grows "
                         "towards the top row), z towards the viewer; alpha 65535 on the fragment, 0 (and RGB 0) "
                         "outside")


def fragment_ids(store: Store) -> list[str]:
    """Ids of the fragments that have at least one RGBN face on storage, sorted."""
    root = store.root / "fragments"
    if not root.is_dir():
        return []
    return sorted(p.name for p in root.iterdir() if p.is_dir() and any((p / "rgbn").glob("*.h5")))


def _created(path: Path) -> str:
    with contextlib.suppress(OSError, KeyError):
        with h5py.File(path, "r", locking=False) as f:
            return str(f.attrs["created"])
    return ""


def face_order(face: str) -> tuple:
    """Sort key of a fragment's faces wherever they are listed: ``front``, ``back``, then the others by name."""
    return ({"front": 0, "back": 1}.get(face, 2), face)


def latest_faces(store: Store, fragment: str) -> dict[str, str]:
    """``{face: relative path}`` of the newest RGBN artifact of each face of ``fragment``."""
    folder = store.path(f"fragments/{fragment}/rgbn")
    faces: dict[str, tuple[str, str]] = {}
    for p in sorted(folder.glob("*.h5")) if folder.is_dir() else []:
        face = p.name.split("-", 1)[0]
        stamp = (_created(p), p.name)
        if face not in faces or stamp > faces[face][0]:
            faces[face] = (stamp, p.relative_to(store.root).as_posix())
    return {face: rel for face, (_, rel) in sorted(faces.items())}


def joins_of(joins, fragment: str) -> list[dict]:
    """The confirmed joins of ``fragment`` among ``joins``
    (:class:`~common.matching.reconstruction.Join`, B in A's frame), each seen from ``fragment``: ``other``, its
    pose in ``fragment``'s frame (``angle_deg`` in [-180, 180), ``tx_mm``, ``ty_mm``: ``p_fragment = R p_other + t``,
    the convention of docs/messages.md), ``by``, ``time`` (Unix s) and ``proposal``, sorted by ``other``.

    >>> from common.matching.reconstruction import Join
    >>> (j,) = joins_of([Join("A", "B", 90.0, 10.0, 0.0)], "B")    # B turned 90° and 10 mm right of A's origin
    >>> j["other"], j["angle_deg"], round(j["tx_mm"], 6) + 0.0, j["ty_mm"]
    ('A', -90.0, 0.0, 10.0)
    """
    return sorted((join_record(j, fragment) for j in joins if fragment in (j.fragment_a, j.fragment_b)),
                  key=lambda j: j["other"])


def join_record(join, fragment: str) -> dict:
    """One confirmed join (:class:`~common.matching.reconstruction.Join`) seen from ``fragment``, one of its two, as
    an export lists it: ``other``, its pose in ``fragment``'s frame, ``by``, ``time``, ``proposal``
    (:func:`joins_of`)."""
    from common.matching.docking import inverse_pose, wrapped_deg

    pose = (join.angle_deg, join.tx_mm, join.ty_mm)
    if fragment != join.fragment_a:
        pose = inverse_pose(*pose)
    return {"other": join.fragment_b if fragment == join.fragment_a else join.fragment_a,
            "angle_deg": wrapped_deg(pose[0]), "tx_mm": float(pose[1]), "ty_mm": float(pose[2]),
            "by": join.by, "time": join.time, "proposal": join.proposal_id}


def export_fragment(store: Store, fragment: str, out_dir: str | os.PathLike, *, albedo_bits: int = 16,
                    overwrite: bool = False, joins=None) -> Path:
    """Write ``<out_dir>/<fragment>/`` (see the module docstring); return its path.

    Raises ValueError naming the fragment when it has no RGBN face on storage, or when the folder
    exists and ``overwrite`` is False; :class:`~common.store.StorageFull` (nothing written) when
    ``out_dir``'s file system has not the room for the files, or fills up while they are written;
    :class:`~common.store.StorageReadOnly` when it refuses writes.
    """
    _check_destination(Path(out_dir) / fragment, overwrite)   # before the encoding, which is the long part
    return write_fragment(out_dir, fragment, encode_fragment(store, fragment, albedo_bits=albedo_bits, joins=joins),
                          overwrite=overwrite)


def _check_destination(final: Path, overwrite: bool) -> None:
    if final.exists() and not overwrite:
        raise ValueError(f"{final} exists; remove it or pass overwrite (--force)")


def encode_fragment(store: Store, fragment: str, *, albedo_bits: int = 16, joins=None) -> dict[str, bytes]:
    """Every file of a fragment's export folder (see the module docstring), encoded in memory: ``{name: bytes}``.
    ``joins``: the station's confirmed joins (:func:`common.matching.reconstruction.confirmed_joins`); given,
    ``metadata.json`` lists the fragment's (:func:`joins_of`, ``[]`` for none); None: no ``joins`` key (not known).

    Raises ValueError naming the fragment when it has no RGBN face on storage, or for ``albedo_bits`` other
    than 8 or 16.
    """
    from common.render.artifact import load_rendering
    from common.rgbn.image import load_rgbn
    from common.rgbn.io import encode_normal_map, encode_png, linear_to_srgb

    if albedo_bits not in (8, 16):
        raise ValueError(f"albedo_bits must be 8 or 16, got {albedo_bits}")
    faces = latest_faces(store, fragment)
    if not faces:
        raise ValueError(f"fragment {fragment} has no RGBN face under {store.root}/fragments/{fragment}/rgbn")
    meta = {"fragment": fragment, "exported": _dt.datetime.now(_dt.timezone.utc).isoformat(),
            "software_version": __version__,
            "albedo": f"{albedo_bits}-bit RGBA PNG, sRGB-encoded reflectance, alpha = mask", "faces": {}}
    out: dict[str, bytes] = {}
    for face, rel in faces.items():
        ref = store.ref(rel)
        img = load_rgbn(store, ref)
        with store.open(ref) as f:
            prov = store.provenance(f)
        mask = img.mask
        files = []
        if img.normals is not None:
            out[f"{face}-normals.png"] = encode_png(encode_normal_map(img.normals, mask, "opengl"), bits=16,
                                                    alpha=mask.astype(np.float32), dpi=img.dpi)
            files.append(f"{face}-normals.png")
        out[f"{face}-albedo.png"] = encode_png(linear_to_srgb(img.albedo) * mask[..., None], bits=albedo_bits,
                                               alpha=mask.astype(np.float32), dpi=img.dpi)
        files.append(f"{face}-albedo.png")
        renders = store.path(f"fragments/{fragment}/renders")
        for rp in sorted(renders.glob(f"{face}-*.h5")) if renders.is_dir() else []:
            try:
                image, alpha, attrs = load_rendering(store, rp.relative_to(store.root).as_posix())
            except ArtifactError:
                continue
            name = f"{face}-render-{attrs.get('recipe', 'render')}-{rp.stem.split('-', 1)[-1][:8]}.png"
            drawn_dpi = attrs.get("dpi") if image.shape[:2] != mask.shape else img.dpi   # a render on another grid
            out[name] = encode_png(image, bits=int(attrs.get("bits", 8)), alpha=alpha,
                                   dpi=float(drawn_dpi) if drawn_dpi else None)
            files.append(name)
        user = img.attrs.get("metadata")
        user = json.loads(user) if isinstance(user, (str, bytes)) and user else {}
        meta["faces"][face] = {
            "artifact": ref.to_dict(), "dpi": img.dpi, "pixel_mm": img.pixel_mm,
            "size_px": [int(mask.shape[1]), int(mask.shape[0])], "mask_px": int(mask.sum()),
            "area_mm2": float(mask.sum() * img.pixel_mm ** 2), "has_normals": img.normals is not None,
            "metadata": user, "provenance": prov, "files": files}
        del img
    if joins is not None:
        meta["joins"] = joins_of(joins, fragment)
    if any(f["has_normals"] for f in meta["faces"].values()):   # a colour-only fragment has no normal map to describe
        meta["normal_map"] = NORMAL_MAP_CONVENTION
    out["metadata.json"] = (json.dumps(meta, indent=2, sort_keys=True, default=str, ensure_ascii=False)
                            + "\n").encode("utf-8")
    return out


def write_fragment(out_dir: str | os.PathLike, fragment: str, files: dict[str, bytes], *,
                   overwrite: bool = False) -> Path:
    """Write ``files`` (:func:`encode_fragment`'s) as ``<out_dir>/<fragment>/``, complete or absent; return its path.

    The free space is checked against their sizes first (:func:`common.store.check_free_space`); raises like
    :func:`export_fragment`.
    """
    out_dir = Path(out_dir)
    final = out_dir / fragment
    _check_destination(final, overwrite)
    check_free_space(out_dir, sum(len(b) for b in files.values()), f"the export of {fragment} ({len(files)} files)")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
        tmp = _temporary_folder(out_dir, fragment)
    except OSError as exc:
        raise storage_error(exc, str(final)) from exc
    try:
        _write_folder(tmp, files)
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
    except BaseException as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        if isinstance(exc, OSError):   # a full or read-only disk is said as such (StorageFull / StorageReadOnly)
            raise storage_error(exc, str(final)) from exc
        raise
    return final


@dataclass
class ExportSize:
    """What :func:`size_export` found: the bytes of each fragment's files, those files for the fragments kept
    (``kept``: name -> bytes per fragment), and the fragments that cannot be exported, with why."""
    sizes: dict[str, int] = field(default_factory=dict)
    kept: dict[str, dict[str, bytes]] = field(default_factory=dict)
    failed: list[tuple[str, str]] = field(default_factory=list)

    @property
    def total(self) -> int:
        return sum(self.sizes.values())


def size_export(store: Store, fragments, out_dir: str | os.PathLike, *, albedo_bits: int = 16,
                overwrite: bool = False, keep_bytes: int | None = None, progress=None, joins=None) -> ExportSize:
    """Size the export of ``fragments`` into ``out_dir`` by encoding every file (:func:`encode_fragment`), writing
    nothing: the whole export's bytes, to check the free space for all of it before the first fragment is written.

    Files are kept for the writing while the kept ones stay under ``keep_bytes`` (default
    :data:`KEEP_ENCODED_BYTES`). A fragment that
    :func:`export_fragment` would refuse (no RGBN face, its folder there without ``overwrite``, unreadable)
    is listed in ``failed`` and not sized. ``progress(i, fragment)`` is called after each.
    """
    keep_bytes = KEEP_ENCODED_BYTES if keep_bytes is None else keep_bytes
    out = ExportSize()
    kept_bytes = 0
    for i, fid in enumerate(fragments):
        try:
            _check_destination(Path(out_dir) / fid, overwrite)
            files = encode_fragment(store, fid, albedo_bits=albedo_bits, joins=joins)
        except (ValueError, OSError) as exc:
            out.failed.append((fid, str(exc)))
        else:
            out.sizes[fid] = sum(len(b) for b in files.values())
            if kept_bytes + out.sizes[fid] <= keep_bytes:
                out.kept[fid] = files
                kept_bytes += out.sizes[fid]
        if progress is not None:
            progress(i + 1, fid)
    return out


def _temporary_folder(out_dir: Path, fragment: str) -> Path:
    """A new folder ``.<fragment>.<random>.tmp`` in ``out_dir``, made with the mode the umask gives (an export is
    for other people and tools: ``tempfile.mkdtemp``'s 0700 kept everyone else out of the folder renamed from it)."""
    while True:
        tmp = out_dir / f".{fragment}.{secrets.token_hex(6)}.tmp"
        try:
            tmp.mkdir()
            return tmp
        except FileExistsError:
            continue


def _write_folder(folder: Path, files: dict[str, bytes]) -> None:
    """Write each ``name: bytes`` of ``files`` into ``folder`` and fsync it (errors surface as OSError)."""
    for name, data in files.items():
        with open(folder / name, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
