"""omnitof.sensor.mirrors: the reflection matrix D and virtual cameras of the paper's eq. 6 against
independent geometry, the 45° mirror analytically, the pyramid's faces and names, per-pixel
mirror assignment and masks (counted), viewing rays through the virtual centres, the figure."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest
from matplotlib.colors import to_rgb

from omnitof.sensor.camera import Camera
from omnitof.errors import ConfigError
from omnitof.sensor.mirrors import (
    ROBOT_R_CAMERA,
    Mirror,
    MirrorPlane,
    assign_pixels,
    bearing_of,
    camera_mount,
    direction_name,
    masks,
    project_via,
    pyramid,
    viewing_rays,
    virtual_cameras,
    virtual_centres,
)
from omnitof.viz.sensor import plot_mirror_regions

Z = np.array([0.0, 0.0, 1.0])


def ideal_camera() -> Camera:
    """A distortion-free pinhole whose principal point lies between pixel centres, so that no
    pixel centre sits exactly on an edge of the yaw-45° pyramid (the image axes through it)."""
    return Camera(176, 144, 200.0, 200.0, 87.3, 71.6)


def face(tilt_deg: float, e: np.ndarray, apex_height: float = 0.1) -> MirrorPlane:
    """A plane through (0, 0, apex_height) tilted tilt_deg from the optical axis that sends the
    optical axis towards the horizontal unit vector e (camera frame), built from a point and a
    normal rather than pyramid's formula."""
    t = math.radians(tilt_deg)
    # In-plane vectors: the horizontal perpendicular to e, and the line of steepest ascent.
    across = np.cross(Z, e)
    rising = math.sin(t) * e + math.cos(t) * Z
    return MirrorPlane.through(np.array([0.0, 0.0, apex_height]), np.cross(across, rising))


def random_plane(rng: np.random.Generator) -> MirrorPlane:
    normal = rng.normal(size=3)
    return MirrorPlane(normal, rng.uniform(0.05, 2.0) * np.linalg.norm(normal))


# --- eq. 6: D and the virtual camera ------------------------------------------------------


@pytest.mark.parametrize("seed", range(5))
def test_reflection_matrix_is_an_involution_that_fixes_the_plane(seed):
    rng = np.random.default_rng(seed)
    plane = random_plane(rng)
    D = plane.reflection_matrix()
    np.testing.assert_allclose(D @ D, np.eye(4), atol=1e-12)
    np.testing.assert_array_equal(D[3], [0, 0, 0, 1])
    assert np.linalg.det(D[:3, :3]) == pytest.approx(-1.0)  # a reflection, not a rotation
    # Points on the plane: d·n plus anything perpendicular to n.
    tangents = rng.normal(size=(20, 3))
    tangents -= np.outer(tangents @ plane.normal, plane.normal)
    on_plane = plane.d * plane.normal + tangents
    homogeneous = np.hstack([on_plane, np.ones((20, 1))])
    np.testing.assert_allclose((D @ homogeneous.T).T, homogeneous, atol=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_reflection_is_the_mirror_image_and_returns_after_two(seed):
    rng = np.random.default_rng(seed)
    plane = random_plane(rng)
    points = rng.uniform(-3, 3, size=(50, 3))
    images = plane.reflect_points(points)
    # Mirror image: the midpoint lies on the plane and the displacement is along the normal.
    np.testing.assert_allclose(((points + images) / 2) @ plane.normal, plane.d, atol=1e-12)
    displacement = images - points
    np.testing.assert_allclose(np.cross(displacement, plane.normal), 0.0, atol=1e-12)
    # Same result through the 4×4 D, and twice gives the point back.
    D = plane.reflection_matrix()
    via_D = (D @ np.hstack([points, np.ones((50, 1))]).T).T[:, :3]
    np.testing.assert_allclose(via_D, images, atol=1e-12)
    np.testing.assert_allclose(plane.reflect_points(images), points, atol=1e-12)


def test_d_is_the_papers_matrix_with_the_planes_offset_negated():
    # The paper writes the plane nᵀx + d_p = 0 and D with −2·d_p·n; ours is n·x = d, so
    # d_p = −d.
    plane = MirrorPlane(np.array([0.0, 0.6, 0.8]), 0.25)
    n, d_paper = plane.normal, -plane.d
    paper = np.block(
        [[np.eye(3) - 2 * np.outer(n, n), -2 * d_paper * n[:, None]], [np.zeros((1, 3)), 1.0]]
    )
    np.testing.assert_allclose(plane.reflection_matrix(), paper, atol=1e-15)


def test_plane_is_normalised_and_its_sign_convention_enforced():
    plane = MirrorPlane(np.array([0.0, 0.0, 2.0]), 1.0)
    np.testing.assert_allclose(plane.normal, Z)
    assert plane.d == pytest.approx(0.5)  # the same plane z = 0.5
    with pytest.raises(ConfigError, match="flip the sign"):
        MirrorPlane(np.array([0.0, 0.0, -1.0]), -0.5)  # z = 0.5 with the normal towards the camera
    flipped = MirrorPlane.through(np.array([0.0, 0.0, 0.5]), np.array([0.0, 0.0, -1.0]))
    np.testing.assert_allclose(flipped.normal, Z)
    assert flipped.signed_distance(np.zeros((1, 3)))[0] < 0  # the camera is on the reflective side


def sample_mirrored_points(camera: Camera, plane: MirrorPlane, n: int, seed: int):
    """(pixels, points): world points that the camera sees through `plane` at those pixels,
    built forwards: pixel → ray → hit → reflected ray → a point 0.3–6 m along it."""
    rng = np.random.default_rng(seed)
    pixels = rng.uniform([0, 0], [camera.width - 1, camera.height - 1], size=(n, 2))
    rays = camera.rays(pixels)
    hits = plane.intersect(np.zeros_like(rays), rays)
    assert hits.hit.all()
    points = hits.points + rng.uniform(0.3, 6.0, size=(n, 1)) * hits.directions
    return pixels, points, hits


def test_virtual_camera_projects_where_the_real_camera_sees_the_mirror_image():
    camera = ideal_camera()
    plane = face(45.0, np.array([0.0, -1.0, 0.0]))
    P = camera.K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    Pv = plane.virtual_camera(P)
    pixels, points, _ = sample_mirrored_points(camera, plane, 200, seed=3)
    homogeneous = (Pv @ np.hstack([points, np.ones((len(points), 1))]).T).T
    through_virtual = homogeneous[:, :2] / homogeneous[:, 2:]
    # Exactly where the real camera projects the mirror image D·X ...
    seen_image = camera.project(plane.reflect_points(points))
    np.testing.assert_allclose(through_virtual, seen_image, atol=1e-9)
    # ... which is the pixel whose ray, reflected in the mirror, passes through X.
    np.testing.assert_allclose(through_virtual, pixels, atol=1e-9)
    # The virtual camera's centre D·(0,0,0,1) is its null space.
    centre = np.append(plane.virtual_centre(), 1.0)
    np.testing.assert_allclose(plane.reflection_matrix() @ [0, 0, 0, 1], centre)
    np.testing.assert_allclose(Pv @ centre, 0.0, atol=1e-9)


def test_project_via_inverts_the_reflected_rays_through_a_distorted_lens():
    camera = Camera.sr4000()
    mirrors = pyramid(tilt_deg=52.0, camera=camera)
    labels = masks(camera, mirrors)
    rays = viewing_rays(camera, mirrors, labels)
    rng = np.random.default_rng(7)
    for index, mirror in enumerate(mirrors):
        rows, cols = np.nonzero(labels == index)
        pick = rng.choice(len(rows), 50, replace=False)
        r, c = rows[pick], cols[pick]
        points = rays.origins[r, c] + rng.uniform(0.3, 6.0, (50, 1)) * rays.directions[r, c]
        seen = project_via(camera, mirror, points)
        np.testing.assert_allclose(seen, np.stack([c, r], 1), atol=1e-6)
        # Behind the mirror (beyond its plane) nothing is seen through it.
        behind = rays.origins[r, c] - 0.5 * rays.directions[r, c] + 0.3 * mirror.plane.normal
        assert np.isnan(project_via(camera, mirror, behind)).all()


# --- rays and the 45° mirror --------------------------------------------------------------


def test_optical_axis_leaves_a_45_degree_mirror_horizontally():
    plane = face(45.0, np.array([1.0, 0.0, 0.0]), apex_height=0.2)
    point, direction = plane.reflect_ray(np.zeros(3), Z)
    np.testing.assert_allclose(point, [0.0, 0.0, 0.2], atol=1e-15)
    np.testing.assert_allclose(direction, [1.0, 0.0, 0.0], atol=1e-15)


@pytest.mark.parametrize("tilt", [40.0, 45.0, 52.0, 60.0])
@pytest.mark.parametrize("theta", [-15.0, 0.0, 10.0, 25.0])
def test_elevation_of_a_reflected_ray_is_theta_plus_90_minus_twice_the_tilt(tilt, theta):
    # In the mirror's plane of symmetry a ray θ off the axis (towards the face) leaves at
    # elevation θ + 90° − 2·tilt: each degree of tilt lowers the view by two.
    plane = face(tilt, np.array([1.0, 0.0, 0.0]))
    t = math.radians(theta)
    _, direction = plane.reflect_ray(np.zeros(3), np.array([math.sin(t), 0.0, math.cos(t)]))
    assert direction[1] == pytest.approx(0.0, abs=1e-15)
    elevation = math.degrees(math.atan2(direction[2], direction[0]))
    assert elevation == pytest.approx(theta + 90.0 - 2.0 * tilt, abs=1e-12)


def test_intersect_hits_only_from_the_reflective_side_and_measures_metres():
    plane = MirrorPlane(Z, 1.0)  # z = 1, reflective below
    origins = np.array([[0, 0, 0], [0, 0, 0], [0, 0, 2], [0, 0, 1], [0.5, 0, 0.5]], float)
    directions = np.array([[0, 0, 3], [0, 0, -1], [0, 0, -1], [0, 0, 1], [1, 0, 1]], float)
    hits = plane.intersect(origins, directions)
    np.testing.assert_array_equal(hits.hit, [True, False, False, False, True])
    np.testing.assert_allclose(hits.distances[[0, 4]], [1.0, math.sqrt(0.5)])
    np.testing.assert_allclose(hits.points[4], [1.0, 0.0, 1.0])
    np.testing.assert_allclose(hits.directions[4], [math.sqrt(0.5), 0.0, -math.sqrt(0.5)])
    assert np.isnan(hits.points[1:4]).all() and np.isnan(hits.directions[1:4]).all()
    assert plane.reflect_ray(np.zeros(3), -Z) is None


def test_mirror_contains_its_convex_outline_and_rejects_bad_ones():
    plane = MirrorPlane(Z, 1.0)
    square = np.array([[0, 0, 1], [2, 0, 1], [2, 1, 1], [0, 1, 1]], float)
    mirror = Mirror(plane, square, "square")
    points = np.array([[1, 0.5, 1], [0, 0.5, 1], [2, 1, 1], [2.01, 0.5, 1], [1, -0.01, 1]], float)
    np.testing.assert_array_equal(mirror.contains(points), [True, True, True, False, False])
    clockwise = Mirror(plane, square[::-1], "clockwise")
    np.testing.assert_array_equal(clockwise.contains(points), mirror.contains(points))
    hits = mirror.intersect(np.array([[1.0, 0.5, 0.0], [3.0, 0.5, 0.0]]), np.array([Z, Z]))
    np.testing.assert_array_equal(hits.hit, [True, False])
    with pytest.raises(ConfigError, match="convex"):
        Mirror(plane, square[[0, 2, 1, 3]], "bow-tie")
    with pytest.raises(ConfigError, match="off its plane"):
        Mirror(plane, square + [0, 0, 0.1], "lifted")


# --- the pyramid --------------------------------------------------------------------------


def test_mount_turns_the_camera_so_the_image_top_looks_forward():
    mount = camera_mount(0.5)
    np.testing.assert_allclose(mount[:3, :3], ROBOT_R_CAMERA)
    np.testing.assert_allclose(mount @ [0, 0, 0, 1], [0, 0, 0.5, 1])  # optical centre
    np.testing.assert_allclose(mount[:3, :3] @ [0, -1, 0], [1, 0, 0])  # image up → forward
    np.testing.assert_allclose(mount[:3, :3] @ [1, 0, 0], [0, 1, 0])  # image right → left
    np.testing.assert_allclose(mount[:3, :3] @ Z, Z)
    assert np.linalg.det(mount[:3, :3]) == pytest.approx(1.0)


@pytest.mark.parametrize(
    ("n", "yaw", "names"),
    [
        (4, 45.0, ["front-left", "back-left", "back-right", "front-right"]),
        (4, 0.0, ["front", "left", "back", "right"]),
        (3, 90.0, ["left", "back-right", "front-right"]),
        (
            8,
            0.0,
            ["front", "front-left", "left", "back-left", "back", "back-right", "right",
             "front-right"],
        ),
    ],
)
def test_pyramid_faces_are_named_after_the_bearing_they_look_at(n, yaw, names):
    mirrors = pyramid(n, 45.0, yaw_deg=yaw, size=0.2)
    assert [m.name for m in mirrors] == names
    for k, mirror in enumerate(mirrors):
        expected = (yaw + 360.0 * k / n) % 360.0
        assert bearing_of(mirror) == pytest.approx(expected, abs=1e-9)
        # At 45° the optical axis leaves the face horizontally, towards that bearing.
        out = ROBOT_R_CAMERA @ mirror.plane.reflect_directions(Z[None])[0]
        b = math.radians(expected)
        np.testing.assert_allclose(out, [math.cos(b), math.sin(b), 0.0], atol=1e-12)
    assert direction_name(359.0) == "front" and direction_name(200.0) == "back"


@pytest.mark.parametrize("tilt", [40.0, 45.0, 55.0])
def test_pyramid_faces_meet_at_the_apex_and_share_their_edges(tilt):
    apex_height, size = 0.12, 0.15
    mirrors = pyramid(5, tilt, apex_height, size, yaw_deg=10.0)
    apex = np.array([0.0, 0.0, apex_height])
    for k, mirror in enumerate(mirrors):
        np.testing.assert_allclose(mirror.polygon[0], apex)
        # Tilted `tilt` from the optical axis: the normal is tilt away from the horizontal.
        assert mirror.plane.normal[2] == pytest.approx(math.sin(math.radians(tilt)))
        np.testing.assert_allclose(mirror.polygon[2], mirrors[(k + 1) % 5].polygon[1], atol=1e-12)
        middle = (mirror.polygon[1] + mirror.polygon[2]) / 2
        assert math.hypot(middle[0], middle[1]) == pytest.approx(size)


def test_pyramid_rejects_bad_parameters():
    for kwargs in ({"n_mirrors": 2}, {"tilt_deg": 90.0}, {"apex_height": 0.0}, {"size": -1.0}):
        with pytest.raises(ConfigError):
            pyramid(**kwargs)
    tilted = camera_mount()
    tilted[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]
    with pytest.raises(ConfigError, match="straight up"):
        pyramid(robot_T_camera=tilted)


def test_default_size_just_fills_the_view():
    camera = Camera.sr4000()
    mirrors = pyramid(tilt_deg=55.0, camera=camera)
    assert (assign_pixels(camera, mirrors) >= 0).all()
    size = math.hypot(*((mirrors[0].polygon[1] + mirrors[0].polygon[2]) / 2)[:2])
    smaller = pyramid(tilt_deg=55.0, size=0.97 * size, camera=camera)
    assert (assign_pixels(camera, smaller) < 0).any()


# --- pixels and mirrors -------------------------------------------------------------------


def test_each_quadrant_centre_sees_its_diagonal_mirror():
    camera = Camera.sr4000()
    mirrors = pyramid(camera=camera)  # yaw 45°: the image axes through (cx, cy) split the mirrors
    labels = assign_pixels(camera, mirrors)
    left_u, right_u = int(camera.cx / 2), int((camera.cx + camera.width) / 2)
    top_v, bottom_v = int(camera.cy / 2), int((camera.cy + camera.height) / 2)
    expected = {  # image top = robot front, image right = robot left
        (top_v, right_u): "front-left",
        (top_v, left_u): "front-right",
        (bottom_v, left_u): "back-right",
        (bottom_v, right_u): "back-left",
    }
    for (v, u), name in expected.items():
        assert mirrors[labels[v, u]].name == name


def entry_into_pyramid(
    rays: np.ndarray, planes: list[MirrorPlane]
) -> tuple[np.ndarray, np.ndarray]:
    """Independent of Mirror.contains: where rays enter the infinite pyramid solid (the
    intersection of the faces' far sides), (face index, entry point); face −1 if never."""
    t = np.full((len(rays), len(planes)), np.inf)
    for k, plane in enumerate(planes):
        approach = rays @ plane.normal
        t[:, k] = np.where(approach > 0, plane.d / np.where(approach > 0, approach, 1), np.inf)
    entry = t.max(axis=1)
    index = np.where(np.isfinite(entry), t.argmax(axis=1), -1)
    return index, rays * np.where(np.isfinite(entry), entry, np.nan)[:, None]


@pytest.mark.parametrize("tilt", [45.0, 55.0])
def test_pixels_beyond_the_pyramid_see_no_mirror(tilt):
    camera, apex_height, size = Camera.sr4000(), 0.1, 0.05
    mirrors = pyramid(4, tilt, apex_height, size, camera=camera)
    labels = assign_pixels(camera, mirrors).ravel()
    rays = camera.pixel_grid_rays().reshape(-1, 3)
    index, entry = entry_into_pyramid(rays, [m.plane for m in mirrors])
    # On a face, the distance out from the axis along its looking direction is
    # (height − apex_height)·tan(tilt); beyond `size` the ray passes the pyramid's rim.
    outward = (entry[:, 2] - apex_height) * math.tan(math.radians(tilt))
    expected = np.where((index >= 0) & (outward <= size), index, -1)
    np.testing.assert_array_equal(labels, expected)
    assert (labels == -1).sum() > 1000 and (labels >= 0).sum() > 1000


@pytest.mark.parametrize("margin", [1, 2, 3])
def test_masks_drop_a_band_of_margin_pixels_on_each_side_of_the_edges(margin):
    camera = ideal_camera()
    mirrors = pyramid(tilt_deg=55.0, camera=camera)  # edges: the column and row through (cx, cy)
    labels = assign_pixels(camera, mirrors)
    assert (labels >= 0).all()
    np.testing.assert_array_equal(masks(camera, mirrors, 0), labels)
    h, w = camera.shape
    # margin columns each side of the vertical edge, margin rows each side of the horizontal.
    expected = 2 * margin * h + 2 * margin * w - (2 * margin) ** 2
    assert (masks(camera, mirrors, margin) < 0).sum() == expected


def test_masks_keep_only_pixels_whose_whole_neighbourhood_sees_the_same_mirror():
    camera, margin = Camera.sr4000(), 2
    mirrors = pyramid(tilt_deg=50.0, size=0.06, camera=camera)
    labels = assign_pixels(camera, mirrors)
    kept = masks(camera, mirrors, margin)
    assert ((kept == labels) | (kept == -1)).all()
    h, w = camera.shape
    padded = np.pad(labels, margin, constant_values=-2)  # -2: outside the image, no boundary
    uniform = np.ones(labels.shape, bool)
    for dv in range(-margin, margin + 1):
        for du in range(-margin, margin + 1):
            if dv * dv + du * du <= margin * margin:
                other = padded[margin + dv : margin + dv + h, margin + du : margin + du + w]
                uniform &= (other == labels) | (other == -2)
    np.testing.assert_array_equal(kept >= 0, uniform & (labels >= 0))


def test_reflected_rays_pass_through_the_virtual_camera_centres():
    camera = Camera.sr4000()
    mirrors = pyramid(tilt_deg=50.0, camera=camera)
    rays = viewing_rays(camera, mirrors)
    centres = virtual_centres(mirrors)
    for k, mirror in enumerate(mirrors):
        sel = rays.labels == k
        origins, directions = rays.origins[sel], rays.directions[sel]
        np.testing.assert_allclose(origins @ mirror.plane.normal, mirror.plane.d, atol=1e-12)
        assert mirror.contains(origins).all()
        np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0, atol=1e-12)
        # Back along the ray from the mirror lies the camera's mirror image.
        np.testing.assert_allclose(np.cross(origins - centres[k], directions), 0.0, atol=1e-12)
        assert np.einsum("ij,ij->i", origins - centres[k], directions).min() > 0
    assert np.isnan(rays.directions[rays.labels < 0]).all()
    for Pv, centre in zip(virtual_cameras(camera, mirrors), centres):
        np.testing.assert_allclose(Pv @ np.append(centre, 1.0), 0.0, atol=1e-9)


def test_region_figure_colours_and_names_each_mirror(tmp_path: Path):
    camera = Camera.sr4000()
    mirrors = pyramid(tilt_deg=52.0, camera=camera)
    path = tmp_path / "regions.png"
    fig = plot_mirror_regions(path, camera, mirrors, dpi=100)
    image = matplotlib.image.imread(path)
    ax = fig.axes[0]
    assert sorted(t.get_text() for t in ax.texts) == sorted(m.name.upper() for m in mirrors)
    labels = masks(camera, mirrors)
    for k in range(len(mirrors)):
        # A pixel of the region a little away from the label's box.
        text = np.array(ax.texts[k].get_position())
        rows, cols = np.nonzero(labels == k)
        far = np.hypot(cols - text[0], rows - text[1])
        pick = int(np.argmin(np.abs(far - 25)))
        x, y = ax.transData.transform((cols[pick], rows[pick]))
        rgb = image[int(round(image.shape[0] - y)), int(round(x)), :3]
        np.testing.assert_allclose(rgb, to_rgb(f"C{k}"), atol=0.02)
    amplitude = np.random.default_rng(0).random(camera.shape)
    plot_mirror_regions(tmp_path / "over.png", camera, mirrors, image=amplitude)
    assert (tmp_path / "over.png").stat().st_size > 0


def test_a_mount_typed_to_five_decimals_is_snapped_to_a_rotation_and_a_skewed_one_refused():
    from omnitof.scan.extract import ScanExtractor
    from omnitof.sensor.design import default_rig
    from omnitof.sensor.mirrors import MirrorParameterError, camera_mount, rigid_mount

    c = round(math.cos(math.pi / 4), 5)  # a 45° yaw written as 0.70711: RᵀR is 9e-6 off I
    typed = np.array([[c, -c, 0, 0], [c, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]) @ camera_mount()
    exact = rigid_mount(typed)
    np.testing.assert_allclose(exact[:3, :3].T @ exact[:3, :3], np.eye(3), atol=1e-15)
    np.testing.assert_allclose(exact, typed, atol=1e-5)
    # The core's renderer and multipath compensation allow 1e-6: the typed mount reaches them exact.
    rig = default_rig()
    ScanExtractor(rig.camera, list(rig.planes), rig.masks(1.0), typed, multipath={"enabled": True})
    for bad, message in [(np.diag([1.0, 1.0, 1.01, 1.0]), "RᵀR is 0.0201 off I"),
                         (np.diag([1.0, 1.0, -1.0, 1.0]), "det -1"),
                         (np.vstack([np.eye(4)[:3], [0, 0, 1, 1]]), "last row must be 0 0 0 1")]:
        with pytest.raises(MirrorParameterError, match=message):
            rigid_mount(bad)
