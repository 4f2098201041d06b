"""An occupancy map against a reference map (omnitof.eval.map_agreement, `omnitof eval map`):
the alignment recovers a known transform, the scores match an independent count and the true
walls' distances, and bad inputs get one clear error."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from omnitof.cli import main
from omnitof.errors import OmnitofWarning
from omnitof.eval.floorplan import plan_map, wall_agreement
from omnitof.eval.map_agreement import MapAgreementError, compare_maps
from omnitof.io.rosmap import write_ros_map
from omnitof.sim.laser2d import World2D
from omnitof.types import OccupancyMap

# A building with no symmetry: an outline, three inner walls of different lengths, a pillar row.
WALLS = np.array([
    [0, 0, 20, 0], [20, 0, 20, 8], [20, 8, 0, 8], [0, 8, 0, 0],
    [5, 0, 5, 3], [12, 8, 12, 4], [0, 4, 3, 4], [15, 2, 18, 2],
], dtype=np.float64)
RES = 0.05


def drawn(segments: np.ndarray, pose=(0.0, 0.0, 0.0), *, res: float = RES, free: bool = True) -> OccupancyMap:
    """The walls as a map in the frame F with world = pose ⊕ F (so reference_T_map = pose), the
    cells inside the outline's bounding box free where `free`."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    seg = np.asarray(segments, dtype=np.float64).reshape(-1, 2, 2) - np.asarray(pose[:2])
    seg = np.stack([c * seg[..., 0] + s * seg[..., 1], -s * seg[..., 0] + c * seg[..., 1]], axis=-1)
    occ = plan_map(seg, res)
    if free:
        rows, cols = np.indices(occ.log_odds.shape)
        x = occ.origin[0] + (cols + 0.5) * res
        y = occ.origin[1] + (rows + 0.5) * res
        wx, wy = c * x - s * y + pose[0], s * x + c * y + pose[1]  # the cell in the world
        inside = (wx > 0.0) & (wx < 20.0) & (wy > 0.0) & (wy < 8.0) & (occ.log_odds <= 0)
        occ.log_odds[inside] = -2.0
        occ.known[inside] = True
    return occ


REFERENCE = drawn(WALLS)


def pose_error(found, true) -> tuple[float, float]:
    return math.hypot(found[0] - true[0], found[1] - true[1]), abs(math.remainder(found[2] - true[2], math.tau))


@settings(max_examples=6, deadline=None)
@given(x=st.floats(-15, 15), y=st.floats(-15, 15), theta=st.floats(-math.pi, math.pi))
def test_the_search_finds_a_turned_and_moved_copy(x, y, theta):
    result, moved, distance = compare_maps(drawn(WALLS, (x, y, theta)), REFERENCE)
    dxy, dth = pose_error(result.pose, (x, y, theta))
    # Both maps are the same walls drawn in 5 cm cells in two frames: one cell and a tenth of a
    # degree is their drawing's quantisation.
    assert dxy < RES and math.degrees(dth) < 0.2
    assert result.near == 1.0 and result.covered == 1.0
    assert result.p90_distance < RES
    assert len(moved) == len(distance) == result.estimate_cells


def test_icp_from_a_start_half_a_metre_and_five_degrees_off():
    true = (2.0, -1.0, math.radians(30.0))
    start = (2.4, -0.7, math.radians(35.0))
    result, _, _ = compare_maps(drawn(WALLS, true), REFERENCE, align="initial", initial=start)
    dxy, dth = pose_error(result.pose, true)
    assert dxy < RES and math.degrees(dth) < 0.2
    assert result.align == "initial"


def test_icp_lands_on_the_walls_not_on_the_lattice():
    # The same cells from a start 3 cm and half a degree off: point-to-point ICP stalled on the
    # cells' lattice 0.17 degrees off; along the walls' normals it comes back to the identity.
    result, _, _ = compare_maps(REFERENCE, REFERENCE, align="initial", initial=(0.03, -0.02, math.radians(0.5)))
    dxy, dth = pose_error(result.pose, (0.0, 0.0, 0.0))
    assert dxy < 0.002 and math.degrees(dth) < 0.01
    assert result.constraint > 0.1 and result.warnings() == []


def test_a_straight_corridor_is_flagged_as_free_along_its_axis():
    corridor = np.array([[0, 0, 40, 0], [0, 2, 40, 2]], dtype=np.float64)
    seen = np.array([[12, 0, 22, 0], [12, 2, 22, 2]], dtype=np.float64)
    result, _, _ = compare_maps(drawn(seen, (1.0, 1.0, 0.3), free=False), plan_map(corridor, RES))
    # Every cell lies on the corridor's walls (turned either way), but where along them is free.
    assert result.near == 1.0
    assert result.constraint < 1e-6
    assert abs(result.weakest[0]) > 0.99  # along x, the corridor's axis in the reference
    assert any("hardly fix" in w for w in result.warnings())


def test_a_square_hall_is_flagged_as_ambiguous():
    square = np.array([[0, 0, 10, 0], [10, 0, 10, 10], [10, 10, 0, 10], [0, 10, 0, 0]], dtype=np.float64)
    result, _, _ = compare_maps(drawn(square, (3.0, 2.0, 0.5), free=False), plan_map(square, RES))
    assert result.near == 1.0 and result.runner_up_near == 1.0 and result.runner_up_moved > 5.0
    assert any("another alignment" in w for w in result.warnings())
    # The asymmetric building has no such twin.
    building, _, _ = compare_maps(drawn(WALLS, (3.0, 2.0, 0.5)), REFERENCE)
    # (its outline turned half a turn still fits: 81 % of its cells, the inner walls not)
    assert building.warnings() == [] and building.runner_up_near < 0.9


def test_align_none_takes_the_frames_as_one():
    result, _, _ = compare_maps(drawn(WALLS, (1.0, 0.0, 0.0)), REFERENCE, align="none")
    assert result.pose == (0.0, 0.0, 0.0)
    # Shifted 1 m along x: only the walls along x (and the pillar row) still lie on the
    # reference's, each but its last metre, which now overhangs.
    assert 0.3 < result.near < 0.8


def test_a_wall_moved_by_ten_cm_counts_against_the_map_by_its_own_share():
    moved_wall = WALLS.copy()
    moved_wall[7] += [0.0, 0.10, 0.0, 0.10]  # the free-standing wall at y = 2 m, now 2.1 m
    estimate = drawn(moved_wall)
    result, cells, distance = compare_maps(estimate, REFERENCE, align="initial")
    # ICP keeps the frame: one short wall does not pull the rest off theirs.
    dxy, dth = pose_error(result.pose, (0.0, 0.0, 0.0))
    assert dxy < 0.01 and math.degrees(dth) < 0.1
    # The share is that of every cell but the moved wall's, counted from the walls' own cells.
    own = (cells[:, 0] > 14.9) & (cells[:, 0] < 18.1) & (cells[:, 1] > 2.05) & (cells[:, 1] < 2.2)
    assert own.sum() > 50
    assert result.near == pytest.approx(1.0 - own.mean(), abs=1e-9)
    assert np.all(distance[own] > RES)


def test_near_agrees_with_the_distance_to_the_true_walls():
    # A map of walls 0-3 cm off, scored against a reference drawn in 1 cm cells, and directly
    # against the segments (eval.floorplan, the demo's metric): the same share but for cells
    # whose distance lies within the reference's half centimetre of the tolerance.
    rng = np.random.default_rng(4)
    noisy = WALLS.reshape(-1, 2, 2) + rng.uniform(-0.03, 0.03, size=(len(WALLS), 2, 2))
    estimate = drawn(noisy.reshape(-1, 4))
    fine_reference = plan_map(WALLS, 0.01)
    result, _, _ = compare_maps(estimate, fine_reference, align="none")
    truth = wall_agreement(estimate, World2D(WALLS.reshape(-1, 2, 2)).distance_to_walls, tolerance=0.05,
                           threshold=0.5)
    assert result.estimate_cells == truth.occupied_cells
    assert result.near == pytest.approx(truth.near_fraction, abs=0.02)
    assert result.median_distance == pytest.approx(truth.median_distance, abs=0.006)


def test_covered_counts_only_the_walls_the_estimate_saw():
    # The estimate saw the west half only: its free cells end at x = 10 m, its walls too.
    half = WALLS.reshape(-1, 2, 2).copy()
    keep = half[:, :, 0].min(axis=1) < 10.0
    half = half[keep]
    half[:, :, 0] = np.minimum(half[:, :, 0], 10.0)
    estimate = drawn(half.reshape(-1, 4))
    inside = estimate.known & (estimate.log_odds < 0)
    cols = np.nonzero(inside)[1]
    estimate.log_odds[inside & (estimate.origin[0] + (np.indices(inside.shape)[1] + 0.5) * RES > 10.0)] = 0.0
    estimate.known[estimate.log_odds == 0.0] = False
    assert len(cols)
    result, _, _ = compare_maps(estimate, REFERENCE, align="none")
    ref_cells = np.argwhere(REFERENCE.log_odds > 0)
    x = REFERENCE.origin[0] + (ref_cells[:, 1] + 0.5) * RES
    # Seen: the reference's walls up to x = 10 m, plus the reach (0.15 m) beyond the last free cell.
    assert np.sum(x < 10.0) <= result.seen_reference_cells <= np.sum(x < 10.0 + 0.15 + RES)
    assert result.covered > 0.97
    assert result.near == 1.0


def test_maps_without_walls_or_overlap_are_refused():
    empty = OccupancyMap(np.full((10, 10), -2.0, np.float32), np.ones((10, 10), bool), RES, (0.0, 0.0))
    with pytest.raises(MapAgreementError, match="the estimate has 0 occupied cells"):
        compare_maps(empty, REFERENCE)
    with pytest.raises(MapAgreementError, match="the reference has 0 occupied cells"):
        compare_maps(REFERENCE, empty)
    with pytest.raises(MapAgreementError, match="do not overlap"):
        compare_maps(REFERENCE, REFERENCE, align="initial", initial=(100.0, 100.0, 0.0))
    with pytest.raises(ValueError, match="align"):
        compare_maps(REFERENCE, REFERENCE, align="rigid")
    with pytest.raises(ValueError, match="tolerance"):
        compare_maps(REFERENCE, REFERENCE, tolerance=0.0)


def test_the_command_prints_writes_and_refuses(tmp_path, capsys):
    est, ref = tmp_path / "est.yaml", tmp_path / "ref.yaml"
    true = (3.0, -2.0, math.radians(-70.0))
    write_ros_map(est, drawn(WALLS, true))
    write_ros_map(ref, REFERENCE)
    out, fig = tmp_path / "agreement.yaml", tmp_path / "agreement.png"
    assert main(["eval", "map", str(est), str(ref), "--out", str(out), "--figure", str(fig)]) == 0
    printed = capsys.readouterr().out
    assert "within 5 cm of the reference's: 100.0 %" in printed
    import yaml

    data = yaml.safe_load(out.read_text())
    assert data["near"] == 1.0 and data["align"] == "search"
    assert math.hypot(data["pose"]["x_m"] - true[0], data["pose"]["y_m"] - true[1]) < RES
    assert abs(data["pose"]["rotation_deg"] - math.degrees(true[2])) < 0.2
    assert fig.stat().st_size > 0
    # --initial implies ICP from there.
    assert main(["eval", "map", str(est), str(ref), "--initial", "2.8", "-2.1", "-68"]) == 0
    assert "ICP from the given pose" in capsys.readouterr().out
    # User mistakes: one line naming the file or the option, no traceback, nothing written.
    lost = tmp_path / "lost.yaml"  # names an image that is not there
    lost.write_text(ref.read_text().replace("ref.pgm", "gone.pgm"))
    empty = tmp_path / "empty.yaml"
    write_ros_map(empty, OccupancyMap(np.full((10, 10), -2.0, np.float32), np.ones((10, 10), bool), RES, (0.0, 0.0)))
    for argv, message in [
        (["eval", "map", str(empty), str(ref)], f"{empty} against {ref}: the estimate has 0 occupied cells"),
        (["eval", "map", str(est), str(ref), "--align", "none", "--initial", "0", "0", "0"], "--initial"),
        (["eval", "map", str(est), str(ref), "--align", "search", "--initial", "0", "0", "0"], "--initial"),
        (["eval", "map", str(est), str(ref), "--out", str(ref)], "is one of the inputs"),
        (["eval", "map", str(est), str(ref), "--out", str(tmp_path / "ref.pgm")], "is one of the inputs"),
        (["eval", "map", str(est), str(ref), "--figure", str(tmp_path / "est.pgm")], "ending in .png"),
        (["eval", "map", str(est), str(ref), "--out", str(tmp_path / "a.png"), "--figure", str(tmp_path / "a.png")],
         "named for two outputs"),
        (["eval", "map", str(est), str(tmp_path / "missing.yaml")], "missing.yaml"),
        (["eval", "map", str(est), str(lost)], f"(the image that {lost} names)"),
    ]:
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err
    assert not (tmp_path / "missing.yaml").exists() and not (tmp_path / "a.png").exists()
    assert (tmp_path / "ref.pgm").read_bytes().startswith(b"P5")
    # A reference coarser than the tolerance: scored, with a warning that says what it costs.
    coarse = tmp_path / "coarse.yaml"
    write_ros_map(coarse, plan_map(WALLS, 0.1))
    with pytest.warns(OmnitofWarning, match="coarser than --tolerance"):
        assert main(["eval", "map", str(est), str(coarse)]) == 0
