"""The artifact store: immutable HDF5 files under one storage root.

Every artifact is written to a temporary name in its final directory, fsynced, then linked to its
final name (which fails if the name exists: two writers racing on one content key never replace
each other's file), so a reader never sees a partial file and no HDF5 file is ever open for writing
by two processes (no SWMR). HDF5 file locking is off by default because it does not work on many NFS/SMB mounts;
atomic rename gives the guarantee instead. A message never carries data, only an
:class:`ArtifactRef` (path relative to the root, sha256, size) that the reader checks.

Every file carries root attributes ``schema``, ``schema_version``, ``created`` (UTC ISO 8601),
``software_version`` and ``provenance`` (JSON: device, calibration, input digests, ...). The layout
is documented in ``docs/storage.md``.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import errno
import hashlib
import io
import json
import os
import re
import shutil
import socket
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Callable, Iterator, Mapping

import h5py

from common import __version__

_CHUNK = 1 << 20


class ArtifactError(Exception):
    """An artifact is missing, truncated, corrupt, of the wrong schema or fails its digest."""


class ArtifactMissing(ArtifactError):
    """An artifact is not (yet) on storage: possibly transient (NFS attribute cache, a share
    remounting), so a worker retries it instead of rejecting the input outright."""


class StorageUnavailable(ArtifactMissing, OSError):
    """The storage root (a mount point, ``create=False``) is not there: nothing can be written."""


class StorageError(OSError):
    """Storage refused a write for a reason of its own, not of the artifact: full or read-only.

    Transient from a worker's point of view (an operator frees space or remounts the share), so
    it is retried with back-off, never counted as a bad input. Nothing is left behind: the
    temporary file is removed, the final name never appears.

    Made as ``StorageFull(errno.ENOSPC, "storage full: ...")``: ``errno`` and ``strerror`` as any
    OSError's, but ``str()`` is the message alone, without OSError's ``[Errno 28]`` prefix, as the
    CLI's and the web's errors quote it (``...: storage full: ...``).
    """

    def __str__(self) -> str:
        return self.strerror if self.strerror is not None else super().__str__()


class StorageFull(StorageError):
    """Not enough free space on the storage (checked before writing, or ENOSPC/EDQUOT while writing)."""


class StorageReadOnly(StorageError):
    """The storage is mounted read-only or refuses writes (EROFS, EACCES/EPERM on the directory)."""


# free space kept in reserve beyond the artifact's own size (file system metadata, other writers)
FREE_SPACE_MARGIN_BYTES = 1 << 20
_FULL_ERRNOS = {errno.ENOSPC, errno.EDQUOT}
_READONLY_ERRNOS = {errno.EROFS, errno.EACCES, errno.EPERM}


def storage_error(exc: OSError, what: str) -> OSError:
    """The :class:`StorageError` an OS error of a write means, or ``exc`` unchanged."""
    if isinstance(exc, StorageError):
        return exc
    if exc.errno in _FULL_ERRNOS:
        return StorageFull(exc.errno, f"storage full: cannot write {what} ({os.strerror(exc.errno)})")
    if exc.errno in _READONLY_ERRNOS:
        return StorageReadOnly(exc.errno, f"storage read-only: cannot write {what} ({os.strerror(exc.errno)})")
    return exc


def check_free_space(directory: str | os.PathLike, nbytes: int, what: str) -> None:
    """Raise :class:`StorageFull` if ``directory``'s file system lacks ``nbytes`` + the margin.

    The one free-space check of the project: artifacts (:func:`write_file`, :meth:`Store.import_file`),
    ``tessera export`` and the archive's downloads call it before writing anything.

    Parameters
    ----------
    directory : path
        Where the bytes will go. It need not exist yet: the file system of its nearest existing
        parent (where it will be made) is asked.
    nbytes : int
        Bytes to be written; :data:`FREE_SPACE_MARGIN_BYTES` more must be free.
    what : str
        What is written, for the message.

    Raises
    ------
    StorageFull
        Naming ``what``, the bytes needed and the bytes available (``shutil.disk_usage(...).free``:
        what an unprivileged writer may use). A file system that does not answer is not checked:
        the write itself will tell.
    """
    probe = Path(directory)
    while not probe.exists() and probe.parent != probe:
        probe = probe.parent
    try:
        free = shutil.disk_usage(probe).free
    except OSError:  # some network file systems do not answer: the write itself will tell
        return
    if free < nbytes + FREE_SPACE_MARGIN_BYTES:
        raise StorageFull(errno.ENOSPC, f"storage full: {what} needs {nbytes} bytes, "
                                        f"{free} free on {directory} (keeping {FREE_SPACE_MARGIN_BYTES} in reserve)")


@dataclass(frozen=True)
class ArtifactRef:
    """Pointer to an artifact: what travels in a message instead of the data.

    Attributes
    ----------
    path : str
        POSIX path relative to the storage root, e.g. ``fragments/F0001/rgbn/front-3fa2c1.h5``.
    sha256 : str
        Hex digest of the whole file.
    bytes : int
        File size in bytes.
    """

    path: str
    sha256: str
    bytes: int

    def to_dict(self) -> dict:
        return {"path": self.path, "sha256": self.sha256, "bytes": self.bytes}

    @classmethod
    def from_dict(cls, d: Mapping) -> "ArtifactRef":
        try:
            return cls(path=str(d["path"]), sha256=str(d["sha256"]), bytes=int(d["bytes"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise ArtifactError(f"malformed artifact pointer {d!r}: needs path, sha256, bytes") from exc


def file_sha256(path: str | os.PathLike) -> str:
    """Hex sha256 of a file, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(_CHUNK), b""):
            h.update(block)
    return h.hexdigest()


def content_key(*parts: str, length: int = 16) -> str:
    """Short stable key from strings (input digests, stage name, stage version).

    Outputs are named by this key so that a re-delivered job writes, or finds, the same file.
    """
    h = hashlib.sha256()
    for p in parts:
        h.update(str(p).encode())
        h.update(b"\0")
    return h.hexdigest()[:length]


def _fsync_dir(path: Path) -> None:
    with contextlib.suppress(OSError):  # some network file systems refuse fsync on a directory
        fd = os.open(path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _host_label() -> str:
    """This machine's name as it appears in temporary file names (dots and odd characters as
    ``_``, so the name splits unambiguously at its dots)."""
    return re.sub(r"[^A-Za-z0-9-]", "_", socket.gethostname()) or "unknown"


# .<final name>.<host>.<pid>.<random>.tmp; older writers used .<final name>.<random>.tmp
_TEMP_NAME = re.compile(r"^\.(?P<final>.+)\.(?P<host>[A-Za-z0-9_-]+)\.(?P<pid>[0-9]+)\.(?P<random>[A-Za-z0-9_]+)\.tmp$")


def _writer_alive(pid: int, written_at: float) -> bool:
    """True if process ``pid`` of this host may still be writing a file last modified at
    ``written_at`` (epoch s). A pid that exists but started after the file was last written is
    a reused pid, not the writer."""
    import psutil
    try:
        started = psutil.Process(pid).create_time()
    except psutil.NoSuchProcess:
        return False
    except (psutil.Error, OSError):  # cannot tell (e.g. access denied): assume alive
        return True
    return started <= written_at + 1.0  # create_time is rounded to clock ticks


# link(2) errors meaning "this file system has no hard links" (FAT, SMB mounts without Unix extensions)
_NO_HARD_LINKS = {errno.EPERM, errno.EOPNOTSUPP, errno.ENOTSUP, errno.ENOSYS}


def _link_into_place(tmp: str, final: Path) -> None:
    """Give the finished ``tmp`` the name ``final`` unless that name exists (:class:`FileExistsError`).

    ``os.replace`` would silently replace the file of a writer that finished first, whose pointer
    may already be announced; a hard link is atomic and refuses a name that is taken.
    """
    try:
        os.link(tmp, final)
    except FileExistsError:
        if not os.path.samefile(tmp, final):  # else NFS lost the reply to a link that worked, and its retry saw it
            raise
    except OSError as exc:
        if exc.errno not in _NO_HARD_LINKS:
            raise
        # no hard links here: check, then rename, as before links were used (a writer finishing
        # between the two is still replaced; such file systems offer nothing better)
        if final.exists():
            raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), str(final)) from None
        os.replace(tmp, final)
        return
    with contextlib.suppress(OSError):  # the artifact is in place; a leftover name is swept later
        os.unlink(tmp)


@contextlib.contextmanager
def atomic_file(final: Path, *, replace: bool = True) -> Iterator[str]:
    """Yield a temporary path beside ``final``; move it into place if the block succeeds.

    The one way the project writes a file that others may read while it is written (artifacts,
    tiles, annotations, exports). :func:`write_file` covers the common case of bytes in memory.

    The temporary name is ``.<final name>.<host>.<pid>.<random>.tmp`` (what
    :meth:`Store.sweep_temporary` looks for: host and pid tell whether its writer is alive); on
    any failure it is removed, so readers only ever see finished files. With ``replace`` the
    temporary is renamed over ``final``; without, it is linked (:func:`_link_into_place`) and a
    ``final`` that appeared meanwhile is kept: :class:`FileExistsError`.
    """
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{final.name}.{_host_label()}.{os.getpid()}.", suffix=".tmp",
                                   dir=final.parent)
    except OSError as exc:
        raise storage_error(exc, str(final)) from exc
    os.close(fd)
    try:
        yield tmp
        if replace:
            os.replace(tmp, final)
        else:
            _link_into_place(tmp, final)
        _fsync_dir(final.parent)
    except BaseException as exc:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(exc, OSError):
            mapped = storage_error(exc, str(final))
            if mapped is not exc:
                raise mapped from exc
        raise


def _write_bytes(path: str, data: bytes) -> None:
    """Write ``data`` to ``path`` with ordinary file I/O and fsync it (errors surface as OSError)."""
    with open(path, "wb") as fh:
        view = memoryview(data)
        while view:
            n = fh.write(view[:_CHUNK])
            view = view[n:]
        fh.flush()
        os.fsync(fh.fileno())


def _umask_mode() -> int:
    """The mode ``open()`` gives a new file: 0666 less the process's umask."""
    umask = os.umask(0)   # the umask can only be read by setting it: set it back at once
    os.umask(umask)
    return 0o666 & ~umask


def write_file(final: str | os.PathLike, data: bytes, *, replace: bool = True, public: bool = False) -> None:
    """Write ``data`` to ``final`` atomically: free space checked, temporary name, fsync, rename.

    Raises :class:`StorageFull` / :class:`StorageReadOnly` / :class:`StorageUnavailable` like
    :meth:`Store.write`, never leaving a partial file behind (an older ``final`` stays as it was);
    without ``replace``, :class:`FileExistsError` if ``final`` exists (see :func:`atomic_file`).

    Parameters
    ----------
    final : path
        The file to write.
    data : bytes
        Its whole content.
    replace : bool
        Replace an existing ``final`` (else :class:`FileExistsError`).
    public : bool
        Give the file the mode the umask allows, as ``open()`` would, for files other people and
        tools read (an export's index, pictures, a reconstruction); else the temporary file's 0600,
        as the store's artifacts.
    """
    final = Path(final)
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise storage_error(exc, str(final)) from exc
    check_free_space(final.parent, len(data), str(final))
    with atomic_file(final, replace=replace) as tmp:
        _write_bytes(tmp, data)
        if public:
            os.chmod(tmp, _umask_mode())


def _copy_verified(source: str | os.PathLike, final: Path, sha256: str) -> None:
    """Copy ``source`` to a new ``final`` if its bytes have digest ``sha256`` (else ArtifactError)."""
    with atomic_file(final, replace=False) as tmp:
        h = hashlib.sha256()
        with open(source, "rb") as src, open(tmp, "wb") as dst:
            for block in iter(lambda: src.read(_CHUNK), b""):
                h.update(block)
                dst.write(block)
            dst.flush()
            os.fsync(dst.fileno())
        if h.hexdigest() != sha256:
            raise ArtifactError(f"{source} has sha256 {h.hexdigest()[:12]}…, expected {sha256[:12]}…: not copied")


class Store:
    """Immutable HDF5 artifacts under ``root``.

    Parameters
    ----------
    root : path
        Storage root: a local directory on one machine, an NFS/SMB mount across machines.
    file_locking : bool
        Pass HDF5 file locking through (False by default: rename-on-close makes it unnecessary,
        and NFS often does not support it).
    create : bool
        Create ``root`` if missing (True). False for a mount point: a missing root then means
        the storage is unreachable (:meth:`available` is False), never a local stand-in directory.
    """

    def __init__(self, root: str | os.PathLike, *, file_locking: bool = False, create: bool = True):
        self.root = Path(root)
        self.file_locking = bool(file_locking)
        self.create = bool(create)
        if create:
            self.root.mkdir(parents=True, exist_ok=True)

    @classmethod
    def from_config(cls, config: Mapping) -> "Store":
        """The station's shared storage as its ``[storage]`` section names it (root, file locking, whether to
        create the root)."""
        st = config["storage"]
        return cls(st["root"], file_locking=st["file_locking"], create=st["create_root"])

    def _check_root(self) -> None:
        # never create a mount point's directories locally: that would hide data from the lab
        if not self.create and not self.root.is_dir():
            raise StorageUnavailable(f"storage root {self.root} is not reachable (not mounted?)")

    def available(self) -> bool:
        """True if the root is a writable directory now (an unmounted or stale NFS share is not)."""
        try:
            return self.root.is_dir() and os.access(self.root, os.W_OK | os.X_OK)
        except OSError:
            return False

    # -- paths -----------------------------------------------------------------------------
    def path(self, relpath: str) -> Path:
        """Absolute path of ``relpath``; refuses paths that escape the root."""
        p = PurePosixPath(relpath)
        if p.is_absolute() or ".." in p.parts or not p.parts:
            raise ArtifactError(f"artifact path {relpath!r} must be relative to the storage root")
        return self.root.joinpath(*p.parts)

    def exists(self, relpath: str) -> bool:
        return self.path(relpath).is_file()

    def ref(self, relpath: str) -> ArtifactRef:
        """Pointer (with digest and size) to an existing artifact."""
        full = self.path(relpath)
        if not full.is_file():
            raise ArtifactMissing(f"artifact {relpath} does not exist under {self.root}")
        return ArtifactRef(relpath, file_sha256(full), full.stat().st_size)

    # -- writing ---------------------------------------------------------------------------
    def write(
        self,
        relpath: str,
        schema: str,
        version: int,
        fill: Callable[[h5py.File], None],
        *,
        provenance: Mapping | None = None,
        overwrite: bool = False,
    ) -> ArtifactRef:
        """Write an artifact atomically and return its pointer.

        ``fill(h5file)`` writes the datasets. If ``relpath`` already exists the artifact is
        immutable: its pointer is returned unchanged (a re-delivered job is harmless), unless
        ``overwrite`` is set (only for files that are not content-keyed, e.g. models). The same
        holds when another writer of the same content key (a job re-dispatched while its first
        worker still runs) finishes first: its file is kept and its pointer returned, digest and
        size read from the disk, since our bytes differ at least in ``created``.

        The HDF5 file is built in memory (libhdf5 never writes to storage: on a full or
        read-only file system it can crash the process instead of failing), then the free
        space is checked and the bytes are written with ordinary file I/O to a temporary name,
        fsynced and linked to the final name (renamed over it with ``overwrite``).

        Raises
        ------
        StorageFull, StorageReadOnly
            The storage refused the write; nothing is left behind (no temporary, no final file).
        StorageUnavailable
            The root of a mount point is not there.
        """
        final = self.path(relpath)
        if final.exists() and not overwrite:
            return self.ref(relpath)
        self._check_root()
        image = io.BytesIO()
        with h5py.File(image, "w") as f:
            f.attrs["schema"] = schema
            f.attrs["schema_version"] = int(version)
            f.attrs["created"] = _dt.datetime.now(_dt.timezone.utc).isoformat()
            f.attrs["software_version"] = __version__
            f.attrs["provenance"] = json.dumps(dict(provenance or {}), default=str, sort_keys=True)
            fill(f)
        data = image.getbuffer()
        try:
            write_file(final, data, replace=overwrite)
        except FileExistsError:
            if not final.is_file():  # not a racing writer's artifact (a file where a folder should be)
                raise
            return self.ref(relpath)
        digest = hashlib.sha256(data).hexdigest()
        return ArtifactRef(relpath, digest, len(data))

    def import_file(self, source: str | os.PathLike, relpath: str, sha256: str) -> ArtifactRef:
        """Copy a finished artifact file (e.g. from a local spool) to ``relpath``, atomically.

        The copy is written to a temporary name, fsynced, checked against ``sha256`` and linked
        to its final name. An existing file is never replaced (artifacts are immutable): with the
        same digest it is kept and its pointer returned (re-running a drain is harmless); with
        another, it is kept too and :class:`ArtifactError` names both digests, because the
        caller's event announces ``sha256`` and would point at bytes that are not there.
        """
        final = self.path(relpath)
        if final.is_file():
            return self._existing(relpath, sha256)
        self._check_root()
        size = os.stat(source).st_size
        try:
            final.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise storage_error(exc, relpath) from exc
        check_free_space(final.parent, size, relpath)
        try:
            _copy_verified(source, final, sha256)
        except FileExistsError:  # another writer finished first: its file stays
            if not final.is_file():
                raise
            return self._existing(relpath, sha256)
        return self.ref(relpath)

    def _existing(self, relpath: str, sha256: str) -> ArtifactRef:
        """Pointer to the artifact already at ``relpath`` if it has digest ``sha256``; else ArtifactError."""
        ref = self.ref(relpath)
        if ref.sha256 != sha256:
            raise ArtifactError(f"artifact {relpath} on storage has sha256 {ref.sha256[:12]}…, the copy to "
                                f"import has {sha256[:12]}…: the existing artifact is kept, never replaced")
        return ref

    # -- reading ---------------------------------------------------------------------------
    @contextlib.contextmanager
    def open(self, ref: ArtifactRef | Mapping | str, *, schema: str | None = None,
             version: int | None = None) -> Iterator[h5py.File]:
        """Open an artifact read-only.

        With an :class:`ArtifactRef` (or its dict) the size and sha256 are checked first; a
        mismatch raises :class:`ArtifactError` naming the file. With ``schema`` the file's
        schema attribute must match; with ``version`` its ``schema_version`` must not be newer
        (a reader understands its own version and older ones).
        """
        if isinstance(ref, Mapping):
            ref = ArtifactRef.from_dict(ref)
        relpath = ref.path if isinstance(ref, ArtifactRef) else str(ref)
        full = self.path(relpath)
        if not full.is_file():
            raise ArtifactMissing(f"artifact {relpath} does not exist under {self.root}")
        if isinstance(ref, ArtifactRef):
            size = full.stat().st_size
            if size != ref.bytes:
                raise ArtifactError(f"artifact {relpath} is {size} bytes, message says {ref.bytes}: truncated or replaced")
            digest = file_sha256(full)
            if digest != ref.sha256:
                raise ArtifactError(f"artifact {relpath} has sha256 {digest[:12]}…, message says {ref.sha256[:12]}…: corrupt or replaced")
        try:
            f = h5py.File(full, "r", locking=self.file_locking)
        except OSError as exc:
            raise ArtifactError(f"artifact {relpath} is not a readable HDF5 file ({exc})") from exc
        try:
            if schema is not None and f.attrs.get("schema") != schema:
                raise ArtifactError(f"artifact {relpath} has schema {f.attrs.get('schema')!r}, expected {schema!r}")
            if version is not None:
                found = f.attrs.get("schema_version", 0)
                try:
                    found = int(found)
                except (TypeError, ValueError):
                    raise ArtifactError(f"artifact {relpath} has schema version {found!r}, not an integer") from None
                if found > int(version):
                    raise ArtifactError(f"artifact {relpath} ({f.attrs.get('schema')}) has schema version {found}; "
                                        f"this reader understands up to {int(version)} (written by a newer Tessera?)")
            yield f
        finally:
            f.close()

    def sweep_temporary(self, older_than_s: float = 3600.0) -> list[str]:
        """Delete temporary files (and export folders) left by writers that died mid-write; return their paths.

        A writer killed between ``mkstemp`` and the rename leaves
        ``.<name>.<host>.<pid>.<random>.tmp`` beside the artifact it never finished. A file
        written from this host whose process is gone (or whose pid now belongs to a process
        started after the file was last written: pid reuse) is removed at once. Files of other
        hosts and old-format names (``.<name>.<random>.tmp``) are removed only when older than
        ``older_than_s``, so a write in progress on another machine of the lab is never touched; so are the
        temporary folders an interrupted export leaves (:func:`common.imports.export.export_fragment`).
        """
        cutoff = time.time() - float(older_than_s)
        host = _host_label()
        removed = []
        for tmp in sorted(self.root.rglob(".*.tmp")):
            with contextlib.suppress(FileNotFoundError):
                if tmp.is_dir():   # an export's folder (``.<id>.<random>.tmp``): no writer to ask, so by age
                    if tmp.stat().st_mtime < cutoff:
                        shutil.rmtree(tmp, ignore_errors=True)
                        removed.append(tmp.relative_to(self.root).as_posix())
                    continue
                if not tmp.is_file():
                    continue
                mtime = tmp.stat().st_mtime
                m = _TEMP_NAME.match(tmp.name)
                dead_here = (m is not None and m["host"] == host and int(m["pid"]) != os.getpid()
                             and not _writer_alive(int(m["pid"]), mtime))
                if dead_here or mtime < cutoff:
                    tmp.unlink()
                    removed.append(tmp.relative_to(self.root).as_posix())
        return removed

    def provenance(self, f: h5py.File) -> dict:
        """The provenance attribute of an open artifact, decoded."""
        return json.loads(f.attrs.get("provenance", "{}"))
