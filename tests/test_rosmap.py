"""Tests of omnitof.io.rosmap (ROS map_server YAML + PGM)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from omnitof.errors import InputError, OutputError
from omnitof.io.rosmap import FREE, OCCUPIED, UNKNOWN, read_ros_map, write_ros_map
from omnitof.types import OccupancyMap


def _map() -> OccupancyMap:
    """A 3 x 4 map: row 0 (lowest y) has an occupied cell at column 0, the top row is unknown."""
    log_odds = np.array(
        [
            [3.0, -3.0, -3.0, 0.2],  # occupied, free, free, in between (p = 0.55)
            [-3.0, 3.0, -3.0, -3.0],
            [0.0, 0.0, 0.0, 0.0],
        ],
        dtype=np.float32,
    )
    known = np.array([[1, 1, 1, 1], [1, 1, 1, 1], [0, 0, 0, 0]], dtype=bool)
    return OccupancyMap(log_odds=log_odds, known=known, resolution=0.05, origin=(-1.25, 2.5))


def _read_pgm_p5(path: Path) -> tuple[int, int, np.ndarray]:
    """Independent minimal P5 parser for the test (header tokens, then raw bytes)."""
    data = path.read_bytes()
    lines = data.split(b"\n")
    tokens = [t for line in lines[:4] if not line.startswith(b"#") for t in line.split()]
    assert tokens[0] == b"P5" and tokens[3] == b"255"
    width, height = int(tokens[1]), int(tokens[2])
    pixels = np.frombuffer(data[-width * height :], dtype=np.uint8).reshape(height, width)
    return width, height, pixels


def test_written_files(tmp_path: Path) -> None:
    yaml_path = tmp_path / "intel.yaml"
    pgm = write_ros_map(yaml_path, _map())
    assert pgm == tmp_path / "intel.pgm"
    meta = yaml.safe_load(yaml_path.read_text())
    assert meta == {
        "image": "intel.pgm",
        "resolution": 0.05,
        "origin": [-1.25, 2.5, 0.0],
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,
        "mode": "trinary",
    }
    width, height, pixels = _read_pgm_p5(pgm)
    assert (width, height) == (4, 3)
    # Image row 0 is the top of the map: the unknown row of the OccupancyMap (its row 2).
    expected = [
        [UNKNOWN] * 4,
        [FREE, OCCUPIED, FREE, FREE],
        [OCCUPIED, FREE, FREE, UNKNOWN],
    ]
    np.testing.assert_array_equal(pixels, expected)
    assert (OCCUPIED, FREE, UNKNOWN) == (0, 254, 205)


def test_round_trip(tmp_path: Path) -> None:
    occ = _map()
    write_ros_map(tmp_path / "m.yaml", occ)
    back = read_ros_map(tmp_path / "m.yaml")
    assert back.resolution == occ.resolution and back.origin == occ.origin
    assert back.extent == occ.extent
    p = occ.probability
    np.testing.assert_array_equal(back.known, occ.known & ((p > 0.65) | (p < 0.196)))
    np.testing.assert_array_equal(back.log_odds > 0, back.known & (p > 0.65))
    np.testing.assert_array_equal(back.log_odds < 0, back.known & (p < 0.196))
    # Writing what was read gives the same image.
    write_ros_map(tmp_path / "again.yaml", back)
    assert (tmp_path / "again.pgm").read_bytes() == (tmp_path / "m.pgm").read_bytes()


def _write_yaml(path: Path, **fields: object) -> None:
    meta: dict[str, object] = {
        "image": "m.pgm",
        "resolution": 0.1,
        "origin": [0.0, 0.0, 0.0],
        "negate": 0,
        "occupied_thresh": 0.65,
        "free_thresh": 0.196,
    }
    meta.update(fields)
    path.write_text(yaml.safe_dump({k: v for k, v in meta.items() if v is not None}))


def test_reads_ascii_p2_with_comments_and_negate(tmp_path: Path) -> None:
    # 2 x 2 image; row 0 is the top. With negate 1, p = value / 255.
    (tmp_path / "m.pgm").write_text("P2\n# a comment\n2 2\n255\n0 255 # end of row\n205 128\n")
    _write_yaml(tmp_path / "m.yaml")
    occ = read_ros_map(tmp_path / "m.yaml")
    # negate 0: 0 -> occupied, 255 -> free, 205 -> unknown, 128 (p = 0.498) -> unknown.
    np.testing.assert_array_equal(occ.known, [[False, False], [True, True]])  # bottom row first
    assert occ.log_odds[1, 0] > 0 and occ.log_odds[1, 1] < 0
    _write_yaml(tmp_path / "m.yaml", negate=1)
    occ = read_ros_map(tmp_path / "m.yaml")
    assert occ.log_odds[1, 0] < 0 and occ.log_odds[1, 1] > 0  # 0 is free, 255 occupied
    assert occ.log_odds[0, 0] > 0  # 205: p = 0.80 > 0.65


@pytest.mark.parametrize(
    "missing", ["image", "resolution", "origin", "negate", "occupied_thresh", "free_thresh"]
)
def test_missing_field_is_named(tmp_path: Path, missing: str) -> None:
    write_ros_map(tmp_path / "m.yaml", _map())
    meta = yaml.safe_load((tmp_path / "m.yaml").read_text())
    del meta[missing]
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(meta))
    with pytest.raises(InputError, match=f"missing field '{missing}'") as info:
        read_ros_map(tmp_path / "m.yaml")
    assert info.value.path == tmp_path / "m.yaml"


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("resolution", -0.05),
        ("resolution", "fine"),
        ("origin", [0.0, 0.0]),
        ("origin", [0.0, 0.0, 0.5]),
        ("negate", 2),
        ("free_thresh", 1.5),
        ("mode", "scale"),
        ("image", 5),
    ],
)
def test_invalid_field_is_named(tmp_path: Path, field: str, value: object) -> None:
    write_ros_map(tmp_path / "m.yaml", _map())
    meta = yaml.safe_load((tmp_path / "m.yaml").read_text())
    meta[field] = value
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(meta))
    with pytest.raises(InputError, match=f"field '{field}'"):
        read_ros_map(tmp_path / "m.yaml")


def test_bad_images(tmp_path: Path) -> None:
    _write_yaml(tmp_path / "m.yaml")
    with pytest.raises(InputError, match="cannot read the map image"):
        read_ros_map(tmp_path / "m.yaml")
    (tmp_path / "m.pgm").write_bytes(b"P6\n1 1\n255\n\x00\x00\x00")
    with pytest.raises(InputError, match="P5 or P2"):
        read_ros_map(tmp_path / "m.yaml")
    (tmp_path / "m.pgm").write_bytes(b"P5\n4 4\n255\n\x00\x00")
    with pytest.raises(InputError, match="truncated"):
        read_ros_map(tmp_path / "m.yaml")


def test_not_yaml_mapping(tmp_path: Path) -> None:
    (tmp_path / "m.yaml").write_text("- just\n- a list\n")
    with pytest.raises(InputError, match="mapping"):
        read_ros_map(tmp_path / "m.yaml")


def test_thresholds_that_would_misread_unknown_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="free_thresh"):
        write_ros_map(tmp_path / "m.yaml", _map(), free_thresh=0.25)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("name", ["rm b: c.yaml", "#rm.yaml", "[rm].yaml", "it's {x}.yaml", "café.yaml"])
def test_any_file_name_round_trips(tmp_path: Path, name: str) -> None:
    # The image name is quoted in the YAML where a plain scalar would be misread.
    pgm = write_ros_map(tmp_path / name, _map())
    assert yaml.safe_load((tmp_path / name).read_text())["image"] == pgm.name
    back = read_ros_map(tmp_path / name)
    assert back.log_odds.shape == (3, 4) and back.origin == (-1.25, 2.5)


def test_yaml_path_ending_in_pgm_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"ends in \.pgm: the YAML would replace the map image"):
        write_ros_map(tmp_path / "a.pgm", _map())
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("folder", ["m.yaml", "m.pgm"])
def test_folder_target_is_refused_before_anything_is_written(tmp_path: Path, folder: str) -> None:
    write_ros_map(tmp_path / "m.yaml", _map())
    (tmp_path / folder).unlink()
    (tmp_path / folder).mkdir()
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()}
    with pytest.raises(OutputError, match=f"{folder}: is a folder"):
        write_ros_map(tmp_path / "m.yaml", _map())
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.is_file()} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.pgm", "m.yaml"]


def test_failed_write_leaves_the_old_pair(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    write_ros_map(tmp_path / "m.yaml", _map())
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    changed = _map()
    changed.log_odds[:] = 3.0

    def broken(*args: object, **kwargs: object) -> str:
        raise OSError(28, "No space left on device")

    # The YAML fails: the new image must not have replaced the old one.
    monkeypatch.setattr("omnitof.io.rosmap._map_yaml", broken)
    with pytest.raises(OSError, match="No space left"):
        write_ros_map(tmp_path / "m.yaml", changed)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def _with(**fields: object) -> OccupancyMap:
    occ = _map()
    return OccupancyMap(**{**vars(occ), **fields})


@pytest.mark.parametrize(
    ("occ", "message"),
    [
        (_with(resolution=float("nan")), "resolution must be a positive finite number, got nan"),
        (_with(resolution=-1.0), "resolution must be a positive finite number, got -1.0"),
        (_with(resolution=0.0), "resolution must be a positive finite number, got 0.0"),
        (_with(origin=(float("inf"), 0.0)), r"origin must be two finite numbers \(x, y\), got \(inf, 0.0\)"),
        (_with(log_odds=np.zeros((0, 0)), known=np.zeros((0, 0), bool)), r"non-empty 2-D grid, got shape \(0, 0\)"),
        (_with(log_odds=np.zeros(4), known=np.zeros(4, bool)), r"non-empty 2-D grid, got shape \(4,\)"),
        (_with(known=np.zeros((2, 2), bool)), r"known must have the shape of log_odds \(3, 4\), got \(2, 2\)"),
    ],
)
def test_maps_the_reader_would_refuse_are_not_written(
    tmp_path: Path, occ: OccupancyMap, message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        write_ros_map(tmp_path / "m.yaml", occ)
    assert list(tmp_path.iterdir()) == []


def test_tiny_and_huge_numbers_round_trip(tmp_path: Path) -> None:
    # repr() writes 1e-05 and 1e+20, which PyYAML reads as strings: the reader takes them as numbers.
    write_ros_map(tmp_path / "m.yaml", _with(resolution=1e-5, origin=(1e20, -2.5e-7)))
    back = read_ros_map(tmp_path / "m.yaml")
    assert back.resolution == 1e-5 and back.origin == (1e20, -2.5e-7)


@pytest.mark.parametrize(("resolution", "x"), [("5e-2", "1e3"), ("'5e-2'", '"1e3"')])
def test_exponent_numbers_are_read_as_numbers(tmp_path: Path, resolution: str, x: str) -> None:
    # As map_server reads them (YAML 1.1 makes 5e-2 a string), quoted or not.
    write_ros_map(tmp_path / "m.yaml", _map())
    text = (tmp_path / "m.yaml").read_text()
    text = text.replace("resolution: 0.05", f"resolution: {resolution}")
    text = text.replace("[-1.25, 2.5, 0.0]", f"[{x}, 0, 0]")
    (tmp_path / "m.yaml").write_text(text)
    back = read_ros_map(tmp_path / "m.yaml")
    assert back.resolution == 0.05 and back.origin == (1000.0, 0.0)


@pytest.mark.parametrize("value", ["fine", "nan", "1e999", 10**400, True])
def test_non_numbers_are_still_refused(tmp_path: Path, value: object) -> None:
    write_ros_map(tmp_path / "m.yaml", _map())
    meta = yaml.safe_load((tmp_path / "m.yaml").read_text())
    meta["resolution"] = value
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(meta))
    with pytest.raises(InputError, match="field 'resolution' must be a finite number, got "):
        read_ros_map(tmp_path / "m.yaml")


def test_contradictory_thresholds_are_refused(tmp_path: Path) -> None:
    (tmp_path / "m.pgm").write_text("P2\n2 1\n255\n0 205\n")
    _write_yaml(tmp_path / "m.yaml", occupied_thresh=0.1, free_thresh=0.9)
    message = (
        r"m.yaml: fields 'free_thresh' \(0.9\) and 'occupied_thresh' \(0.1\): "
        "free_thresh must be below occupied_thresh"
    )
    with pytest.raises(InputError, match=message):
        read_ros_map(tmp_path / "m.yaml")


@pytest.mark.parametrize("log_odds", [float("nan"), float("inf"), 0.0, -2.0])
def test_bad_log_odds_argument_is_refused(tmp_path: Path, log_odds: float) -> None:
    write_ros_map(tmp_path / "m.yaml", _map())
    with pytest.raises(ValueError, match=f"log_odds must be a positive finite number, got {log_odds}"):
        read_ros_map(tmp_path / "m.yaml", log_odds=log_odds)


def test_p2_pixel_beyond_int64_names_the_image(tmp_path: Path) -> None:
    (tmp_path / "m.pgm").write_text("P2\n2 1\n255\n99999999999999999999999 0\n")
    _write_yaml(tmp_path / "m.yaml")
    with pytest.raises(InputError, match=r"m.pgm: a P2 PGM pixel value is too large") as info:
        read_ros_map(tmp_path / "m.yaml")
    assert info.value.path == tmp_path / "m.pgm"
