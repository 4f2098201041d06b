"""Tests of omnitof.io.rosmap (ROS map_server YAML + PGM)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from omnitof.errors import InputError
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
