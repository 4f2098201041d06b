"""Range readings from ToF frames (omnitof.scan, paper sec. III), against analytic geometry and
the simulator's ground truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnitof.sensor.design import default_rig
from omnitof.errors import ConfigError, InputError
from omnitof.sensor.mirrors import camera_mount, masks, viewing_rays
from omnitof.scan.grazing import drop_grazing
from omnitof.scan import ScanConfigError, ScanExtractor, ScanInputError, ScanSettings, scans_from_frames

RIG = default_rig()


@pytest.fixture(scope="module")
def extractor() -> ScanExtractor:
    return ScanExtractor.from_rig()


@pytest.fixture(scope="module")
def rays_robot():
    """Independent per-pixel geometry: mirrors.viewing_rays (camera frame) moved to the robot
    frame; origin o, unit direction u, path L from the camera centre to the mirror."""
    camera, mirrors = RIG.camera, RIG.mirrors
    labels = masks(camera, mirrors)
    vr = viewing_rays(camera, mirrors, labels)
    mount = camera_mount()
    o = vr.origins @ mount[:3, :3].T + mount[:3, 3]
    u = vr.directions @ mount[:3, :3].T
    path = np.linalg.norm(vr.origins, axis=-1)
    return o, u, path, labels


def _cylinder_frame(rays_robot, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Distance image of a vertical cylinder wall of `radius` around the robot origin (an
    analytic scene): solve |o_xy + s·u_xy| = radius for s > 0; distance = L + s."""
    o, u, path, labels = rays_robot
    a = u[..., 0] ** 2 + u[..., 1] ** 2
    b = 2.0 * (o[..., 0] * u[..., 0] + o[..., 1] * u[..., 1])
    c = o[..., 0] ** 2 + o[..., 1] ** 2 - radius**2
    with np.errstate(invalid="ignore", divide="ignore"):
        s = (-b + np.sqrt(b * b - 4.0 * a * c)) / (2.0 * a)
    distance = np.where(labels >= 0, path + s, np.nan).astype(np.float32)
    # A plausible return: apparent reflectance amplitude·d² = 2000 (albedo ≈ 0.3 through a mirror),
    # inside the scan filters' window at every radius used here.
    amplitude = (2000.0 / np.where(np.isfinite(distance), distance, 1.0) ** 2).astype(np.float32)
    return distance, amplitude


def test_cylinder_wall_gives_its_radius_in_every_bin_that_sees_it(extractor, rays_robot):
    for radius in (1.0, 2.5, 6.0):
        distance, amplitude = _cylinder_frame(rays_robot, radius)
        ranges = extractor.extract(distance, amplitude)
        assert ranges.shape == (360,) and ranges.dtype == np.float32
        seen = np.isfinite(ranges)
        assert seen.mean() > 0.35, f"radius {radius}: only {seen.mean():.0%} of bins"
        np.testing.assert_allclose(ranges[seen], radius, atol=2e-4)  # 0.1 mm sort quantum
        assert np.all(np.isinf(ranges[~seen]))  # no reading is +inf, never 0 or NaN


def test_a_wall_just_inside_max_range_is_not_cut_short(rays_robot):
    # A cylinder wall 6.9 m away, 10 cm inside max_range (7 m), with 8 cm of Gaussian distance
    # noise (the sensor's at 7 m): its points spread beyond max_range. Cut there, each bin's
    # median is that of its near 89 % only, about 1 cm short; with range_margin the bins are
    # unbiased (within the 0.1 cm of the mean over some 170 bins of a few points each). A wall
    # 7.2 m away is no reading.
    distance, amplitude = _cylinder_frame(rays_robot, 6.9)
    noisy = distance + np.random.default_rng(5).normal(0.0, 0.08, distance.shape).astype(np.float32)
    cut = ScanExtractor.from_rig(range_margin=0.0, pixel_filter={"enabled": False}).extract(noisy, amplitude)
    kept = ScanExtractor.from_rig(pixel_filter={"enabled": False}).extract(noisy, amplitude)
    seen = np.isfinite(cut) & np.isfinite(kept)
    assert seen.sum() > 150
    assert np.mean(cut[seen]) - 6.9 < -0.007
    assert abs(np.mean(kept[seen]) - 6.9) < 0.004
    far, far_amplitude = _cylinder_frame(rays_robot, 7.2)
    assert np.all(np.isinf(ScanExtractor.from_rig().extract(far, far_amplitude)))
    # A statistic above the median takes no points beyond max_range (they would push it beyond).
    high = ScanExtractor.from_rig(statistic="max", pixel_filter={"enabled": False}).extract(noisy, amplitude)
    uncut = ScanExtractor.from_rig(statistic="max", range_margin=0.0, pixel_filter={"enabled": False})
    np.testing.assert_array_equal(high, uncut.extract(noisy, amplitude))
    assert np.isfinite(high).sum() > 150
    with pytest.raises(ScanConfigError, match=r"max_range \+ range_margin is 110 m; it must stay below 104.86 m"):
        ScanExtractor.from_rig(max_range=100.0, range_margin=10.0)
    with pytest.raises(ScanConfigError, match=r"min_range 10 m must be less than max_range 7 m: every bin would be empty"):
        ScanExtractor.from_rig(min_range=10.0, max_range=7.0)


def test_slice_height_selects_points_analytically(rays_robot):
    """Points fed to the slice lie within band of the height: check with the independent rays."""
    o, u, path, labels = rays_robot
    distance, amplitude = _cylinder_frame(rays_robot, 3.0)
    ex = ScanExtractor.from_rig(height=0.9, band=0.05, pixel_filter={"enabled": False})  # the slice alone
    mask = ex.slice_pixels(distance, amplitude)
    s = distance - path
    z = o[..., 2] + s * u[..., 2]
    assert mask.sum() > 100
    assert np.all(np.abs(z[mask] - 0.9) <= 0.05 + 1e-5)
    # and every labelled pixel in the band at 3 m is in the mask (no range limit bites at 3 m)
    inside = (labels >= 0) & (np.abs(z - 0.9) <= 0.05 - 1e-5)
    assert np.all(mask[inside])


def test_bearing_convention_box_room(extractor, rays_robot):
    """A 2 m (x) by 4 m (y) box room centred on the robot, analytic: bins 0 and 180 see the
    front and back walls at 1 m, bins 90 and 270 the side walls at 2 m."""
    o, u, path, labels = rays_robot
    half = np.array([1.0, 2.0])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = [np.where(u[..., k] != 0, (np.sign(u[..., k]) * half[k] - o[..., k]) / u[..., k], np.inf)
             for k in (0, 1)]
    s = np.minimum(t[0], t[1])
    distance = np.where(labels >= 0, path + s, np.nan).astype(np.float32)
    ranges = extractor.extract(distance, np.full(distance.shape, 800.0, np.float32))
    bearing = extractor.angles
    truth = np.minimum(1.0 / np.abs(np.cos(bearing) + 1e-300), 2.0 / np.abs(np.sin(bearing) + 1e-300))
    seen = np.isfinite(ranges)
    for k in (0, 90, 180, 270):
        assert seen[k], f"bin {k} empty"
    # a bin spans ±0.5°; over it, a wall seen at incidence φ (tan φ <= 2 here) changes its
    # range by at most r·tan φ·tan 0.5°; the median of the bin's points stays within that
    slack = truth * 2.0 * math.tan(math.radians(0.5)) + 1e-3
    assert np.all(np.abs(ranges[seen] - truth[seen]) <= slack[seen])
    assert math.isclose(ranges[0], 1.0, abs_tol=1e-3) and math.isclose(ranges[90], 2.0, abs_tol=1e-3)


def test_grazing_bins_of_the_box_room_are_dropped(rays_robot):
    """The box room again, with max_incidence_deg 20 (the rig sees no bearing 28–66° off the
    axes, so its walls are never seen more obliquely): the bins that see their wall well beyond
    20° from its normal lose their reading, those well within it keep theirs unchanged. The bins'
    own estimate errs by up to 4° here (omnitof.scan.grazing; one-sided differences of medians)."""
    o, u, path, labels = rays_robot
    half = np.array([1.0, 2.0])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = [np.where(u[..., k] != 0, (np.sign(u[..., k]) * half[k] - o[..., k]) / u[..., k], np.inf)
             for k in (0, 1)]
    distance = np.where(labels >= 0, path + np.minimum(t[0], t[1]), np.nan).astype(np.float32)
    amplitude = np.full(distance.shape, 800.0, np.float32)
    every = ScanExtractor.from_rig().extract(distance, amplitude)
    some = ScanExtractor.from_rig(max_incidence_deg=20.0).extract(distance, amplitude)
    b = ScanExtractor.from_rig().angles
    front = np.abs(np.cos(b)) * 2.0 > np.abs(np.sin(b))  # the bin's ray meets the x = ±1 wall first
    incidence = np.degrees(np.where(front, np.arccos(np.abs(np.cos(b))), np.arccos(np.abs(np.sin(b)))))
    seen = np.isfinite(every)
    assert np.isfinite(some[seen & (incidence <= 15.0)]).all()
    assert np.isinf(some[seen & (incidence >= 25.0)]).all()
    assert (seen & (incidence >= 25.0)).sum() >= 4 and (seen & (incidence <= 15.0)).sum() >= 60
    assert np.array_equal(some, drop_grazing(every, math.radians(1.0), math.radians(20.0)))


def test_amplitude_filter_and_nan_pixels(extractor, rays_robot):
    distance, amplitude = _cylinder_frame(rays_robot, 2.0)
    weak = extractor.extract(distance, np.full_like(amplitude, extractor.settings.min_amplitude - 1))
    assert np.all(np.isinf(weak))
    gone = extractor.extract(np.full_like(distance, np.nan), amplitude)
    assert np.all(np.isinf(gone))
    # 50 units at ~2.2 m is 240 units·m² scaled to 1 m: too dark for a real surface there (a
    # wrapped reading of a wall ~9.5 m away looks like this), dropped by min_amplitude_1m
    dim = np.full_like(amplitude, 50.0)
    assert np.all(np.isinf(extractor.extract(distance, dim)))
    kept = ScanExtractor.from_rig(min_amplitude_1m=0.0).extract(distance, dim)
    np.testing.assert_allclose(kept[np.isfinite(kept)], 2.0, atol=2e-4)


def test_statistics_order_and_extract_many_matches(extractor):
    from omnitof.sim.render import Renderer
    from omnitof.sim.worlds import load_world

    frames = Renderer(load_world("room")).render_many(np.array([[2.0, 1.5, 0.3], [4.0, 3.0, 2.0]]), seed=1)
    d = np.stack([f.distance for f in frames])
    a = np.stack([f.amplitude for f in frames])
    many = extractor.extract_many(d, a, chunk=1)
    np.testing.assert_array_equal(many, extractor.extract_many(d, a))
    np.testing.assert_array_equal(many[1], extractor.extract(d[1], a[1]))
    lo = ScanExtractor.from_rig(statistic="min").extract_many(d, a)
    hi = ScanExtractor.from_rig(statistic="max").extract_many(d, a)
    ok = np.isfinite(many)
    assert np.all(lo[ok] <= many[ok]) and np.all(many[ok] <= hi[ok])
    assert np.all(np.isfinite(lo) == ok)


def _room_errors(world, renderer, extractor, poses, seed=0):
    frames = renderer.render_many(poses, seed=seed)
    ranges = extractor.extract_many(np.stack([f.distance for f in frames]), np.stack([f.amplitude for f in frames]))
    h = extractor.settings.height
    errors, kinds = [], []
    for pose, r in zip(poses, ranges):
        bearings = extractor.angles + pose[2]  # robot bearing + θ = world bearing
        truth = world.horizontal_distance(pose[:2], bearings, h)
        directions = np.column_stack([np.cos(bearings), np.sin(bearings), np.zeros(360)])
        _, names = renderer.first_surface(np.tile([pose[0], pose[1], h], (360, 1)), directions)
        kinds.append([world.materials[n].kind if n else "none" for n in names])
        errors.append(r - truth)
    return np.concatenate(errors), np.concatenate(kinds)


def test_rendered_room_matches_true_wall_distances(extractor):
    """Static frames rendered in the matte-walled `room`: each bin's range against the exact
    horizontal distance to the nearest surface at the slice height (World.horizontal_distance)."""
    from omnitof.sim.render import Renderer
    from omnitof.sim.worlds import load_world

    world = load_world("room")
    renderer = Renderer(world)
    poses = np.array([[1.5, 1.5, 0.0], [4.5, 1.5, 1.2], [4.5, 3.0, -2.5], [2.2, 3.0, 3.0]])
    errors, kinds = _room_errors(world, renderer, extractor, poses)
    matte = kinds == "matte"
    seen = matte & np.isfinite(errors)
    assert matte.sum() > 1000
    assert seen.sum() / matte.sum() > 0.45  # the default rig covers ~60 % of bearings at all
    assert np.median(np.abs(errors[seen])) < 0.01
    assert np.mean(np.abs(errors[seen]) < 0.05) > 0.95
    # the metal cabinet sends mirrored, longer paths back: readings there are too long, not short
    metal = (kinds == "metal") & np.isfinite(errors)
    assert metal.sum() == 0 or np.median(errors[metal]) > -0.05


def test_errors_name_the_array(extractor):
    d = np.zeros((10, 10), np.float32)
    with pytest.raises(ScanInputError, match=r"distance must have shape \(144, 176\).*\(10, 10\)"):
        extractor.extract(d, d)
    good = np.zeros((144, 176), np.float32)
    with pytest.raises(ScanInputError, match="amplitude must have shape"):
        extractor.extract(good, good[:, :-1])
    with pytest.raises(ScanInputError, match="distances must have shape"):
        extractor.extract_many(good, good)
    with pytest.raises(ValueError):  # ScanInputError is a ValueError and an InputError too
        extractor.extract(good.astype(complex), good)
    assert issubclass(ScanInputError, InputError) and issubclass(ScanConfigError, ConfigError)


def test_bad_settings_and_rig():
    camera, mirrors = RIG.camera, RIG.mirrors
    labels = masks(camera, mirrors)
    with pytest.raises(ScanConfigError, match="statistic"):
        ScanExtractor(camera, mirrors, labels, camera_mount(), statistic="mean")
    with pytest.raises(ScanConfigError, match="band"):
        ScanExtractor(camera, mirrors, labels, camera_mount(), band=-1.0)
    with pytest.raises(ScanConfigError, match="labels must have"):
        ScanExtractor(camera, mirrors, labels[:-1], camera_mount())
    with pytest.raises(ScanConfigError, match="labels must lie"):
        ScanExtractor(camera, mirrors[:2], labels, camera_mount())
    assert ScanSettings(statistic="p25").quantile() == 0.25


def test_from_calibration_duck_typed_and_angles():
    camera, mirrors = RIG.camera, RIG.mirrors

    class Cal:
        pass

    cal = Cal()
    cal.camera, cal.planes = camera, [m.plane for m in mirrors]
    cal.labels, cal.robot_T_camera = masks(camera, mirrors), camera_mount()
    ex = ScanExtractor.from_calibration(cal, height=0.5)
    assert ex.settings.height == 0.5
    np.testing.assert_allclose(np.degrees(ex.angles), np.arange(360))


def test_scans_from_frames_exports_to_carmen_and_rosbag(tmp_path, extractor):
    from omnitof.io.carmen import read_carmen, write_carmen
    from omnitof.sim.render import Renderer
    from omnitof.sim.worlds import load_world

    poses = np.array([[1.5, 1.5, 0.0], [1.7, 1.5, 0.1], [1.9, 1.6, 0.2]])
    frames = Renderer(load_world("room")).render_many(poses, seed=0)
    odometry = poses + 0.01
    scans = scans_from_frames(extractor, frames, timestamps=np.arange(3) * 0.1, odometry=odometry, source="room")
    assert scans.ranges.shape == (3, 360) and np.all(scans.sensor_pose == 0.0)
    np.testing.assert_array_equal(scans.ground_truth, poses)
    assert not np.any(scans.ranges == 0) and not np.any(np.isnan(scans.ranges))
    write_carmen(tmp_path / "scan.log", scans)
    back = read_carmen(tmp_path / "scan.log").scans
    np.testing.assert_allclose(back.angles, scans.angles, atol=1e-9)
    finite = np.isfinite(scans.ranges)
    np.testing.assert_allclose(back.ranges[finite], scans.ranges[finite], atol=6e-4)
    assert np.all(~np.isfinite(back.ranges[~finite]))
    from omnitof.io.rosbag import read_laserscan_bag, write_laserscan_bag

    write_laserscan_bag(tmp_path / "bag", scans)
    bag = read_laserscan_bag(tmp_path / "bag")
    np.testing.assert_allclose(bag.ranges[finite], scans.ranges[finite], atol=1e-5)
    with pytest.raises(ScanInputError, match="odometry"):
        scans_from_frames(extractor, frames, timestamps=np.arange(3) * 0.1)


def test_plots_write_pngs(tmp_path, extractor, rays_robot):
    from omnitof.viz.scans import plot_scan, plot_slice_overlay

    distance, amplitude = _cylinder_frame(rays_robot, 2.0)
    ranges = extractor.extract(distance, amplitude)
    plot_scan(tmp_path / "scan.png", ranges, extractor.angles, truth=np.full(360, 2.0))
    plot_slice_overlay(tmp_path / "overlay.png", extractor, distance, amplitude)
    for name in ("scan.png", "overlay.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_points_lie_on_the_cylinder(extractor, rays_robot):
    distance, amplitude = _cylinder_frame(rays_robot, 2.5)
    pts = extractor.points(distance, amplitude)
    assert len(pts) > 10000
    np.testing.assert_allclose(np.hypot(pts[:, 0], pts[:, 1]), 2.5, atol=1e-6)
    assert pts[:, 2].min() < 0.0 < 1.0 < pts[:, 2].max()  # the whole cloud, not only the slice


def test_rays_start_on_the_mirrors_and_end_on_the_cylinder(extractor, rays_robot):
    o, _, _, labels = rays_robot
    distance, amplitude = _cylinder_frame(rays_robot, 3.0)
    origins, points = extractor.rays(distance, amplitude)
    assert origins.shape == points.shape and len(points) > 10000
    np.testing.assert_allclose(np.hypot(points[:, 0], points[:, 1]), 3.0, atol=1e-6)
    # every labelled pixel passes here, so the origins are the independent per-pixel mirror
    # points of mirrors.viewing_rays, in image order
    np.testing.assert_allclose(origins, o[labels >= 0], atol=1e-9)


def test_scan_settings_errors_name_the_field():
    from pydantic import ValidationError

    from omnitof.scan import scan_settings

    with pytest.raises(ScanConfigError, match=r"ScanSettings\.height"):
        scan_settings(height=-0.1)
    with pytest.raises(ScanConfigError, match=r"ScanSettings\.statistic"):
        scan_settings(statistic="p120")
    with pytest.raises(ValidationError):  # constructed directly, pydantic's own error
        ScanSettings(statistic="mean")
    assert scan_settings(ScanSettings(band=0.2), height=0.7) == ScanSettings(band=0.2, height=0.7)
