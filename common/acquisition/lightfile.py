"""Light files of hand-held flash captures (thesis §3.2): ``.lp`` files and plain direction lists.

Museums hold many captures made for RTI (reflectance transformation imaging). The RTI tools
(RTIBuilder, relight) write the light of every photograph into an ``.lp`` file::

    3
    IMG_0001.JPG 0.403259 0.480808 0.778592
    IMG_0002.JPG 0.0982272 0.163712 0.981606
    IMG_0003.JPG -0.0654826 0.180077 0.98147

The first line is the number of images, then one line per image: the file name and the light
direction (x right, y up, z towards the camera — the same frame as Tessera's normals). Other
sources (the photometric-stereo benchmarks) give plain directions, one ``x y z`` per line,
optionally preceded by the count. Directions are normalised to unit length on reading.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path, PurePath, PureWindowsPath

import numpy as np


@dataclass
class LightSet:
    """Light directions of a capture, optionally with file names and relative intensities.

    Attributes
    ----------
    directions : (N, 3) float64
        Unit light directions (x right, y up, z towards the camera).
    filenames : list of str or None
        Image file name of each light (from an ``.lp`` file), or None for a plain list.
    intensities : (N, 3) float64 or None
        Relative RGB intensity of each light (divide image *i* by row *i*), or None = all equal.
    positions : (N, 3) float64 or None
        Near lights: each light's position in pixels from the image centre (x right, y up, z
        towards the camera; z > 0), when the light file gives positions rather than directions.
        ``directions`` are then the directions seen from the image centre.
    """

    directions: np.ndarray
    filenames: list[str] | None = None
    intensities: np.ndarray | None = None
    positions: np.ndarray | None = None

    def __post_init__(self):
        self.directions = _unit_directions(self.directions, "directions")
        n = len(self.directions)
        if self.filenames is not None and len(self.filenames) != n:
            raise ValueError(f"filenames has {len(self.filenames)} entries for {n} light directions")
        if self.intensities is not None:
            self.intensities = _intensities(self.intensities, n)
        if self.positions is not None:
            pos = np.asarray(self.positions, dtype=np.float64)
            if pos.shape != (n, 3) or not np.all(np.isfinite(pos)):
                raise ValueError(f"positions must be ({n}, 3) and finite, got {pos.shape}")
            if np.any(pos[:, 2] <= 0):
                bad = int(np.argmin(pos[:, 2]))
                raise ValueError(f"light position {bad} = {pos[bad]} is not in front of the object (z must be > 0)")
            self.positions = pos

    def __len__(self) -> int:
        return len(self.directions)

    def order_for(self, paths) -> np.ndarray:
        """Indices of this set's lights matching each image path (by file name).

        Raises ValueError naming the first image that the light file does not list. Without
        file names, the lights are taken in order and the counts must agree.
        """
        paths = [os.fspath(p) for p in paths]
        if self.filenames is None:
            if len(paths) != len(self):
                raise ValueError(f"{len(paths)} images but the light file has {len(self)} directions")
            return np.arange(len(paths))
        index = {}
        for i, name in enumerate(self.filenames):
            index.setdefault(_basename(name).lower(), i)
        order = []
        for p in paths:
            key = _basename(p).lower()
            if key not in index:
                raise ValueError(f"image {p} is not listed in the light file (names: {self.filenames[:3]}...)")
            order.append(index[key])
        return np.asarray(order, dtype=int)

    def subset(self, order) -> "LightSet":
        """The lights at indices ``order`` (see :meth:`order_for`)."""
        order = np.asarray(order, dtype=int)
        return LightSet(self.directions[order],
                        None if self.filenames is None else [self.filenames[i] for i in order],
                        None if self.intensities is None else self.intensities[order],
                        None if self.positions is None else self.positions[order])


def natural_key(name: str) -> list:
    """Sort key of a file name with its digit runs compared as numbers ('img2' before 'img10')."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", _basename(os.fspath(name)))]


def shell_sorted(names) -> bool:
    """True if ``names`` are in plain character order but not in natural order: 1, 10, 11, 2, ...

    That is what a shell glob (``shots/*.jpg``) gives for unpadded numbers; images matched to
    lights by position would then be paired with the wrong lights.
    """
    names = [os.fspath(n) for n in names]
    plain = sorted(names, key=lambda n: _basename(n).lower())
    natural = sorted(names, key=natural_key)
    return names == plain and names != natural


def natural_order(names) -> np.ndarray:
    """Indices that put ``names`` in natural order (:func:`natural_key`)."""
    names = [os.fspath(n) for n in names]
    return np.asarray(sorted(range(len(names)), key=lambda i: natural_key(names[i])), dtype=int)


def _basename(name: str) -> str:
    # .lp files written on Windows carry backslash paths
    return PureWindowsPath(name).name if "\\" in name else PurePath(name).name


def _unit_directions(directions, name: str) -> np.ndarray:
    d = np.asarray(directions, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3 or len(d) == 0:
        raise ValueError(f"{name} must be (N, 3) with N >= 1, got shape {d.shape}")
    if not np.all(np.isfinite(d)):
        raise ValueError(f"{name} contains NaN or infinite values")
    norm = np.linalg.norm(d, axis=1)
    if np.any(norm < 1e-6):
        bad = int(np.argmin(norm))
        raise ValueError(f"{name}[{bad}] = {d[bad]} has (almost) zero length")
    return d / norm[:, None]


def _intensities(values, n: int) -> np.ndarray:
    e = np.asarray(values, dtype=np.float64)
    if e.ndim == 1:
        e = np.repeat(e[:, None], 3, axis=1)
    if e.shape != (n, 3):
        raise ValueError(f"intensities must be ({n},) or ({n}, 3), got {e.shape}")
    if not np.all(np.isfinite(e)) or np.any(e <= 0):
        raise ValueError("intensities must be finite and positive")
    return e


def _numeric_rows(path: Path) -> list[list[str]]:
    rows = []
    with open(path, encoding="utf-8-sig", errors="replace") as fh:
        for line in fh:
            line = line.split("#", 1)[0].strip()
            if line:
                rows.append(line.replace(",", " ").split())
    return rows


def read_lp(path: str | os.PathLike, *, positions: float | None = None) -> LightSet:
    """Read an RTI ``.lp`` light file.

    Parameters
    ----------
    path : path
        File whose first line is the image count and each further line ``filename x y z``
        (file names may contain spaces: the last three fields are the direction).
    positions : float, optional
        The vectors are light positions: kept, times this many pixels per unit, in
        ``LightSet.positions`` (see :func:`read_lights`).

    Returns
    -------
    LightSet
        Unit directions (x right, y up, z towards the camera) with file names.

    Raises
    ------
    ValueError
        If the count is missing or disagrees with the lines, or a line is malformed.

    References
    ----------
    Thesis §3.2; the ``.lp`` format of RTIBuilder (Cultural Heritage Imaging) and relight
    (ISTI-CNR).
    """
    path = Path(path)
    with open(path, encoding="utf-8-sig", errors="replace") as fh:
        lines = [ln.strip() for ln in fh if ln.strip()]
    if not lines:
        raise ValueError(f"light file {path} is empty")
    try:
        count = int(lines[0].split()[0])
    except ValueError:
        raise ValueError(f"light file {path}: first line must be the number of images, got {lines[0]!r}") from None
    body = lines[1:]
    if count <= 0 or len(body) < count:
        raise ValueError(f"light file {path} announces {count} images but has {len(body)} light lines")
    names, dirs = [], []
    for k, line in enumerate(body[:count], start=2):
        tokens = line.split()
        if len(tokens) < 4:
            raise ValueError(f"light file {path} line {k}: expected 'filename x y z', got {line!r}")
        try:
            dirs.append([float(t) for t in tokens[-3:]])
        except ValueError:
            raise ValueError(f"light file {path} line {k}: direction is not three numbers: {line!r}") from None
        names.append(" ".join(tokens[:-3]))
    d = np.asarray(dirs, dtype=np.float64)
    return LightSet(d, names, positions=None if positions is None else d * float(positions))


def read_directions(path: str | os.PathLike, *, positions: float | None = None) -> LightSet:
    """Read a plain light-direction file: ``x y z`` per line, optionally the count first.

    Parameters
    ----------
    path : path
        Text file of directions (x right, y up, z towards the camera); ``#`` starts a comment.
    positions : float, optional
        The vectors are light positions (see :func:`read_lights`).

    Returns
    -------
    LightSet
        Unit directions without file names.
    """
    path = Path(path)
    rows = _numeric_rows(path)
    if rows and len(rows[0]) == 1:
        try:
            count = int(rows[0][0])
        except ValueError:
            raise ValueError(f"direction file {path}: first line {rows[0]!r} is neither a count nor x y z") from None
        rows = rows[1:]
        if count != len(rows):
            raise ValueError(f"direction file {path} announces {count} directions but has {len(rows)}")
    try:
        d = np.asarray([[float(t) for t in r] for r in rows])
    except ValueError as exc:
        raise ValueError(f"direction file {path}: non-numeric entry ({exc})") from None
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"direction file {path}: every line must hold three numbers x y z")
    return LightSet(d, positions=None if positions is None else d.astype(np.float64) * float(positions))


def read_intensities(path: str | os.PathLike) -> np.ndarray:
    """Read per-image light intensities: one value or ``r g b`` per line → (N, 3)."""
    path = Path(path)
    rows = _numeric_rows(path)
    try:
        e = np.asarray([[float(t) for t in r] for r in rows])
    except ValueError as exc:
        raise ValueError(f"intensity file {path}: non-numeric entry ({exc})") from None
    if e.ndim != 2 or e.shape[1] not in (1, 3):
        raise ValueError(f"intensity file {path}: every line must hold 1 or 3 numbers")
    return _intensities(e if e.shape[1] == 3 else e[:, 0], len(e))


def read_lights(path: str | os.PathLike, intensities: str | os.PathLike | None = None, *,
                positions: float | None = None) -> LightSet:
    """Read a light file of either kind (``.lp`` or plain directions), plus optional intensities.

    The kind is told from the content: an ``.lp`` line has a file name before the numbers.

    Parameters
    ----------
    path : path
        The light file.
    intensities : path, optional
        Per-image intensities (:func:`read_intensities`).
    positions : float, optional
        The file's vectors are light *positions* (near lights), not directions, measured from the
        image centre (x right, y up, z towards the camera) in units of which ``positions``
        pixels make one (e.g. ``dpi / 25.4`` for millimetres, 1 for pixels). They are kept in
        ``LightSet.positions`` (pixels); ``directions`` are their unit vectors.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"light file {path} does not exist")
    if positions is not None and not (np.isfinite(positions) and positions > 0):
        raise ValueError(f"positions must be a positive number of pixels per unit, got {positions!r}")
    rows = _numeric_rows(path)
    is_lp = len(rows) > 1 and len(rows[0]) == 1 and len(rows[1]) >= 4
    reader = read_lp if is_lp or path.suffix.lower() == ".lp" else read_directions
    lights = reader(path, positions=positions)
    if intensities is not None:
        lights.intensities = _intensities(read_intensities(intensities), len(lights))
    return lights


def write_lp(path: str | os.PathLike, filenames, directions) -> None:
    """Write an RTI ``.lp`` file (count, then ``filename x y z`` per line)."""
    d = _unit_directions(directions, "directions")
    filenames = [str(f) for f in filenames]
    if len(filenames) != len(d):
        raise ValueError(f"filenames has {len(filenames)} entries for {len(d)} directions")
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(f"{len(d)}\n")
        for name, (x, y, z) in zip(filenames, d):
            fh.write(f"{name} {x:.6f} {y:.6f} {z:.6f}\n")
