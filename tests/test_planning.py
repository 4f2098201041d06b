"""Board poses planned for the intrinsics (omnitof.calibration.planning)."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest

from omnitof.calibration import CalibrationError
from omnitof.calibration.planning import board_information, plan_boards, predicted_covariance, projection_weight
from omnitof.calibration.targets import Checkerboard, checkerboard_poses, planned_checkerboard_poses
from omnitof.sensor.design import default_rig

NAMES = ("fx", "fy", "cx", "cy")


@pytest.fixture(scope="module")
def camera():
    return default_rig().camera


def _with_intrinsics(camera, theta):
    fx, fy, cx, cy, k1, k2, p1, p2 = theta
    return dataclasses.replace(camera, fx=fx, fy=fy, cx=cx, cy=cy, dist=(k1, k2, p1, p2, 0.0))


def _theta(camera):
    return np.array([camera.fx, camera.fy, camera.cx, camera.cy, *camera.dist[:4]])


def _corners(camera, points, pose):
    return camera.project(points @ pose[:3, :3].T + pose[:3, 3]).ravel()


def test_board_information_is_the_schur_complement_of_a_numerical_jacobian(camera):
    # Independent of OpenCV: central differences of the project's own lens model.
    board = Checkerboard()
    points = board.object_points().reshape(-1, 3)
    pose = checkerboard_poses(camera, board, 1, seed=3)[0]
    theta = _theta(camera)
    j_theta = np.empty((2 * len(points), 8))
    for k in range(8):
        step = np.zeros(8)
        step[k] = 1e-6 * max(1.0, abs(theta[k]))
        j_theta[:, k] = (_corners(_with_intrinsics(camera, theta + step), points, pose)
                         - _corners(_with_intrinsics(camera, theta - step), points, pose)) / (2 * step[k])
    # The board's pose in another parameterisation than OpenCV's (rotation applied in the
    # board's frame): the Schur complement does not depend on how the nuisance is written.
    j_pose = np.empty((2 * len(points), 6))
    h = 1e-7
    for k in range(6):
        plus, minus = pose.copy(), pose.copy()
        if k < 3:
            plus[:3, :3] = pose[:3, :3] @ cv2.Rodrigues(h * np.eye(3)[k])[0]
            minus[:3, :3] = pose[:3, :3] @ cv2.Rodrigues(-h * np.eye(3)[k])[0]
        else:
            plus[k - 3, 3] += h
            minus[k - 3, 3] -= h
        j_pose[:, k] = (_corners(camera, points, plus) - _corners(camera, points, minus)) / (2 * h)
    a, b, c = j_theta.T @ j_theta, j_theta.T @ j_pose, j_pose.T @ j_pose
    expected = a - b @ np.linalg.solve(c, b.T)
    got = board_information(camera, points, pose)
    assert np.allclose(got, expected, rtol=1e-3, atol=1e-4 * np.abs(expected).max())


def _fit(camera, points, poses, rng, sigma):
    image_points = [(_corners(camera, points, pose).reshape(-1, 1, 2) + rng.normal(0, sigma, (len(points), 1, 2)))
                    .astype(np.float32) for pose in poses]
    object_points = [points.astype(np.float32)] * len(poses)
    _, K, dist, _, _ = cv2.calibrateCamera(object_points, image_points, (camera.width, camera.height), None, None,
                                           flags=cv2.CALIB_FIX_K3,
                                           criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-12))
    return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])


def test_predicted_covariance_matches_the_spread_of_opencv_calibrations(camera):
    board = Checkerboard()
    points = board.object_points().reshape(-1, 3)
    poses = planned_checkerboard_poses(camera, board, 12, seed=1)
    predicted = np.sqrt(np.diag(predicted_covariance(
        [board_information(camera, points, p) for p in poses], 0.05))[:4])
    rng = np.random.default_rng(5)
    fits = np.array([_fit(camera, points, poses, rng, 0.05) for _ in range(60)])
    spread = fits.std(axis=0, ddof=1)
    # 60 draws estimate a standard deviation to about ±9 % (1 σ).
    for name, s, p in zip(NAMES, spread, predicted):
        assert 0.7 < s / p < 1.35, f"{name}: spread {s:.4f} against predicted {p:.4f}"


def test_planned_boards_calibrate_the_principal_point_better_than_random_ones(camera):
    board = Checkerboard()
    points = board.object_points().reshape(-1, 3)
    random_poses = checkerboard_poses(camera, board, 15, seed=8)
    planned = planned_checkerboard_poses(camera, board, 15, seed=8)
    truth = _theta(camera)[:4]
    rng = np.random.default_rng(2)
    errors = {}
    for name, poses in (("random", random_poses), ("planned", planned)):
        fits = np.array([_fit(camera, points, poses, rng, 0.05) for _ in range(30)])
        errors[name] = np.sqrt(np.mean(np.sum((fits[:, 2:] - truth[2:]) ** 2, axis=1)))
    assert errors["planned"] < 0.8 * errors["random"], errors


def test_the_plan_lowers_the_predicted_projection_uncertainty_at_every_step(camera):
    board = Checkerboard()
    points = board.object_points().reshape(-1, 3)
    pool = checkerboard_poses(camera, board, 60, seed=4)
    infos = [board_information(camera, points, p) for p in pool]
    weight = projection_weight(camera)
    chosen = plan_boards(infos, 10, weight)
    assert len(set(chosen)) == 10
    costs = [np.trace(predicted_covariance([infos[i] for i in chosen[:k]], 1.0) @ weight) for k in range(8, 11)]
    assert costs[0] > costs[1] > costs[2]
    # The plan beats the first 10 candidates (a random draw of the same pool).
    random_cost = np.trace(predicted_covariance(infos[:10], 1.0) @ weight)
    assert costs[-1] < random_cost
    with pytest.raises(ValueError, match="cannot choose 61 from 60"):
        plan_boards(infos, 61, weight)


def test_a_plan_after_boards_taken_fills_in_what_they_leave_uncertain(camera):
    board = Checkerboard()
    points = board.object_points().reshape(-1, 3)

    def centre_u(pose):
        return camera.project((points @ pose[:3, :3].T + pose[:3, 3]).mean(axis=0)[None])[0, 0]

    # Six boards taken, all in the image's left part.
    taken = [p for p in checkerboard_poses(camera, board, 200, seed=5) if centre_u(p) < 0.4 * camera.width][:6]
    assert len(taken) == 6
    prior = sum(board_information(camera, points, p) for p in taken)
    pool = checkerboard_poses(camera, board, 120, seed=6)
    infos = [board_information(camera, points, p) for p in pool]
    weight = projection_weight(camera)

    def cost(chosen):
        return np.trace(np.linalg.inv(prior + sum(infos[i] for i in chosen)) @ weight)

    after = plan_boards(infos, 6, weight, prior=prior)
    blind = plan_boards(infos, 6, weight)
    assert plan_boards(infos, 6, weight, prior=np.zeros_like(prior)) == blind
    assert cost(after) < cost(blind) < np.trace(np.linalg.inv(prior) @ weight)
    # planned_checkerboard_poses counts the boards taken the same way.
    assert [p.tobytes() for p in planned_checkerboard_poses(camera, board, 6, 6, candidates_per_board=20, taken=taken)] \
        == [pool[i].tobytes() for i in after]


def test_a_camera_whose_distortion_folds_before_the_image_corner_still_plans(camera):
    # A first calibration from 10 boards (benchmarks/calibration_planning.py --nominal, seed 9):
    # k2 a tenth low, so the image's top right corner lies beyond the fold and has no ray. Its NaN
    # once turned every candidate's cost into NaN and the plan into a random pick.
    rough = dataclasses.replace(camera, fx=145.8057, fy=145.2744, cx=83.5388, cy=76.1167,
                                dist=(-0.2721349, 0.03116001, 0.00598305, 5.935e-06, 0.0))
    assert np.isnan(rough.rays(np.array([[camera.width - 1.0, 0.0]]))).all()
    weight = projection_weight(rough)
    assert np.isfinite(weight).all()
    board = Checkerboard()
    points = board.object_points().reshape(-1, 3)
    truth_weight = projection_weight(camera)

    def cost(poses):  # predicted with the true camera
        return np.trace(np.linalg.inv(sum(board_information(camera, points, p) for p in poses)) @ truth_weight)

    with_rough = cost(planned_checkerboard_poses(rough, board, 15, seed=9))
    with_truth = cost(planned_checkerboard_poses(camera, board, 15, seed=9))
    at_random = cost(checkerboard_poses(camera, board, 15, seed=9))
    assert with_rough < 1.25 * with_truth < at_random
    nan_weight = weight.copy()
    nan_weight[0, 0] = np.nan
    with pytest.raises(CalibrationError, match="not finite"):
        plan_boards([board_information(camera, points, p) for p in checkerboard_poses(camera, board, 4, seed=1)],
                    2, nan_weight)


def test_plan_boards_command_writes_poses_that_show_the_whole_board(tmp_path, capsys):
    import yaml

    from omnitof.cli import main

    assert main(["calibrate", "plan-boards", "--out", str(tmp_path), "--boards", "6", "--seed", "3"]) == 0
    printed = capsys.readouterr().out
    assert "predicted σ" in printed and (tmp_path / "boards.png").stat().st_size > 0
    plan = yaml.safe_load((tmp_path / "boards.yaml").read_text())
    camera = default_rig().camera
    assert len(plan["boards"]) == 6
    for entry in plan["boards"]:
        pose = np.array(entry["camera_T_board"])
        board = Checkerboard()
        x0, x1, y0, y1 = board.extent()
        outline = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])
        pixels = camera.project(outline @ pose[:3, :3].T + pose[:3, 3])
        assert np.allclose(pixels, entry["outline_px"], atol=0.06)
        assert np.all((pixels >= 0) & (pixels <= [camera.width - 1, camera.height - 1]))
        assert 0.0 <= entry["tilt_deg"] <= 50.0 + 1e-6
    spread = plan["predicted_std"]
    assert spread["corner_error_px"] == 0.05 and "taken" not in spread and "taken" not in plan
    assert spread["planned"]["cx_px"] < spread["random"]["cx_px"]


def test_plan_boards_command_plans_after_the_boards_taken(tmp_path, capsys):
    import yaml

    from omnitof.calibration.targets import render_checkerboard_images
    from omnitof.cli import main

    rig = default_rig()
    camera, board = rig.camera, Checkerboard()
    images, poses = render_checkerboard_images(camera, 5, seed=2, sensor=rig.sensor, planned=False)
    taken = tmp_path / "taken"
    taken.mkdir()
    for image in images:
        np.savez(taken / f"{image.name}.npz", amplitude=image.amplitude, distance=image.distance)
    out = tmp_path / "plan"
    assert main(["calibrate", "plan-boards", "--out", str(out), "--taken", str(taken), "--boards", "4"]) == 0
    printed = capsys.readouterr().out
    assert "calibrated from 5 boards taken" in printed and "the 5 boards taken alone" in printed
    plan = yaml.safe_load((out / "boards.yaml").read_text())
    # The camera planned with is the one calibrated from the boards taken, not the design's.
    assert abs(plan["camera"]["cx"] - camera.cx) < 0.5 and plan["camera"]["cx"] != camera.cx
    assert len(plan["boards"]) == 4 and [t["name"] for t in plan["taken"]] == sorted(str(p) for p in taken.iterdir())
    x0, x1, y0, y1 = board.extent()
    outline = np.array([[x0, y0, 0.0], [x1, y0, 0.0], [x1, y1, 0.0], [x0, y1, 0.0]])
    for entry, pose in zip(plan["taken"], poses):  # where each board taken really was
        truth = camera.project(outline @ pose[:3, :3].T + pose[:3, 3])
        # The corners' order is the detector's (a board turned by 180° looks the same).
        gaps = np.linalg.norm(truth[:, None, :] - np.array(entry["outline_px"])[None, :, :], axis=2)
        assert gaps.min(axis=1).max() < 0.3
    spread = plan["predicted_std"]
    assert 0.0 < spread["corner_error_px"] < 0.05  # the boards' own residuals, not the round figure
    assert spread["planned"]["cx_px"] < spread["taken"]["cx_px"]
    assert spread["planned"]["cx_px"] <= spread["random"]["cx_px"]
    assert (out / "boards.png").stat().st_size > 0
    # Too few boards taken to calibrate from: one clear error, nothing written.
    few = tmp_path / "few"
    few.mkdir()
    for image in images[:2]:
        np.savez(few / f"{image.name}.npz", amplitude=image.amplitude, distance=image.distance)
    assert main(["calibrate", "plan-boards", "--out", str(tmp_path / "none"), "--taken", str(few)]) == 2
    assert "found in 2 of 2 images, need 3" in capsys.readouterr().err
    assert not (tmp_path / "none").exists()


def test_plan_boards_command_takes_one_source_of_the_camera(tmp_path, capsys):
    from omnitof.cli import main

    with pytest.raises(SystemExit) as stopped:  # argparse's own refusal, before anything runs
        main(["calibrate", "plan-boards", "--out", str(tmp_path / "plan"), "--taken", str(tmp_path),
              "--calibration", str(tmp_path / "cal.yaml")])
    assert stopped.value.code == 2
    assert "not allowed with argument" in capsys.readouterr().err
    assert not (tmp_path / "plan").exists()


def test_plan_boards_command_names_a_bad_board(tmp_path, capsys):
    from omnitof.cli import main

    assert main(["calibrate", "plan-boards", "--out", str(tmp_path), "--board", "8by6"]) == 2
    assert "--board" in capsys.readouterr().err
    assert not (tmp_path / "boards.yaml").exists()


def test_plan_boards_command_refuses_a_board_too_large_for_the_view(tmp_path, capsys):
    from omnitof.cli import main

    assert main(["calibrate", "plan-boards", "--out", str(tmp_path), "--square", "0.2", "--boards", "5"]) == 2
    err = capsys.readouterr().err
    assert "8x6 checkerboard of 0.2 m squares" in err and "smaller board" in err
    assert not (tmp_path / "boards.yaml").exists()
