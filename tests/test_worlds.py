"""The world files and their loader (omnitof.sim.worlds): schema errors name file and field, the
building's five landmarks hold the paper's Table I distances, every loop is collision-free and
as long as the paper's, and the geometry queries agree with hand-computed answers."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from omnitof.sim.worlds import (
    MIN_CLEARANCE,
    WorldError,
    load_world,
    parse_world,
    world_names,
)

# The paper's Table I ground truth (cm in the paper), metres here, by location number.
TABLE_I = {"1": 2.17, "2": 1.34, "3": 3.06, "4": 12.13, "5": 1.33}
LOOP_LENGTHS = {"corridor1": 118.0, "corridor2": 58.0, "office": 46.0}


def box_room(**extra) -> dict:
    """A 4 m × 3 m room as plain data, for building small worlds in tests."""
    data = {
        "name": "box",
        "ceiling_height": 2.5,
        "walls": [{"points": [[0, 0], [4, 0], [4, 3], [0, 3]], "closed": True}],
    }
    data.update(extra)
    return data


def write(tmp_path: Path, text: str, name: str = "bad.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


# --- the bundled worlds ---------------------------------------------------------------------


def test_the_four_worlds_are_bundled_and_load():
    assert world_names() == ["corridor1", "corridor2", "office", "room"]
    for name in world_names():
        world = load_world(name)
        assert world.name == name
        assert len(world.quads) > 0 and len(world.waypoints) >= 3


@pytest.mark.parametrize("name", ["corridor1", "corridor2"])
def test_building_landmarks_are_the_papers_table_1(name):
    world = load_world(name)
    assert {m.name: m.distance for m in world.landmarks} == TABLE_I
    for mark in world.landmarks:
        # The distance between the two surfaces either side, cast in the plan independently of
        # the number written in the file.
        assert world.landmark_distance(mark) == pytest.approx(mark.distance, abs=1e-9), mark.name


def test_both_corridor_sequences_share_one_building():
    one, two = load_world("corridor1"), load_world("corridor2")
    assert np.array_equal(one.quads, two.quads) and np.array_equal(one.boxes, two.boxes)
    assert not np.array_equal(one.waypoints, two.waypoints)


@pytest.mark.parametrize("name", world_names())
def test_loops_are_collision_free(name):
    world = load_world(name)
    assert world.path_clearance() >= MIN_CLEARANCE - 1e-9


@pytest.mark.parametrize("name", sorted(LOOP_LENGTHS))
def test_loops_are_as_long_as_the_papers(name):
    assert load_world(name).path_length() == pytest.approx(LOOP_LENGTHS[name], rel=0.02)


def test_office_is_broader_than_the_sensor_range():
    world = load_world("office")
    bearings = np.radians(np.arange(0, 360, 1.0))
    beyond = []
    for x, y in world.waypoints:
        ranges = world.horizontal_distance(np.array([x, y]), bearings, height=0.45)
        beyond.append(np.mean(ranges > 7.5))
    # From every waypoint some bearings see nothing within the 7.5 m unambiguous range.
    assert min(beyond) > 0.1


def test_building_has_the_difficult_materials():
    world = load_world("corridor1")
    kinds = {world.materials[m].kind for m in world.quad_materials}
    assert {"matte", "metal", "glass", "grid"} <= kinds
    leaves = [world.materials[m].kind for m, r in zip(world.quad_materials, world.quad_roles) if r == "leaf"]
    assert "metal" in leaves and "glass" in leaves


# --- geometry queries ---------------------------------------------------------------------------


def test_open_doors_let_a_ray_through_and_the_lintel_stops_it():
    world = load_world("corridor1")
    start = np.array([4.5, 1.085])  # south corridor, in front of the vestibule
    # North at 1 m: through the vestibule, the meeting room, the passage and the north corridor
    # (all doorways open) to the outer wall at y = 22.25.
    assert world.horizontal_distance(start, math.pi / 2, 1.0) == pytest.approx(22.25 - 1.085)
    # Above the 2.05 m doorway the wall piece over it stops the ray at y = 2.17.
    assert world.horizontal_distance(start, math.pi / 2, 2.5) == pytest.approx(2.17 - 1.085)


def test_closed_glass_leaf_and_see_through():
    world = load_world("corridor1")
    start = np.array([15.67, 1.085])  # in front of a glazed office door
    assert world.horizontal_distance(start, math.pi / 2, 1.0) == pytest.approx(1.085)
    behind = world.horizontal_distance(start, math.pi / 2, 1.0, see_through=("glass",))
    assert behind == pytest.approx(7.17 - 1.085)  # the office's back wall


def test_open_leaf_stands_perpendicular_to_its_wall():
    world = load_world("corridor1")
    leaves = [q for q, m, r in zip(world.quads, world.quad_materials, world.quad_roles)
              if r == "leaf" and np.allclose(q[:2], [3.9, 2.17])]
    assert len(leaves) == 1
    np.testing.assert_allclose(leaves[0][2:4], [3.9, 2.17 + 1.2], atol=1e-12)


def test_rotated_box_and_heights():
    world = parse_world(box_room(boxes=[
        {"centre": [2.0, 1.5], "size": [1.0, 0.5], "yaw_deg": 90.0, "height": 0.8},
        {"centre": [3.0, 2.5], "size": [0.4, 0.4], "bottom": 1.5, "height": 1.6},
    ]))
    # Turned 90°, the 1 m side runs along y: from x = 0.5 at y = 1.5 the ray meets x = 1.75.
    assert world.horizontal_distance(np.array([0.5, 1.5]), 0.0, 0.5) == pytest.approx(1.25)
    # Above the box the ray reaches the wall at x = 4.
    assert world.horizontal_distance(np.array([0.5, 1.5]), 0.0, 0.9) == pytest.approx(3.5)
    # A box hanging at 1.5–1.6 m appears only in that slice.
    assert len(world.segments_at(1.55)) == len(world.segments_at(0.9)) + 4
    assert len(world.segments_at(0.5)) == 4 + 4


def test_wall_segments_are_the_floor_plan_with_door_gaps():
    world = parse_world(box_room(walls=[{
        "points": [[0, 0], [4, 0]], "doors": [{"at": 2.0, "width": 1.0, "leaf": "wood"}],
    }]))
    np.testing.assert_allclose(world.wall_segments(), [[[0, 0], [1.5, 0]], [[2.5, 0], [4, 0]]])
    roles = sorted(world.quad_roles)
    assert roles == ["leaf", "lintel", "wall", "wall"]


def test_clearance_is_the_distance_to_the_nearest_obstacle():
    world = parse_world(box_room(
        boxes=[{"centre": [2.0, 1.5], "size": [0.4, 0.4], "height": 0.7},
               {"centre": [1.0, 1.0], "size": [0.2, 0.2], "bottom": 1.2, "height": 1.3}],
        path={"waypoints": [[1.0, 0.8], [3.0, 0.8], [3.0, 2.2], [1.0, 2.2]]},
    ))
    # The low box's corner zone: its sides at y = 1.3 and 1.7 are 0.5 m from the legs at
    # y = 0.8 and 2.2; the outer walls are 0.8 m away; the hanging box (bottom 1.2 m) is above
    # the robot and does not count although the path passes under it.
    assert world.path_clearance() == pytest.approx(0.5)
    assert world.path_length() == pytest.approx(6.8)


def test_path_through_a_box_has_no_clearance():
    world = parse_world(box_room(
        boxes=[{"centre": [2.0, 1.5], "size": [0.4, 0.4], "height": 0.7}],
        path={"waypoints": [[1.0, 1.5], [3.0, 1.5], [2.0, 2.5]]},
    ))
    assert world.path_clearance() == 0.0


def test_waypoints_on_the_outline_or_under_a_high_box_are_kept():
    # A table top at 1.2 m is above the robot; the outline itself is inside the world (the
    # drive's clearance check keeps the robot off it).
    world = parse_world(box_room(
        boxes=[{"centre": [2.0, 1.5], "size": [0.4, 0.4], "bottom": 1.2, "height": 1.3}],
        path={"waypoints": [[2.0, 1.5], [4.0, 1.5], [0.0, 3.0]]},
    ))
    np.testing.assert_array_equal(world.waypoints, [[2.0, 1.5], [4.0, 1.5], [0.0, 3.0]])


def test_extends_takes_over_and_replaces_keys(tmp_path):
    write(tmp_path, "name: base\nceiling_height: 2.5\nwalls:\n  - points: [[0, 0], [4, 0]]\n", "_base.yaml")
    child = write(tmp_path, "extends: _base\nname: child\nceiling_height: 3.0\n", "child.yaml")
    world = load_world(child)
    assert (world.name, world.ceiling_height, len(world.quads)) == ("child", 3.0, 1)


def test_extends_a_bundled_world(tmp_path):
    # `extends: office` beside no office.yaml was refused, though a user's variant of a bundled
    # world is what the key is for; a file of that name beside it still comes first.
    bundled = load_world("office")
    variant = load_world(write(tmp_path, "extends: office\nname: my office\nceiling_height: 3.1\n", "mine.yaml"))
    assert (variant.name, variant.ceiling_height) == ("my office", 3.1)
    assert len(variant.quads) == len(bundled.quads) and variant.landmarks == bundled.landmarks
    write(tmp_path, "name: base\nceiling_height: 2.5\nwalls:\n  - points: [[0, 0], [4, 0]]\n", "office.yaml")
    assert len(load_world(tmp_path / "mine.yaml").quads) == 1


# --- the loader refuses bad files -------------------------------------------------------------

BAD_FILES = [
    # (file text, words the message must contain)
    ("name: x\nwalls:\n  - points: [[0, 0], [1, 0]]\n", ["ceiling_height", "Field required"]),
    ("name: x\nceiling_height: 2.5\nwalls:\n  - points: [[0, 0], [1, 0]]\n  - points: [[0, 1], [1, 1]]\n"
     "    material: plaster\n", ["walls[1].material", "unknown material 'plaster'"]),
    ("name: x\nceiling_height: 2.5\nwalls:\n  - points: [[0, 0], [1, 0]]\n    hieght: 2\n",
     ["walls[0].hieght", "Extra inputs"]),
    ("name: x\nceiling_height: 2.5\nwalls:\n  - points: [[0, 0], [3, 0]]\n    doors:\n"
     "      - {at: 2.8, width: 0.9}\n", ["walls[0].doors[0].at", "past the end of edge 0"]),
    ("name: x\nceiling_height: 2.5\nwalls:\n  - points: [[0, 0], [3, 0]]\n    doors:\n"
     "      - {at: 1.0, width: -0.9}\n", ["walls[0].doors[0].width", "greater than 0"]),
    ("name: x\nceiling_height: 2.5\nwalls:\n  - points: [[0, 0], [3, 0]]\n    doors:\n"
     "      - {at: 1.0, width: 0.9}\n      - {at: 1.5, width: 0.9}\n", ["walls[0].doors[1].at", "overlaps"]),
    ("name: x\nceiling_height: 2.5\nwalls:\n  - points: [[0, 0], [3, 0]]\n    height: 3.0\n",
     ["walls[0].height", "above the ceiling"]),
    ("name: x\nceiling_height: 2.5\nmaterials:\n  frosted: {kind: glass, transmission: 0.95, specular: 0.1}\n"
     "walls:\n  - points: [[0, 0], [3, 0]]\n", ["materials.frosted", "must not exceed 1"]),
    ("name: x\nceiling_height: 2.5\nmaterials:\n  foil: {kind: mirror}\nwalls:\n  - points: [[0, 0], [3, 0]]\n",
     ["materials.foil", "kind"]),
    ("name: x\nceiling_height: 2.5\nboxes:\n  - {centre: [1, 1], size: [1, 1], bottom: 1.0, height: 0.5}\n",
     ["boxes[0].height", "above bottom"]),
    ("name: x\nceiling_height: 2.5\nwalls:\n  - points: [[0, 0], [3, nan]]\n", ["walls[0].points[1][1]", "finite"]),
    ("name: x\nceiling_height: 2.5\n", ["walls", "at least one wall or box"]),
    ("name: x\nceiling_height: 2.5\nwalls:\n  - points: [[0, 0], [3, 0]]\npath:\n  waypoints: [[1, 1], [2, 1]]\n"
     "  laps: 1000000000000\n", ["path.laps", "less than or equal to 10000"]),
    ("name: x\nceiling_height: 2.5\nwalls:\n  - points: [[0, 0], [3, 0]]\npath:\n  waypoints: [[1, 1], [1, 1], [2, 1]]\n",
     ["path", "waypoints 0 and 1 are both [1.0, 1.0]: consecutive waypoints must differ"]),
    # Landmarks that the world does not hold were accepted, and Table I showed n/a or a wrong offset.
    ("name: x\nceiling_height: 2.5\nwalls:\n  - {points: [[0, 0], [5, 0], [5, 4], [0, 4]], closed: true}\n"
     "landmarks:\n  - {name: a, position: [2.5, 2], direction_deg: 0, distance: 1.0}\n",
     ["landmarks[0].distance: 1 m, but the walls along its line are 5.000 m apart at 1 m (2.500 + 2.500 m)"]),
    ("name: x\nceiling_height: 2.5\nwalls:\n  - {points: [[0, 0], [5, 0], [5, 4], [0, 4]], closed: true}\n"
     "landmarks:\n  - {name: a, position: [100, 100], direction_deg: 0, distance: 5.0}\n",
     ["landmarks[0].position: (100, 100) lies outside the world"]),
    ("name: x\nceiling_height: 2.5\nwalls:\n  - points: [[0, 0], [5, 0]]\n  - points: [[0, 3], [1, 3]]\n"
     "landmarks:\n  - {name: a, position: [2.5, 0.5], direction_deg: 90, distance: 5.0}\n",
     ["landmarks[0]: no wall along its line at 1 m"]),
    # Laps of an open path were driven once without a word.
    ("name: x\nceiling_height: 2.5\nwalls:\n  - points: [[0, 0], [3, 0]]\npath:\n  waypoints: [[1, 1], [2, 1]]\n"
     "  closed: false\n  laps: 3\n", ["path", "laps: 3 laps of an open path (closed: false) cannot be driven"]),
    ("name: x\nceiling_height: 2.5\nwalls: [[0, 0], [1, 0]\n", ["not valid YAML"]),
    # Paths the drive's clearance check let through: out of a room open to the east, beyond its
    # walls (the robot drove through nowhere), and round a sharp corner whose arc passes 2.7 m
    # from the box around its waypoint.
    ("name: x\nceiling_height: 2.5\nwalls:\n  - points: [[4, 0], [0, 0], [0, 3], [4, 3]]\n"
     "path:\n  waypoints: [[1, 0.75], [6, 0.75], [6, 2.25], [1, 2.25]]\n",
     ["path.waypoints[1]: (6, 0.75) lies outside the world, whose walls and boxes span x 0 .. 4 m, y 0 .. 3 m"]),
    ("name: x\nceiling_height: 2.5\nwalls:\n  - {points: [[0, 0], [20, 0], [20, 10], [0, 10]], closed: true}\n"
     "boxes:\n  - {centre: [18, 5], size: [0.5, 0.5], height: 0.7}\npath:\n  waypoints: [[2, 8], [18, 5], [2, 2]]\n",
     ["path.waypoints[1]: (18, 5) lies inside boxes[0], which reaches below 1 m: the robot cannot pass it"]),
    # A box 1e300 m wide made the path's clearance NaN, and the robot drove through it.
    ("name: x\nceiling_height: 2.5\nboxes:\n  - {centre: [3, 1], size: [1.0e300, 0.2], height: 1}\n",
     ["boxes[0].size[0]", "less than or equal to 100000"]),
    ("name: x\nceiling_height: 2.5\nwalls:\n  - points: [[0, 0], [3, 1e9]]\n", ["walls[0].points[1][1]", "100000"]),
    ("name: x\nceiling_height: 2.5\nambient: 1.0e300\nwalls:\n  - points: [[0, 0], [3, 0]]\n",
     ["ambient", "less than or equal to 10000"]),
]


@pytest.mark.parametrize("text, words", BAD_FILES)
def test_bad_files_are_refused_naming_file_and_field(tmp_path, text, words):
    path = write(tmp_path, text)
    with pytest.raises(WorldError) as err:
        load_world(path)
    message = str(err.value)
    assert message.startswith(str(path)), message
    for word in words:
        assert word in message, message


def test_yaml_syntax_errors_name_the_line(tmp_path):
    path = write(tmp_path, "name: x\nceiling_height: 2.5\nwalls: [[0, 0], [1, 0]\n")
    with pytest.raises(WorldError) as err:
        load_world(path)
    assert err.value.line is not None and str(err.value).startswith(f"{path}:{err.value.line}:")


def test_unknown_world_names_list_the_known_ones(tmp_path, monkeypatch):
    with pytest.raises(WorldError, match="no bundled world 'kitchen'.*corridor1, corridor2, office, room"):
        load_world("kitchen")
    # A name that is no bundled world but a folder or another file here says what it is.
    monkeypatch.chdir(tmp_path)
    (tmp_path / "worlds").mkdir()
    (tmp_path / "plan.png").write_bytes(b"\x89PNG")
    with pytest.raises(WorldError, match="'worlds' is a folder: give a world file"):
        load_world("worlds")
    with pytest.raises(WorldError, match="'plan.png' is not a world file"):
        load_world("plan.png")


def test_extends_cycles_and_missing_bases_are_refused(tmp_path):
    write(tmp_path, "extends: b\nname: a\nceiling_height: 2\n", "a.yaml")
    write(tmp_path, "extends: a\nname: b\n", "b.yaml")
    with pytest.raises(WorldError, match="cycle"):
        load_world(tmp_path / "a.yaml")
    lonely = write(tmp_path, "extends: nowhere\nname: c\n", "c.yaml")
    with pytest.raises(WorldError, match="extends: no world file 'nowhere.yaml' beside this one, nor a bundled world "
                                         r"of that name \(corridor1, corridor2, office, room\)"):
        load_world(lonely)


def test_a_folder_or_a_missing_file_is_named_as_such(tmp_path):
    with pytest.raises(WorldError, match="a folder, not a world file"):
        load_world(tmp_path)
    with pytest.raises(WorldError, match="no such world file"):
        load_world(tmp_path / "absent.yaml")
