"""Tests of the joint refinement (omnitof.calibration.refine, issue 16): it recovers perturbed
parameters from rendered targets, its reported standard deviations cover the true errors, and
it refuses data that cannot determine every parameter, naming what is missing."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from omnitof.calibration import CalibrationError
from omnitof.calibration.refine import PlaneView, PosedView, Problem, ToFSamples, mirror_errors, refine
from omnitof.calibration.targets import Checkerboard, DotTarget, PlainBoard, checkerboard_poses, pair_board_poses
from omnitof.sensor.design import default_rig
from omnitof.sensor.mirrors import MirrorPlane, project_via


@pytest.fixture(scope="module")
def rig():
    return default_rig()


def _card_points(extent, n, rng):
    x0, x1, y0, y1 = extent
    return np.column_stack([rng.uniform(x0, x1, n), rng.uniform(y0, y1, n), np.zeros(n)])


_DOT_POSES: dict = {}


def _dot_poses(rig, k, n, seed):
    from omnitof.calibration.targets import dot_target_poses

    key = (k, n, seed)
    if key not in _DOT_POSES:  # the pose search is the slow part: once per geometry
        _DOT_POSES[key] = dot_target_poses(rig.camera, rig.mirrors, k, DotTarget(), n, seed)
    return _DOT_POSES[key]


def _synthetic_problem(rig, seed, *, boards=6, dots_per_mirror=2, px_noise=0.1, range_noise=0.003,
                       tilt=True, mirrors_with_dots=None, noise_seed=None):
    """Observations drawn from the true rig with Gaussian noise (no rendering): corners and dots
    projected exactly, path lengths exact along the pixel's ray, plus noise. `seed` fixes the
    targets' poses, `noise_seed` (default: seed) the noise."""
    rng = np.random.default_rng(seed if noise_seed is None else noise_seed)
    camera, mirrors = rig.camera, rig.mirrors
    board = Checkerboard()
    views = []
    poses = checkerboard_poses(camera, board, boards, seed)
    for i, pose in enumerate(poses):
        if not tilt:  # face the camera: the board's normal along its line of sight
            centre = pose[:3, 3] + pose[:3, :3] @ board.object_points().mean(axis=0)
            from omnitof.calibration.targets import look_at_pose
            pose = look_at_pose(centre, -centre, 0.3 * i)
            pose[:3, 3] -= pose[:3, :3] @ board.object_points().mean(axis=0).astype(float)
        pts = board.object_points().astype(float)
        px = camera.project(pts @ pose[:3, :3].T + pose[:3, 3]) + rng.normal(0, px_noise, (len(pts), 2))
        card = _card_points(board.extent(), 40, rng) @ pose[:3, :3].T + pose[:3, 3]
        tof = ToFSamples(camera.project(card), np.linalg.norm(card, axis=1) + rng.normal(0, range_noise, 40),
                         np.ones(40))
        views.append(PosedView(f"board_{i}", "board", pts, px, np.full(len(pts), -1), pose, [tof]))
    target = DotTarget()
    for k, mirror in enumerate(mirrors):
        if mirrors_with_dots is not None and k not in mirrors_with_dots:
            continue
        for i, pose in enumerate(_dot_poses(rig, k, dots_per_mirror, seed * 10 + k)):
            dots = target.dot_centres() @ pose[:3, :3].T + pose[:3, 3]
            direct = camera.project(dots) + rng.normal(0, px_noise, (4, 2))
            via = project_via(camera, mirror, dots) + rng.normal(0, px_noise, (4, 2))
            card = _card_points(target.extent(), 30, rng) @ pose[:3, :3].T + pose[:3, 3]
            virtual = mirror.plane.reflect_points(card)
            tof = [ToFSamples(camera.project(card), np.linalg.norm(card, axis=1) + rng.normal(0, range_noise, 30), np.ones(30)),
                   ToFSamples(camera.project(virtual), np.linalg.norm(virtual, axis=1) + rng.normal(0, range_noise, 30), np.ones(30), k)]
            views.append(PosedView(f"{mirror.name}_{i}", "dots", np.vstack([target.dot_centres()] * 2),
                                   np.vstack([direct, via]), np.array([-1] * 4 + [k] * 4), pose, tof))
    return Problem(camera, [m.plane for m in mirrors], [m.name for m in mirrors], views), poses


def _perturbed(problem, rng):
    cam = problem.camera
    camera = replace(cam, fx=cam.fx * (1 + rng.normal(0, 0.003)), fy=cam.fy * (1 + rng.normal(0, 0.003)),
                     cx=cam.cx + rng.normal(0, 0.5), cy=cam.cy + rng.normal(0, 0.5))
    planes = []
    for p in problem.planes:
        n = p.normal + rng.normal(0, 0.003, 3)
        planes.append(MirrorPlane(n / np.linalg.norm(n), p.d + rng.normal(0, 0.001)))
    return replace(problem, camera=camera, planes=planes)


def test_the_reported_uncertainty_covers_the_true_error(rig):
    """Over many noise draws (two target layouts), the true error lies within 1.96 reported σ
    about 95 % of the time (camera fx, fy, cx, cy; each mirror's two normal angles and d)."""
    inside, total = 0, 0
    for seed in range(12):
        problem, _ = _synthetic_problem(rig, seed % 2, noise_seed=seed, boards=5, dots_per_mirror=1)
        result = refine(_perturbed(problem, np.random.default_rng(1000 + seed)))
        cam, true = result.camera, rig.camera
        for name, err in (("fx", cam.fx - true.fx), ("fy", cam.fy - true.fy), ("cx", cam.cx - true.cx),
                          ("cy", cam.cy - true.cy)):
            inside += abs(err) <= 1.96 * result.std["camera"][name]
            total += 1
        for err, std in zip(mirror_errors(result, [m.plane for m in rig.mirrors]), result.std["mirrors"].values()):
            sa, sb = (math.radians(v) for v in std["tangent_deg"])
            inside += (abs(err["a"]) <= 1.96 * sa) + (abs(err["b"]) <= 1.96 * sb)
            inside += abs(err["d"]) <= 1.96 * std["d_mm"] / 1000.0
            total += 3
    share = inside / total
    assert 0.88 <= share <= 0.995, f"{share:.3f} of the true errors within 1.96 σ ({total} errors)"


def test_refinement_recovers_perturbed_parameters_from_rendered_targets(rig):
    from omnitof.calibration import Calibration
    from omnitof.calibration.observations import refine_calibration
    from omnitof.calibration.targets import render_checkerboard_images, render_dot_images, render_pair_images

    camera, mirrors = rig.camera, rig.mirrors
    boards, _ = render_checkerboard_images(camera, 10, 3)
    dots, _ = render_dot_images(camera, mirrors, 2, 3)
    pairs, _ = render_pair_images(camera, mirrors, 1, 3)
    truth = Calibration.from_rig(rig)
    rng = np.random.default_rng(5)
    start_planes = []
    for p in rig.planes:  # normals ~0.4° and d 2 mm off
        n = p.normal + rng.normal(0, 0.005, 3)
        start_planes.append(MirrorPlane(n / np.linalg.norm(n), p.d + 0.002))
    start_camera = replace(camera, fx=camera.fx * 1.01, cx=camera.cx + 1.0, cy=camera.cy - 1.0)
    start = truth.with_rig(replace(truth.rig, camera=start_camera, planes=tuple(start_planes)))
    refined, result = refine_calibration(start, boards, dots, pairs)
    cam = refined.camera
    assert abs(cam.fx / camera.fx - 1) < 0.003 and abs(cam.fy / camera.fy - 1) < 0.003
    assert math.hypot(cam.cx - camera.cx, cam.cy - camera.cy) < 0.6
    for got, want in zip(refined.planes, rig.planes):
        assert math.degrees(math.acos(min(1.0, got.normal @ want.normal))) < 0.25
        assert abs(got.d - want.d) < 0.0008
    assert set(result.per_mirror) == {m.name for m in mirrors}
    assert refined.quality["refinement"]["std"]["camera"]["cx"] > 0


def test_fronto_parallel_boards_are_refused(rig):
    problem, _ = _synthetic_problem(rig, 0, tilt=False, dots_per_mirror=1)
    with pytest.raises(CalibrationError, match="face the camera.*focal length"):
        refine(problem)


def test_a_mirror_without_dots_is_refused_by_name(rig):
    problem, _ = _synthetic_problem(rig, 0, dots_per_mirror=1, mirrors_with_dots=[0, 1, 2])
    with pytest.raises(CalibrationError, match="'right'.*seen in no image"):
        refine(problem)


def test_a_two_mirror_board_counts_for_both_mirrors(rig):
    """A mirror with no dot target but seen through a two-mirror board is determined."""
    problem, _ = _synthetic_problem(rig, 1, dots_per_mirror=1, mirrors_with_dots=[0, 1, 2])
    rng = np.random.default_rng(0)
    camera, mirrors = rig.camera, rig.mirrors
    for j, pose in enumerate(pair_board_poses(camera, mirrors, 2, 3, PlainBoard(), 2, 0)):
        samples = []
        for k in (2, 3):
            card = _card_points(PlainBoard().extent(), 400, rng) @ pose[:3, :3].T + pose[:3, 3]
            px = project_via(camera, mirrors[k], card)
            ok = np.isfinite(px[:, 0])
            virtual = mirrors[k].plane.reflect_points(card[ok])
            samples.append(ToFSamples(px[ok], np.linalg.norm(virtual, axis=1) + rng.normal(0, 0.003, ok.sum()),
                                      np.ones(ok.sum()), k))
        n = pose[:3, 2]
        problem.plane_views.append(PlaneView(f"pair_{j}", n, float(n @ pose[:3, 3]), samples))
    result = refine(problem)  # refused without the boards (the test above)
    err = mirror_errors(result, [m.plane for m in mirrors])[3]
    std = result.std["mirrors"]["right"]
    assert std["normal_deg"] < 1.0 and std["d_mm"] < 2.0
    assert math.degrees(math.hypot(err["a"], err["b"])) < 3.0 * std["normal_deg"]


def test_a_dim_two_mirror_board_is_found_against_the_room_behind(rig):
    """`simulate calibration` seed 0's back-right boards (the same poses and noise): dimmer
    than the others, so the room behind the front and left mirrors passed the brightness test
    and its flat patches outscored the board, which was then left unused ("seen through 1
    mirror"). Each must give a plane view through both mirrors, its plane the board's."""
    from omnitof.calibration import Calibration
    from omnitof.calibration.images import AmplitudeImage
    from omnitof.calibration.observations import plane_view
    from omnitof.calibration.targets import render_target

    camera, mirrors = rig.camera, rig.mirrors
    back, right = (next(i for i, m in enumerate(mirrors) if m.name == n) for n in ("back", "right"))
    truth = Calibration.from_rig(rig)
    poses = pair_board_poses(camera, mirrors, back, right, PlainBoard(), 2, 100 + back)
    for i, pose in enumerate(poses):
        frame, _ = render_target(camera, PlainBoard(), pose, mirrors, rng=np.random.default_rng([0, 100 + back, i]))
        image = AmplitudeImage(f"pair_back-right_{i:02d}", frame.amplitude, frame.distance)
        view, why = plane_view(camera, image, truth.planes, truth.labels, np.random.default_rng(0))
        assert view is not None, why
        assert sorted(t.mirror for t in view.tof) == sorted([back, right])
        normal = pose[:3, 2]
        assert math.degrees(math.acos(min(1.0, abs(float(view.normal @ normal))))) < 1.0
        assert abs(abs(view.c) - abs(float(normal @ pose[:3, 3]))) < 0.01


def test_refine_and_report_commands(tmp_path, rig, capsys):
    """`omnitof calibrate refine` on rendered targets, then `calibrate report`: the refined file
    carries standard deviations, the report its sections and figures."""
    from omnitof.calibration import load_calibration
    from omnitof.cli import main

    folder = tmp_path / "targets"
    assert main(["simulate", "calibration", "--out", str(folder), "--boards", "8", "--placements", "2",
                 "--pair-boards", "1", "--seed", "4"]) == 0
    cal = tmp_path / "cal.yaml"
    assert main(["calibrate", "intrinsics", str(folder / "intrinsics"), "--out", str(cal)]) == 0
    assert main(["calibrate", "mirrors", str(folder / "mirrors"), "--calibration", str(cal)]) == 0
    refined = tmp_path / "refined.yaml"
    capsys.readouterr()
    assert main(["calibrate", "refine", str(folder), "--calibration", str(cal), "--out", str(refined)]) == 0
    result = load_calibration(refined)
    assert set(result.quality["refinement"]["std"]["mirrors"]) == set(result.names)
    # What it says it used: of the 8 boards, 4 × 2 dot cards and 4 two-mirror boards read, each
    # image used or named as not used (skipped) or left out (an outlier).
    used = result.quality["refinement"]["views_used"]
    printed = capsys.readouterr().out
    assert (f"refined from {used['boards']} of 8 board, {used['dot_targets']} of 8 dot-target and "
            f"{used['two_mirror_boards']} of 4 two-mirror images") in printed
    unused = len(result.quality["refinement"]["skipped"]) + len(result.quality["refinement"]["rejected"])
    assert used["boards"] + used["dot_targets"] + used["two_mirror_boards"] + unused == 8 + 8 + 4
    report = tmp_path / "report"
    assert main(["calibrate", "report", str(refined), "--out", str(report), "--truth", str(folder / "truth.yaml")]) == 0
    text = (report / "report.md").read_text()
    for heading in ("## Camera", "## Mirrors", "## Residuals", "## Distance correction", "Fig. 6 check"):
        assert heading in text
    assert (report / "residuals.png").stat().st_size > 1000
    assert (report / "fig6_side_view.png").stat().st_size > 1000


def test_a_discs_predicted_centroid_is_the_centroid_of_its_image(rig):
    """`polygon_centroids` of a projected disc outline against the centroid of the disc's image
    found independently: a fine grid of image points, each back-projected onto the card."""
    from omnitof.calibration.refine import DISC_VERTICES, polygon_centroids

    camera = rig.camera
    square = np.array([[[0.0, 0.0], [2.0, 0.0], [2.0, 1.0], [0.0, 1.0]]])
    assert np.allclose(polygon_centroids(square), [[1.0, 0.5]])
    assert np.allclose(polygon_centroids(square[:, ::-1]), [[1.0, 0.5]])  # either orientation
    radius = 0.0025
    tilt = math.radians(50.0)
    normal = np.array([math.sin(tilt), 0.0, -math.cos(tilt)])  # the card faces the camera
    centre = np.array([0.05, 0.03, 0.12])
    e1 = np.cross(normal, [0.0, 1.0, 0.0]); e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    angle = np.linspace(0.0, 2.0 * math.pi, DISC_VERTICES, endpoint=False)
    outline = centre + radius * (np.cos(angle)[:, None] * e1 + np.sin(angle)[:, None] * e2)
    predicted = polygon_centroids(camera.project(outline)[None])[0]
    # The image of the disc: pixels of a 0.02 px grid whose rays meet the card inside the disc.
    middle = camera.project(centre[None])[0]
    step = 0.02
    g = np.arange(-6.0, 6.0, step)
    gu, gv = np.meshgrid(middle[0] + g, middle[1] + g)
    pixels = np.stack([gu.ravel(), gv.ravel()], axis=1)
    rays = camera.rays(pixels)
    hits = rays * ((centre @ normal) / (rays @ normal))[:, None]
    inside = np.linalg.norm(hits - centre, axis=1) <= radius
    measured = pixels[inside].mean(axis=0)
    projected_centre = camera.project(centre[None])[0]
    assert np.hypot(*(predicted - measured)) < 0.005
    # ... and the projected centre is not that centroid (the reason for the model).
    assert np.hypot(*(projected_centre - measured)) > 0.01  # 0.016 px here


def test_a_misdetected_board_is_left_out_and_named(rig, monkeypatch):
    """One board's corners misassigned (its last two rows of corners found one row early, as a
    detection that slipped would): the refinement names it, leaves it out, and comes out as the
    fit without it does, σ included. The clean problem loses no view."""
    clean, _ = _synthetic_problem(rig, 0, boards=8, dots_per_mirror=2)
    start = _perturbed(clean, np.random.default_rng(7))
    reference = refine(start)
    assert reference.rejected == {}
    views = list(start.views)
    bad = views[2]
    per_row = Checkerboard().pattern_size[0]
    moved = bad.pixels.copy()
    moved[-2 * per_row:] = bad.pixels[-3 * per_row:-per_row]
    views[2] = replace(bad, pixels=moved)
    result = refine(replace(start, views=views))
    assert list(result.rejected) == [bad.name] and result.rejected[bad.name] > 0.2
    assert bad.name not in result.per_view
    without = refine(replace(start, views=[v for i, v in enumerate(start.views) if i != 2]))
    for name in ("fx", "fy", "cx", "cy"):
        assert getattr(result.camera, name) == pytest.approx(getattr(without.camera, name), abs=1e-6)
        assert result.std["camera"][name] == pytest.approx(without.std["camera"][name], rel=1e-6)
    # Kept in (no robust step), the board pulls the principal point and inflates its σ.
    import omnitof.calibration.refine as refine_module

    monkeypatch.setattr(refine_module, "REJECTION_ROUNDS", 0)
    kept = refine(replace(start, views=views))
    assert kept.rejected == {} and kept.std["camera"]["cx"] > 1.3 * result.std["camera"]["cx"]


def test_an_outlying_board_stays_where_leaving_it_out_would_leave_too_few(rig):
    # Three boards are the least the refinement takes (check_problem): a slipped one stays.
    problem, _ = _synthetic_problem(rig, 1, boards=3, dots_per_mirror=2)
    views = list(problem.views)
    per_row = Checkerboard().pattern_size[0]
    moved = views[1].pixels.copy()
    moved[-2 * per_row:] = views[1].pixels[-3 * per_row:-per_row]
    views[1] = replace(views[1], pixels=moved)
    result = refine(replace(problem, views=views))
    assert result.rejected == {} and views[1].name in result.per_view


def test_the_refinement_is_the_same_for_one_blas_thread_and_two(rig, monkeypatch):
    # A multithreaded BLAS sums the fit's products in an order that depends on its thread count:
    # the demo's calibration, and then its map, differed between one core and two. The
    # refinement runs BLAS on one thread; without that (the limit made a no-op below) the two
    # results differ in their last digits.
    from contextlib import nullcontext

    from threadpoolctl import threadpool_limits

    import omnitof.calibration.refine as refine_module

    problem, _ = _synthetic_problem(rig, 3, boards=12, dots_per_mirror=3)
    start = _perturbed(problem, np.random.default_rng(7))

    def fitted(threads):
        with threadpool_limits(limits=threads, user_api="blas"):
            result = refine(start)
        return np.array([result.camera.fx, result.camera.fy, result.camera.cx, result.camera.cy,
                         *np.concatenate([[*p.normal, p.d] for p in result.planes])])

    assert np.array_equal(fitted(1), fitted(2))
    monkeypatch.setattr(refine_module, "threadpool_limits", lambda **_: nullcontext())
    if not np.array_equal(fitted(1), fitted(2)):
        return  # what the limit prevents, seen here
    pytest.skip("this BLAS sums alike on one thread and two for a problem of this size")
