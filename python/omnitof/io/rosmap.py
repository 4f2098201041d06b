"""Occupancy maps in the ROS map_server format: a YAML description beside a PGM image.

The YAML names the image (relative to the YAML's own directory), the `resolution` (metres per
pixel), the `origin` [x, y, yaw] (the lower-left corner of the lower-left pixel, in metres; yaw
must be 0 here), `negate`, `occupied_thresh`, `free_thresh` and `mode`.

Trinary pixel values, as ROS's map_saver writes them: occupied 0 (black), free 254 (white),
unknown 205 (grey). map_server reads a pixel back as the occupancy probability
p = (255 - value) / 255 (p = value / 255 when negate is 1): occupied if p > occupied_thresh, free if
p < free_thresh, unknown otherwise. Note 205 gives p = 50/255 = 0.19608, just above the usual
free_thresh 0.196, which is why unknown survives a round trip.

Image row 0 is the TOP of the map (the highest y); OccupancyMap row 0 is the lowest y. Both
functions flip the rows at the one place marked below.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from omnitof.errors import InputError, OutputError, dump_yaml, read_problem, read_yaml_mapping
from omnitof.io.atomic import atomic_write
from omnitof.types import OccupancyMap

OCCUPIED, FREE, UNKNOWN = 0, 254, 205

# The probability 205 stands for; thresholds must keep it unknown (see _check_thresholds).
_UNKNOWN_P = (255 - UNKNOWN) / 255.0

# map_server's usual thresholds, which write_ros_map writes into the YAML by default.
DEFAULT_OCCUPIED_THRESH = 0.65
DEFAULT_FREE_THRESH = 0.196

# Log-odds given to cells read from a map: trinary maps carry no confidence, so every occupied or
# free cell gets the same magnitude (2.0 <=> p = 0.88), well clear of the usual thresholds.
DEFAULT_LOG_ODDS = 2.0


# --------------------------------------------------------------------------------------------
# Writing


def write_ros_map(
    yaml_path: str | Path,
    occ: OccupancyMap,
    *,
    occupied_thresh: float = DEFAULT_OCCUPIED_THRESH,
    free_thresh: float = DEFAULT_FREE_THRESH,
) -> Path:
    """Write `occ` as `<stem>.pgm` (binary P5, 8 bit) and the YAML at `yaml_path`, atomically.

    Cells never observed, or with free_thresh <= p <= occupied_thresh, are written as unknown.
    Both files are written in full under temporary names before either is renamed into place,
    the image first, so the YAML never names a missing image and a failure leaves an existing
    pair as it was. Returns the PGM path.

    Raises:
        ValueError: for a `yaml_path` ending in .pgm (the YAML would replace the image), a map
            that `read_ros_map` could not read back (naming the field), or thresholds with which
            map_server would misread the written values.
        OutputError: where the YAML or the PGM path is a folder.
    """
    _check_thresholds(occupied_thresh, free_thresh)
    _check_map(occ)
    yaml_path = Path(yaml_path)
    if yaml_path.suffix.lower() == ".pgm":
        raise ValueError(
            f"yaml_path {str(yaml_path)!r} ends in .pgm: the YAML would replace the map image; "
            "give it a .yaml name"
        )
    pgm_path = yaml_path.with_suffix(".pgm")
    for target in (yaml_path, pgm_path):  # before anything is written
        if target.is_dir():
            raise OutputError(f"{target}: is a folder; a map file cannot replace it")
    pixels = _trinary_pixels(occ, occupied_thresh, free_thresh)
    # The flip: OccupancyMap row 0 is the lowest y, image row 0 the highest y.
    image = pixels[::-1]
    with atomic_write(yaml_path, "w") as yaml_file:
        yaml_file.write(_map_yaml(pgm_path.name, occ, occupied_thresh, free_thresh))
        yaml_file.flush()  # a full disk shows here, before the image is replaced
        with atomic_write(pgm_path, "wb") as pgm_file:
            pgm_file.write(_encode_pgm(image, comment=f"omnitof {occ.resolution:.3f} m/pix"))
    return pgm_path


def _check_map(occ: OccupancyMap) -> None:
    """Refuse what read_ros_map would refuse on reading the files back."""
    shape = np.shape(occ.log_odds)
    if len(shape) != 2 or 0 in shape:
        raise ValueError(f"the map's log_odds must be a non-empty 2-D grid, got shape {shape}")
    if np.shape(occ.known) != shape:
        raise ValueError(f"the map's known must have the shape of log_odds {shape}, got {np.shape(occ.known)}")
    resolution = float(occ.resolution)
    if not (math.isfinite(resolution) and resolution > 0.0):
        raise ValueError(f"the map's resolution must be a positive finite number, got {resolution}")
    origin = np.asarray(occ.origin, dtype=np.float64)
    if origin.shape != (2,) or not np.isfinite(origin).all():
        raise ValueError(f"the map's origin must be two finite numbers (x, y), got {occ.origin}")


def _check_thresholds(occupied_thresh: float, free_thresh: float) -> None:
    # map_server reads 254 as p = 1/255 (must be free), 205 as p = 50/255 (must stay unknown),
    # 0 as p = 1 (must be occupied); other thresholds would change the map on reading.
    if not 1.0 / 255.0 < free_thresh < _UNKNOWN_P:
        raise ValueError(
            f"free_thresh must be in (1/255, 50/255 = {_UNKNOWN_P:.5f}), got {free_thresh}"
        )
    if not _UNKNOWN_P <= occupied_thresh < 1.0:
        raise ValueError(f"occupied_thresh must be in [50/255, 1), got {occupied_thresh}")


def _trinary_pixels(occ: OccupancyMap, occupied_thresh: float, free_thresh: float) -> np.ndarray:
    """Pixel values in OccupancyMap row order (row 0 = lowest y)."""
    p = occ.probability
    known = np.asarray(occ.known, dtype=bool)
    pixels = np.full(p.shape, UNKNOWN, dtype=np.uint8)
    pixels[known & (p > occupied_thresh)] = OCCUPIED
    pixels[known & (p < free_thresh)] = FREE
    return pixels


def _encode_pgm(image: np.ndarray, comment: str = "") -> bytes:
    """A binary (P5) 8-bit PGM, written by hand: the format is a short text header + raw bytes."""
    height, width = image.shape
    header = "P5\n" + (f"# {comment}\n" if comment else "") + f"{width} {height}\n255\n"
    return header.encode("ascii") + np.ascontiguousarray(image, dtype=np.uint8).tobytes()


def _map_yaml(
    image_name: str, occ: OccupancyMap, occupied_thresh: float, free_thresh: float
) -> str:
    x0, y0 = (float(v) for v in occ.origin)
    # repr() of a float round-trips exactly; written by hand to keep map_server's familiar layout.
    # The image name goes through PyYAML, which quotes it where a plain scalar would be misread
    # ('#m.pgm' is a comment, 'a: b.pgm' a mapping).
    return dump_yaml({"image": image_name}, width=1 << 30) + (
        f"resolution: {float(occ.resolution)!r}\n"
        f"origin: [{x0!r}, {y0!r}, 0.0]\n"
        "negate: 0\n"
        f"occupied_thresh: {float(occupied_thresh)!r}\n"
        f"free_thresh: {float(free_thresh)!r}\n"
        "mode: trinary\n"
    )


# --------------------------------------------------------------------------------------------
# Reading


def read_ros_map(yaml_path: str | Path, *, log_odds: float = DEFAULT_LOG_ODDS) -> OccupancyMap:
    """Read a map_server map (YAML + P5 or P2 PGM) in trinary mode.

    Occupied cells get log-odds +`log_odds`, free cells -`log_odds`, both known; unknown cells get
    0 and known = False.

    Raises:
        InputError: naming the YAML and the missing or invalid field (free_thresh must be below
            occupied_thresh), or the image and what is wrong with it.
        ValueError: for a `log_odds` that is not a positive finite number.
    """
    if not (math.isfinite(log_odds) and log_odds > 0.0):
        raise ValueError(f"log_odds must be a positive finite number, got {log_odds}")
    yaml_path = Path(yaml_path)
    meta = _load_yaml(yaml_path)
    resolution = _positive_number(meta, "resolution", yaml_path)
    origin = _origin(meta, yaml_path)
    negate = _negate(meta, yaml_path)
    occupied_thresh = _probability(meta, "occupied_thresh", yaml_path)
    free_thresh = _probability(meta, "free_thresh", yaml_path)
    if free_thresh >= occupied_thresh:
        # A pixel would be both occupied and free (it ends up free: unknown cells become known).
        raise InputError(
            f"fields 'free_thresh' ({free_thresh!r}) and 'occupied_thresh' ({occupied_thresh!r}): "
            "free_thresh must be below occupied_thresh",
            yaml_path,
        )
    _check_mode(meta, yaml_path)
    image_path = _image_path(meta, yaml_path)
    try:
        image, maxval = _decode_pgm(image_path)
    except InputError as exc:  # the image's own problem, and which map description names it
        raise InputError(f"{exc.reason} (the image that {yaml_path} names)", image_path) from None

    p = image.astype(np.float64) / maxval
    if not negate:
        p = 1.0 - p
    # The flip: image row 0 is the highest y, OccupancyMap row 0 the lowest y.
    p = p[::-1]
    occupied = p > occupied_thresh
    free = p < free_thresh
    values = np.zeros(p.shape, dtype=np.float32)
    values[occupied] = log_odds
    values[free] = -log_odds
    return OccupancyMap(
        log_odds=values, known=occupied | free, resolution=resolution, origin=origin
    )


def map_image(yaml_path: str | Path) -> Path:
    """The image file a map description names (relative to the YAML's folder, as map_server
    reads it); InputError naming the YAML where it names none."""
    yaml_path = Path(yaml_path)
    return _image_path(_load_yaml(yaml_path), yaml_path)


def _load_yaml(path: Path) -> dict[str, Any]:
    return read_yaml_mapping(path, "the map description",
                             "a map description must be a YAML mapping with image, resolution, ...")


def _field(meta: dict[str, Any], key: str, path: Path) -> Any:
    if key not in meta:
        raise InputError(f"missing field '{key}'", path)
    return meta[key]


def _number(value: Any, key: str, path: Path) -> float:
    number = math.nan
    # A string too: map_server (yaml-cpp) reads any scalar that spells a number as one, quoted
    # or not, where YAML 1.1 makes 5e-2 a string.
    if isinstance(value, (str, int, float)) and not isinstance(value, bool):
        try:
            number = float(value)
        except (ValueError, OverflowError):  # not a number; an integer beyond float's range
            pass
    if not math.isfinite(number):
        raise InputError(f"field '{key}' must be a finite number, got {value!r}", path)
    return number


def _positive_number(meta: dict[str, Any], key: str, path: Path) -> float:
    value = _number(_field(meta, key, path), key, path)
    if value <= 0:
        raise InputError(f"field '{key}' must be positive, got {value!r}", path)
    return value


def _probability(meta: dict[str, Any], key: str, path: Path) -> float:
    value = _number(_field(meta, key, path), key, path)
    if not 0.0 <= value <= 1.0:
        raise InputError(f"field '{key}' must be in [0, 1], got {value!r}", path)
    return value


def _origin(meta: dict[str, Any], path: Path) -> tuple[float, float]:
    value = _field(meta, "origin", path)
    if not isinstance(value, list) or len(value) != 3:
        raise InputError(f"field 'origin' must be a list [x, y, yaw], got {value!r}", path)
    x, y, yaw = (_number(v, "origin", path) for v in value)
    if yaw != 0.0:
        raise InputError(f"field 'origin': a rotated map (yaw {yaw!r}) is not supported", path)
    return (x, y)


def _negate(meta: dict[str, Any], path: Path) -> bool:
    value = _field(meta, "negate", path)
    if value not in (0, 1) or isinstance(value, float):
        raise InputError(f"field 'negate' must be 0 or 1, got {value!r}", path)
    return bool(value)


def _check_mode(meta: dict[str, Any], path: Path) -> None:
    # map_server's default mode is trinary; the others need alpha channels or raw values.
    mode = meta.get("mode", "trinary")
    if mode != "trinary":
        raise InputError(f"field 'mode': only 'trinary' maps are supported, got {mode!r}", path)


def _image_path(meta: dict[str, Any], path: Path) -> Path:
    value = _field(meta, "image", path)
    if not isinstance(value, str) or not value:
        raise InputError(f"field 'image' must be a file name, got {value!r}", path)
    image = Path(value)
    # As map_server does: a relative image name is relative to the YAML's directory.
    return image if image.is_absolute() else path.parent / image


def _decode_pgm(path: Path) -> tuple[np.ndarray, int]:
    """Read a P5 (binary) or P2 (ASCII) PGM: (image (rows, cols) uint16 in file order, maxval)."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read the map image: {read_problem(exc)}", path) from None
    magic, width, height, maxval, offset = _pgm_header(data, path)
    if magic == b"P5":
        pixels = _p5_pixels(data[offset:], width * height, maxval, path)
    else:
        pixels = _p2_pixels(data[offset:], width * height, path)
    if pixels.size and pixels.max() > maxval:
        raise InputError(f"pixel value {pixels.max()} exceeds the maximum {maxval}", path)
    return pixels.astype(np.uint16).reshape(height, width), maxval


def _pgm_header(data: bytes, path: Path) -> tuple[bytes, int, int, int, int]:
    """(magic, width, height, maxval, offset of the pixel data), skipping '#' comments."""
    tokens: list[bytes] = []
    i = 0
    while len(tokens) < 4:
        while i < len(data) and data[i : i + 1].isspace():
            i += 1
        if i < len(data) and data[i : i + 1] == b"#":
            while i < len(data) and data[i : i + 1] not in (b"\n", b"\r"):
                i += 1
            continue
        start = i
        while i < len(data) and not data[i : i + 1].isspace() and data[i : i + 1] != b"#":
            i += 1
        if start == i:
            raise InputError("truncated PGM header", path)
        tokens.append(data[start:i])
    magic = tokens[0]
    if magic not in (b"P5", b"P2"):
        raise InputError(f"not a greyscale PGM (P5 or P2): magic {magic!r}", path)
    try:
        width, height, maxval = (int(t) for t in tokens[1:])
    except ValueError as exc:
        raise InputError("PGM width, height and maxval must be integers", path) from exc
    if width <= 0 or height <= 0 or not 0 < maxval < 65536:
        raise InputError(f"invalid PGM size {width}x{height} or maxval {maxval}", path)
    # Exactly one whitespace byte separates the header from P5 pixel data.
    return magic, width, height, maxval, i + 1


def _p5_pixels(raw: bytes, count: int, maxval: int, path: Path) -> np.ndarray:
    dtype = np.dtype(">u2") if maxval > 255 else np.dtype(np.uint8)  # 16-bit PGM is big-endian
    if len(raw) < count * dtype.itemsize:
        raise InputError(
            f"PGM pixel data truncated: {len(raw)} bytes for {count} pixels "
            f"of {dtype.itemsize} byte(s)",
            path,
        )
    return np.frombuffer(raw, dtype=dtype, count=count)


def _p2_pixels(raw: bytes, count: int, path: Path) -> np.ndarray:
    text = b"\n".join(line.split(b"#", 1)[0] for line in raw.splitlines())
    try:
        values = np.array(text.split(), dtype=np.int64)
    except ValueError as exc:
        raise InputError("P2 PGM pixels must be integers", path) from exc
    except OverflowError:
        raise InputError("a P2 PGM pixel value is too large (a PGM's maximum is 65535)", path) from None
    if values.size != count:
        raise InputError(f"P2 PGM has {values.size} pixels, expected {count}", path)
    if values.size and values.min() < 0:
        raise InputError("P2 PGM pixels must not be negative", path)
    return values
