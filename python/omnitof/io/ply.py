"""PLY vertex clouds (the occupied voxels of a 3D map): what MeshLab, CloudCompare, Open3D and
Blender read. Written atomically; read back for tests and for users' own tools."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from omnitof.errors import ConfigError, InputError
from omnitof.io.atomic import atomic_write
from omnitof.types import FLOAT32_MAX


class PlyError(ConfigError, ValueError):
    """Points or colours that cannot be written as a PLY cloud."""


# The ASCII characters at which str.splitlines() (the reader's) ends a header line.
_LINE_BREAKS = "\n\r\x0b\x0c\x1c\x1d\x1e"
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def write_ply(
    path: str | Path,
    points: np.ndarray,
    colors: np.ndarray | None = None,
    *,
    binary: bool = True,
    comment: str = "omnitof occupied voxel centres, metres, world frame (z up)",
) -> None:
    """Write points (N, 3) (and colours (N, 3) uint8 RGB) as a PLY vertex cloud, atomically.

    Format: PLY 1.0, `binary_little_endian` (default) or `ascii`; one `vertex` element with
    float (float32) x, y, z and, with colours, uchar red, green, blue — what MeshLab,
    CloudCompare, Open3D and Blender read.

    Raises:
        PlyError (a ValueError): for what `read_ply` would refuse or misread: points that are
            not finite or lie beyond float32's range (naming the first), colours that are not
            uint8 of the points' shape, a comment that is not one line of ASCII text.
    """
    pts = _points(points)
    if not comment.isascii() or any(c in comment for c in _LINE_BREAKS):
        # A line break would start header lines of its own ('end_header' among them).
        raise PlyError(f"the comment must be one line of ASCII text, got {comment!r}")
    cols = None
    if colors is not None:
        cols = np.asarray(colors)
        if cols.shape != pts.shape:
            raise PlyError(f"colors must have shape {pts.shape}, got {cols.shape}")
        if cols.dtype != np.uint8:
            raise PlyError(f"colors must be uint8 RGB, got {cols.dtype}")
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if cols is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    rows = np.empty(len(pts), dtype=fields)
    for a, name in enumerate("xyz"):
        rows[name] = pts[:, a]
    if cols is not None:
        for a, name in enumerate(("red", "green", "blue")):
            rows[name] = cols[:, a]
    header = [
        "ply",
        f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
        *([f"comment {comment}"] if comment else []),
        f"element vertex {len(pts)}",
        "property float x",
        "property float y",
        "property float z",
    ]
    if cols is not None:
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    header.append("end_header")
    with atomic_write(path, "wb") as handle:
        handle.write(("\n".join(header) + "\n").encode("ascii"))
        if binary:
            handle.write(rows.tobytes())
        else:
            # %.9g: enough digits to give back every float32 exactly.
            table = np.column_stack([rows[n].astype(np.float64) for n in rows.dtype.names or ()])
            fmt = " ".join(["%.9g"] * 3 + (["%d"] * 3 if cols is not None else []))
            if len(table):
                np.savetxt(handle, table, fmt=fmt, newline="\n")


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a PLY vertex cloud (ascii or binary_little_endian, scalar vertex properties, no
    other elements): (points (N, 3) float64, colours (N, 3) uint8 or None). Integer colours are
    0..255; float colours are fractions 0..1, scaled to 0..255.

    Raises:
        InputError: naming the file (and the header line) for anything else: a file that cannot
            be read, a header that is not ASCII or not of this shape or has CRLF line ends, a
            body that does not hold the vertices it declares, coordinates that are not finite,
            colours outside 0..255 (0..1 for float ones).
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as err:
        raise InputError(f"cannot read the PLY file: {err.strerror or err}", path) from None
    if data.startswith(b"ply\r\n"):
        raise InputError(
            "the PLY header's lines end in CRLF (\\r\\n), as Windows writes them; this reader "
            "takes LF (\\n) line ends only",
            path,
        )
    # end_header on a line of its own: a comment may hold the word.
    end = data.find(b"\nend_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise InputError("not a PLY file (no 'ply' magic or 'end_header')", path)
    fmt, count, fields = _header(data[:end], path)
    body = data[end + len(b"\nend_header\n"):]
    names = [f[0] for f in fields]
    dtype = np.dtype(fields)
    if fmt == "binary_little_endian":
        if len(body) < count * dtype.itemsize:
            raise InputError(f"PLY body holds fewer than {count} vertices", path)
        rows = np.frombuffer(body, dtype=dtype, count=count)
        table = {n: rows[n] for n in names}
    else:
        try:
            values = np.array(body.split(), dtype=np.float64)
        except ValueError:
            raise InputError("the PLY body holds something that is not a number", path) from None
        if values.size != count * len(names):
            raise InputError(
                f"PLY body has {values.size} values, expected {count}×{len(names)}", path
            )
        grid = values.reshape(count, len(names))
        if not np.isfinite(grid).all() or not all(
            np.array_equal(grid[:, i].astype(dtype[n]), grid[:, i]) for i, n in enumerate(names)
            if dtype[n].kind in "iu"
        ):
            raise InputError("the PLY body holds a value its property's type cannot hold", path)
        # Through each property's own type, as a binary file would store it.
        with np.errstate(invalid="ignore", over="ignore"):
            table = {n: grid[:, i].astype(dtype[n]) for i, n in enumerate(names)}
    points = np.stack([table[a].astype(np.float64) for a in "xyz"], axis=1).reshape(-1, 3)
    if not np.isfinite(points).all():
        raise InputError("PLY vertex coordinates must be finite", path)
    colors = None
    if {"red", "green", "blue"} <= set(names):
        channels = ("red", "green", "blue")
        rgb = np.stack([table[c] for c in channels], axis=1).astype(np.float64)
        # Float colours are fractions 0..1 (as Blender, CGAL and openFrameworks read them),
        # integer ones 0..255.
        top = np.array([1.0 if dtype[c].kind == "f" else 255.0 for c in channels])
        if rgb.size and (not np.isfinite(rgb).all() or rgb.min() < 0 or (rgb > top).any()):
            raise InputError("PLY colours must lie in 0..255 (0..1 for float properties)", path)
        colors = np.rint(rgb * (255.0 / top)).astype(np.uint8)
    return points, colors


# A PLY header line: "format <f> 1.0", "element vertex <n>", "property <type> <name>".
_MAX_VERTICES = 2**40


def _header(text: bytes, path: Path) -> tuple[str, int, list[tuple[str, str]]]:
    """(format, vertex count, fields) of a PLY header; InputError naming the line."""
    try:
        lines = text.decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise InputError("the PLY header is not ASCII text", path) from None
    fmt, count, fields = None, None, []
    for number, line in enumerate(lines, start=1):
        words = line.split()
        if not words or words[0] in ("ply", "comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) == 3:
            fmt = words[1]
            if fmt not in ("ascii", "binary_little_endian"):
                raise InputError(f"unsupported PLY format {fmt!r}", path, number)
        elif words[0] == "element" and len(words) == 3:
            if words[1] != "vertex" or count is not None:
                raise InputError(
                    f"only one 'vertex' element is supported, got {line!r}", path, number
                )
            if not (words[2].isascii() and words[2].isdigit() and int(words[2]) < _MAX_VERTICES):
                raise InputError(f"the vertex count {words[2]!r} is not a whole number", path, number)
            count = int(words[2])
        elif words[0] == "property":
            if len(words) != 3 or words[1] not in _PLY_TYPES:
                raise InputError(f"unsupported PLY property {line!r}", path, number)
            if words[2] in (f[0] for f in fields):
                raise InputError(f"the property {words[2]!r} appears twice", path, number)
            fields.append((words[2], "<" + _PLY_TYPES[words[1]]))
        else:
            raise InputError(f"unexpected PLY header line {line!r}", path, number)
    if fmt is None or count is None or not {"x", "y", "z"} <= {f[0] for f in fields}:
        raise InputError("PLY header lacks format, vertex count or x/y/z", path)
    return fmt, count, fields


def _points(array: np.ndarray) -> np.ndarray:
    pts = np.ascontiguousarray(array, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise PlyError(f"points must have shape (N, 3), got {pts.shape}")
    bad = np.flatnonzero(~np.isfinite(pts).all(axis=1))
    if bad.size:
        raise PlyError(f"point {bad[0]} is not finite: {pts[bad[0]].tolist()}")
    far = np.flatnonzero((np.abs(pts) > FLOAT32_MAX).any(axis=1))
    if far.size:
        raise PlyError(
            f"point {far[0]} lies beyond float32's range (±{FLOAT32_MAX:.3g}) of PLY float "
            f"coordinates: {pts[far[0]].tolist()}"
        )
    return pts
