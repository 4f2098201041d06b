"""The ToF renderer (omnitof.sim.render, rust/src/render.rs) against independent computations:
unfolded mirror paths worked out here with omnitof.sensor.mirrors, the virtual camera of eq. 6, mixed
pixels, glass, metal, grids, phase wrapping, and the distance noise of a matte wall."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnitof.sensor.design import default_rig
from omnitof.sensor.mirrors import assign_pixels, camera_mount
from omnitof.sim.render import AMBIENT_REFERENCE_ALBEDO, RenderConfigError, Renderer, RenderSettings
from omnitof.sim.worlds import load_world, parse_world
from omnitof.sensor.tof import SensorNoise, decode, phase_to_distance, unambiguous_range

CAMERA, MIRRORS = default_rig().camera, default_rig().mirrors
MOUNT = camera_mount()
SENSOR = SensorNoise()
RANGE = unambiguous_range(SENSOR.f_mod)
ORIGIN = np.zeros(3)  # robot pose (0, 0, 0): the robot frame is the world frame
BLACK = {"kind": "matte", "albedo": 0.0}


def world(walls=(), boxes=(), materials=None, ceiling=3.0, **extra):
    """A world from plain data; walls given as (x0, y0, x1, y1, material)."""
    return parse_world({
        "name": "test",
        "ceiling_height": ceiling,
        "materials": materials or {},
        "walls": [{"points": [[w[0], w[1]], [w[2], w[3]]], "material": w[4]} for w in walls],
        "boxes": list(boxes),
        **extra,
    })


def wall_across_x(x: float, material: str = "wall") -> tuple:
    """A wall across the whole view, facing the robot at the origin, at x metres."""
    return (x, -30.0, x, 30.0, material)


def renderer(w, **settings) -> Renderer:
    return Renderer(w, camera=CAMERA, mirrors=MIRRORS, settings=RenderSettings(**settings))


def clean_distance(phasor: np.ndarray) -> np.ndarray:
    """Noise-free distance of phasors, decoded here (not via the renderer or tof.decode)."""
    return phase_to_distance(np.mod(np.angle(phasor.astype(np.complex128)), 2 * math.pi), SENSOR.f_mod)


def wrapped_error(distance: np.ndarray, path: np.ndarray) -> np.ndarray:
    """distance − path folded into [−R/2, R/2) for the unambiguous range R (phase wraps)."""
    return np.mod(distance - path + RANGE / 2, RANGE) - RANGE / 2


def central_rays():
    """Per pixel of the default rig at pose ORIGIN: the mirror label, the path from the camera
    to the mirror, and the reflected ray in the world (origin, unit direction), from
    omnitof.sensor.mirrors; pixels that see no mirror are NaN."""
    labels = assign_pixels(CAMERA, MIRRORS)
    rays = CAMERA.pixel_grid_rays()
    h, w = labels.shape
    to_mirror = np.full((h, w), np.nan)
    origin = np.full((h, w, 3), np.nan)
    direction = np.full((h, w, 3), np.nan)
    for k, mirror in enumerate(MIRRORS):
        sel = labels == k
        hits = mirror.plane.intersect(np.zeros((sel.sum(), 3)), rays[sel])
        to_mirror[sel] = hits.distances
        origin[sel] = hits.points @ MOUNT[:3, :3].T + MOUNT[:3, 3]
        direction[sel] = hits.directions @ MOUNT[:3, :3].T
    return labels, rays, to_mirror, origin, direction


LABELS, RAYS, TO_MIRROR, RAY_O, RAY_D = central_rays()


def first_plane(x_planes, ceiling, origin=RAY_O, direction=RAY_D):
    """Ray length to the first of the planes x = c (c in x_planes), z = 0 and z = ceiling;
    returns (length, index of the plane: 0.. for x_planes, −1 floor, −2 ceiling, −3 none)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        candidates = []
        for c in x_planes:
            t = (c - origin[..., 0]) / direction[..., 0]
            # The walls of wall_across_x end at |y| = 30 m.
            candidates.append(np.where(np.abs(origin[..., 1] + t * direction[..., 1]) < 29.9, t, np.inf))
        candidates += [-origin[..., 2] / direction[..., 2], (ceiling - origin[..., 2]) / direction[..., 2]]
        stack = np.stack(candidates)
        stack = np.where(stack > 1e-9, stack, np.inf)
    index = np.argmin(np.nan_to_num(stack, nan=np.inf), axis=0)
    length = np.min(np.nan_to_num(stack, nan=np.inf), axis=0)
    which = np.where(index < len(x_planes), index, len(x_planes) - 1 - index)
    return length, np.where(np.isfinite(length), which, -3)


def sub_ray_paths(r: Renderer):
    """Per pixel and sub-ray at pose ORIGIN: (path length camera → mirror → first surface,
    material name), traced here with omnitof.sensor.mirrors and the renderer's first-surface cast."""
    h, w, s, _ = r.directions.shape
    v = r.directions.reshape(-1, 3)
    best = np.full(len(v), np.inf)
    points = np.zeros_like(v)
    reflected = v.copy()
    for mirror in MIRRORS:
        hits = mirror.intersect(np.zeros_like(v), v)
        nearer = hits.hit & (hits.distances < best)
        best[nearer] = hits.distances[nearer]
        points[nearer] = hits.points[nearer]
        reflected[nearer] = hits.directions[nearer]
    best[~np.isfinite(best)] = 0.0  # past the mirrors: straight from the camera centre
    t, names = r.first_surface(points @ MOUNT[:3, :3].T + MOUNT[:3, 3], reflected @ MOUNT[:3, :3].T)
    return (best + t).reshape(h, w, s), names.reshape(h, w, s)


# --- through a mirror: eq. 6 ------------------------------------------------------------------


def test_wall_through_a_mirror_reads_the_unfolded_path_and_back_projects_onto_it():
    x_wall, ceiling = 3.0, 3.0
    r = renderer(world([wall_across_x(x_wall)], ceiling=ceiling), sub_rays=1)
    distance = clean_distance(r.phasors(ORIGIN).phasor[0])
    length, which = first_plane([x_wall], ceiling)
    z_at_wall = RAY_O[..., 2] + length * RAY_D[..., 2]
    unfolded = TO_MIRROR + length
    on_wall = (which == 0) & (z_at_wall > 0.05) & (z_at_wall < ceiling - 0.05) & (unfolded < RANGE - 0.05)
    assert on_wall.sum() > 1000
    np.testing.assert_allclose(distance[on_wall], unfolded[on_wall], atol=2e-5)

    # Back-projection through the virtual camera: the camera sees the point D·X along its own
    # pixel ray at the measured distance, so X = D·(distance · ray) (D = D⁻¹) lies on the wall.
    for k, mirror in enumerate(MIRRORS):
        sel = on_wall & (LABELS == k)
        if not sel.any():
            continue
        seen = distance[sel, None] * RAYS[sel]
        point = mirror.plane.reflect_points(seen)
        world_point = point @ MOUNT[:3, :3].T + MOUNT[:3, 3]
        np.testing.assert_allclose(world_point[:, 0], x_wall, atol=2e-5)
        # And the virtual camera Pv = P·D maps that point to the pixel's (undistorted) ray.
        pv = mirror.virtual_camera(CAMERA.K @ np.hstack([np.eye(3), np.zeros((3, 1))]))
        image = np.hstack([point, np.ones((len(point), 1))]) @ pv.T
        expected = RAYS[sel] @ CAMERA.K.T
        np.testing.assert_allclose(image[:, :2] / image[:, 2:], expected[:, :2] / expected[:, 2:], atol=1e-6)


def test_beyond_the_unambiguous_range_the_distance_wraps():
    x_wall, ceiling = 9.0, 6.0
    r = renderer(world([wall_across_x(x_wall)], ceiling=ceiling), sub_rays=1)
    distance = clean_distance(r.phasors(ORIGIN).phasor[0])
    length, which = first_plane([x_wall], ceiling)
    unfolded = TO_MIRROR + length
    far = (which == 0) & (unfolded > RANGE + 0.5) & (unfolded < 2 * RANGE)
    assert far.sum() > 500
    np.testing.assert_allclose(distance[far], unfolded[far] - RANGE, atol=2e-5)


# --- mixed pixels --------------------------------------------------------------------------------


def test_pixels_across_depth_and_pyramid_edges_read_between_their_surfaces():
    # A room with a pillar in front: its edges and the pyramid's edges straddle surfaces.
    w = world(
        walls=[(4.0, -3.0, 4.0, 3.0, "wall"), (4.0, 3.0, -3.0, 3.0, "wall"),
               (-3.0, 3.0, -3.0, -3.0, "wall"), (-3.0, -3.0, 4.0, -3.0, "wall")],
        boxes=[{"centre": [1.8, 0.4], "size": [0.4, 0.8], "height": 3.0}],
    )
    r = renderer(w, sub_rays=4, max_bounces=0)
    distance = clean_distance(r.phasors(ORIGIN).phasor[0])
    paths, _ = sub_ray_paths(r)
    low, high = paths.min(axis=2), paths.max(axis=2)
    # Sub-rays of one pixel less than π apart in phase (paths < c/(4f) apart): the mean phasor's
    # phase lies between theirs.
    mixed = (high - low > 0.5) & (high - low < RANGE / 2)
    plain = high - low < 0.01
    assert mixed.sum() > 50 and plain.sum() > 0.8 * plain.size
    inside = (distance[mixed] > low[mixed] + 0.01) & (distance[mixed] < high[mixed] - 0.01)
    assert inside.mean() > 0.97
    np.testing.assert_allclose(distance[plain], paths[plain].mean(axis=1), atol=0.01)


# --- materials -----------------------------------------------------------------------------------


def test_glass_shows_the_wall_behind_it():
    plain = renderer(world([wall_across_x(3.0)]), sub_rays=1)
    glazed = renderer(world([wall_across_x(1.5, "glass"), wall_across_x(3.0)]), sub_rays=1)
    back, which = first_plane([3.0], 3.0)
    length, _ = first_plane([1.5], 3.0)
    z = RAY_O[..., 2] + back * RAY_D[..., 2]
    # Through the glass onto the back wall, within the unambiguous range.
    sel = (which == 0) & (z > 0.1) & (z < 2.9) & (TO_MIRROR + back < RANGE - 0.1)
    assert sel.sum() > 1000
    p_plain, p_glass = plain.phasors(ORIGIN).phasor[0][sel], glazed.phasors(ORIGIN).phasor[0][sel]
    d_plain, d_glass = clean_distance(p_plain), clean_distance(p_glass)
    d_pane = (TO_MIRROR + length)[sel]
    # The pane's weak scatter pulls the reading a few centimetres towards it.
    assert np.median(np.abs(d_glass - d_plain)) < 0.06
    assert np.all(np.abs(d_glass - d_pane) > 0.8)
    # Most light passes twice: amplitude ≈ transmission² of the wall's.
    assert np.median(np.abs(p_glass) / np.abs(p_plain)) == pytest.approx(0.88**2, abs=0.05)


def test_metal_gives_the_mirrored_world():
    polished = {"polished": {"kind": "metal", "albedo": 0.0, "specular": 0.9}}
    w = world([wall_across_x(1.0, "polished"), wall_across_x(-2.5)], materials=polished)
    distance = clean_distance(renderer(w, sub_rays=1).phasors(ORIGIN).phasor[0])
    # Unfolded: the wall 3.5 m behind the robot appears 3.5 m beyond the metal, at x = 4.5.
    metal, which_metal = first_plane([1.0], 3.0)
    mirrored, which = first_plane([4.5], 3.0)
    z_metal = RAY_O[..., 2] + metal * RAY_D[..., 2]
    sel = (which_metal == 0) & (which == 0) & (z_metal > 0.05) & (z_metal < 2.95)
    sel &= TO_MIRROR + mirrored < RANGE - 0.05
    assert sel.sum() > 500
    np.testing.assert_allclose(distance[sel], (TO_MIRROR + mirrored)[sel], atol=2e-5)
    assert np.all(distance[sel] > (TO_MIRROR + metal)[sel] + 3.0)


def test_metal_alone_returns_only_its_weak_diffuse_part():
    front, which = first_plane([2.0], 3.0)
    z = RAY_O[..., 2] + front * RAY_D[..., 2]
    sel = (which == 0) & (z > 0.05) & (z < 2.95)
    metal = renderer(world([wall_across_x(2.0, "metal")]), sub_rays=1, max_bounces=0)
    matte = renderer(world([wall_across_x(2.0, "wall")]), sub_rays=1, max_bounces=0)
    ratio = np.abs(metal.phasors(ORIGIN).phasor[0][sel]) / np.abs(matte.phasors(ORIGIN).phasor[0][sel])
    # Default metal scatters 0.05 against the wall's 0.6: a reading an amplitude filter drops.
    np.testing.assert_allclose(ratio, 0.05 / 0.6, rtol=1e-4)


def test_metal_door_in_the_building_reads_far_from_itself_or_weakly():
    # In front of the metal door at x = 19.67 in the south corridor, facing it.
    w = load_world("corridor1")
    r = renderer(w, sub_rays=1)
    pose = np.array([19.67, 1.085, math.pi / 2])
    ph = r.phasors(pose)
    distance, amplitude = clean_distance(ph.phasor[0]), np.abs(ph.phasor[0])
    # Pixels of the front mirror whose central ray meets the door leaf (robot frame → world).
    c, s = math.cos(pose[2]), math.sin(pose[2])
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    o = RAY_O @ rot.T + [pose[0], pose[1], 0.0]
    d = RAY_D @ rot.T
    t, names = r.first_surface(np.nan_to_num(o).reshape(-1, 3), d.reshape(-1, 3))
    on_door = (names.reshape(LABELS.shape) == "metal") & (LABELS >= 0)
    assert on_door.sum() > 200
    door_distance = (TO_MIRROR + t.reshape(LABELS.shape))[on_door]
    # A matte wall there would give amplitude_at_1m · 0.6 · 0.81 · cos / r²; the door's
    # readings are either far from the door (the mirrored corridor) or much weaker.
    expected_matte = SENSOR.amplitude_at_1m * 0.6 * 0.81 / door_distance**2
    wrong = np.abs(distance[on_door] - door_distance) > 0.2
    weak = amplitude[on_door] < 0.3 * expected_matte
    assert np.mean(wrong | weak) > 0.95


def test_a_grid_returns_only_where_its_bars_are():
    materials = {"black": BLACK, "bars": {"kind": "matte", "albedo": 0.3},
                 "grid": {"kind": "grid", "albedo": 0.3, "coverage": 0.3, "pitch": 0.1}}
    dark = {"floor_material": "black", "ceiling_material": "black"}
    grid = renderer(world([wall_across_x(2.0, "grid"), wall_across_x(6.0, "black")], materials=materials, **dark))
    solid = renderer(world([wall_across_x(2.0, "bars"), wall_across_x(6.0, "black")], materials=materials, **dark))
    front, which = first_plane([2.0], 3.0)
    z = RAY_O[..., 2] + front * RAY_D[..., 2]
    sel = (which == 0) & (z > 0.1) & (z < 2.9)
    share = grid.phasors(ORIGIN).active_offset[0][sel] / solid.phasors(ORIGIN).active_offset[0][sel]
    assert share.mean() == pytest.approx(0.3, abs=0.03)  # the grid's coverage
    assert np.mean(share < 1e-6) > 0.2  # pixels that see only holes: no return at all
    assert np.mean(share > 1 - 1e-6) > 0.05  # pixels on bars
    assert np.mean((share > 0.05) & (share < 0.95)) > 0.1  # partial returns


def test_ambient_offset_follows_the_seen_albedo_through_the_mirror():
    r = renderer(world([wall_across_x(3.0)], floor_material="wall", ceiling_material="wall"), sub_rays=1)
    ambient = r.phasors(ORIGIN).ambient[0]
    seen = LABELS >= 0
    expected = SENSOR.ambient * 0.6 * 0.9 / AMBIENT_REFERENCE_ALBEDO  # albedo 0.6, mirror 0.9
    np.testing.assert_allclose(ambient[seen], expected, rtol=1e-6)


# --- realism -----------------------------------------------------------------------------------


def wall_noise(path: float, frames: int = 300) -> tuple[float, float, float]:
    """(measured σ_d, predicted σ_d, mean amplitude) over the pixels that see an albedo-0.5
    wall square on, `path` metres away through the front mirror."""
    matte = {"paint": {"kind": "matte", "albedo": 0.5}}
    front = LABELS == int(np.argmax([np.mean(RAY_D[LABELS == k][:, 0]) for k in range(len(MIRRORS))]))
    square = front & (RAY_D[..., 0] > math.cos(math.radians(3.0)))
    x = path - float(np.median((TO_MIRROR + 0.0)[square] - RAY_O[square][:, 0]))
    r = renderer(world([wall_across_x(x, "paint")], materials=matte), sub_rays=4)
    ph = r.phasors(ORIGIN)
    p, amb, act = ph.phasor[0][square], ph.ambient[0][square], ph.active_offset[0][square]
    distances, amplitudes, offsets = [], [], []
    for seed in range(frames):
        a0, a1, a2, a3, sat = SENSOR.synthesise(p, amb, rng=seed, active_offset=act)
        frame = decode(a0, a1, a2, a3, SENSOR.f_mod)
        distances.append(frame.distance)
        amplitudes.append(frame.amplitude)
        offsets.append(frame.offset)
    measured = float(np.median(np.std(np.array(distances, dtype=np.float64), axis=0)))
    amp, off = float(np.mean(amplitudes)), float(np.mean(offsets))
    predicted = float(SENSOR.distance_noise_std(amp, off))
    return measured, predicted, amp


def test_distance_noise_on_a_matte_wall_is_about_a_centimetre_at_two_metres():
    sigma2, predicted2, amp2 = wall_noise(2.0)
    sigma4, predicted4, amp4 = wall_noise(4.0)
    print(f"matte wall (albedo 0.5) through a mirror: 2 m: σ = {1000 * sigma2:.1f} mm "
          f"(A = {amp2:.0f}); 4 m: σ = {1000 * sigma4:.1f} mm (A = {amp4:.0f})")
    assert 0.007 < sigma2 < 0.015
    assert sigma2 == pytest.approx(predicted2, rel=0.15)
    assert sigma4 == pytest.approx(predicted4, rel=0.15)
    # The amplitude falls as 1/r² and the noise grows with it.
    assert amp4 == pytest.approx(amp2 / 4, rel=0.05)
    assert sigma4 > 2.5 * sigma2


# --- the renderer as a tool ----------------------------------------------------------------------


def test_renderer_cast_matches_the_plan_ground_truth_in_a_real_world():
    w = load_world("corridor1")
    r = renderer(w, sub_rays=1)
    rng = np.random.default_rng(3)
    xmin, xmax, ymin, ymax = w.bounds
    xy = np.column_stack([rng.uniform(xmin, xmax, 3000), rng.uniform(ymin, ymax, 3000)])
    bearing = rng.uniform(-math.pi, math.pi, 3000)
    height = 0.45
    t, _ = r.first_surface(np.column_stack([xy, np.full(3000, height)]),
                           np.column_stack([np.cos(bearing), np.sin(bearing), np.zeros(3000)]))
    want = np.array([w.horizontal_distance(p, b, height) for p, b in zip(xy, bearing)])
    np.testing.assert_allclose(t, want, atol=1e-9)


def test_same_frames_for_any_thread_count_and_seed_controls_the_jitter():
    w = load_world("corridor2")
    poses = np.array([[4.5, 1.085, 0.0], [13.0, 10.0, math.pi / 2]])
    one = renderer(w, threads=1).phasors(poses)
    two = renderer(w, threads=2).phasors(poses)
    assert np.array_equal(one.phasor, two.phasor) and np.array_equal(one.active_offset, two.active_offset)
    other = renderer(w, threads=2, seed=1).phasors(poses)
    assert not np.array_equal(one.phasor, other.phasor)
    single = renderer(w, threads=2).phasors(poses[1])
    assert np.array_equal(single.phasor[0], one.phasor[1])


def test_frames_decode_their_own_samples():
    r = renderer(load_world("room"))
    frames = r.render_many(np.array([[1.5, 1.5, 0.0], [4.5, 3.0, 1.0]]), seed=5)
    assert len(frames) == 2
    frame = frames[1]
    assert frame.phasor.shape == CAMERA.shape and frame.samples.shape == (4, *CAMERA.shape)
    assert frame.samples.dtype == np.float32 and frame.distance.dtype == np.float32
    again = decode(*frame.samples, SENSOR.f_mod)
    np.testing.assert_array_equal(again.distance, frame.distance)
    assert np.all((frame.distance >= 0) & (frame.distance < RANGE))
    # Frame i depends only on (seed, i).
    alone = r.render_many(np.array([[4.5, 3.0, 1.0]]), seed=5)[0]
    assert not np.array_equal(alone.samples, frame.samples)
    assert np.array_equal(r.render(np.array([4.5, 3.0, 1.0]), seed=np.random.default_rng([5, 1])).samples,
                          frame.samples)


def test_bad_settings_and_poses_are_refused():
    with pytest.raises(RenderConfigError, match="sub_rays"):
        RenderSettings(sub_rays=0)
    with pytest.raises(RenderConfigError, match="mirror_reflectivity"):
        RenderSettings(mirror_reflectivity=1.5)
    with pytest.raises(RenderConfigError, match="max_bounces must be at most 64"):
        RenderSettings(max_bounces=10**9)  # between two perfect mirrors a ray never fades: it hung
    with pytest.raises(RenderConfigError, match="seed must be below 2..64"):
        RenderSettings(seed=2**70)
    r = renderer(load_world("room"), sub_rays=1)
    with pytest.raises(RenderConfigError, match="poses"):
        r.phasors(np.zeros((2, 2)))
    with pytest.raises(RenderConfigError, match="finite"):
        r.phasors(np.array([np.nan, 0.0, 0.0]))
    with pytest.raises(RenderConfigError, match="seed"):
        r.render_many(np.array([[4.5, 3.0, 1.0]]), seed=-1)
    with pytest.raises(RenderConfigError, match="seed must be >= 0, got -1"):
        r.render(np.array([4.5, 3.0, 1.0]), seed=-1)


def test_poses_along_the_loop_for_the_benchmarks():
    from omnitof.sim.sequence import poses_along_loop

    w = load_world("corridor1")
    poses = poses_along_loop(w, 12)
    assert poses.shape == (12, 3)
    assert np.all(w.horizontal_distance(poses[:, :2], np.array([0.0]), 0.45) > 0.5)


def test_a_plan_grid_too_fine_for_the_world_is_an_error_not_a_panic():
    # 1 µm cells over the room's 8 m × 4.5 m: 3.6e13 cells, which overflowed the core's i32 cell
    # count ("capacity overflow" panic, a traceback through PyO3) or asked for terabytes.
    from omnitof.sim.render import RenderConfigError, RenderSettings

    with pytest.raises(RenderConfigError, match=r"world 'room': the plan spans 8\.0000 m × 4\.5000 m: too large"):
        Renderer(load_world("room"), settings=RenderSettings(cell=1e-6))


# --- motion during a frame -------------------------------------------------------------------------


def test_turning_smears_a_depth_edge_over_the_angle_swept_between_first_and_last_sample():
    # A camera looking horizontally along the robot's +x (no mirrors, no distortion), on the
    # robot's turning axis; a near wall (x = 2, y < 0) in front of a far one (x = 4): the depth
    # edge lies at bearing 0. Pixel column u looks at α_u = atan((u − cx)/fx) right of the
    # optical axis, i.e. bearing θ − α_u; it sees the near wall while α_u > θ. Turning at ω,
    # sample k is taken at θ_k = ω·(k − 1.5)·T, so the columns with θ_0 < α_u < θ_3 see the near
    # wall in some samples and the far one in others: the smear, analytic here.
    from omnitof.sensor.camera import Camera
    from omnitof.sensor.tof_errors import ToFErrors

    cam = Camera(width=96, height=8, fx=200.0, fy=200.0, cx=47.5, cy=3.5)
    mount = np.eye(4)
    mount[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=float)  # camera z → robot x
    mount[2, 3] = 1.0
    w = world(walls=[(2.0, 0.0, 2.0, -30.0, "wall"), wall_across_x(4.0)])
    omega, t_int = 4.0, 0.005
    sensor = SensorNoise(electrons_per_unit=math.inf, read_noise=0.0,
                         errors=ToFErrors(motion=True, integration_time=t_int))
    r = Renderer(w, camera=cam, mirrors=[], robot_T_camera=mount, sensor=sensor,
                 settings=RenderSettings(sub_rays=1, max_bounces=0))
    thetas = omega * (np.arange(4) - 1.5) * t_int
    samples = np.column_stack([np.zeros((4, 2)), thetas])[None]
    frame = r.render_many(np.zeros((1, 3)), seed=0, sample_poses=samples)[0]
    alpha = np.arctan((np.arange(96) - 47.5) / 200.0)
    # Along column u's ray the walls are x/cos(α_u) away. Off the axis the path changes by up
    # to 3 cm from sample 0 to 3 while turning, and such a ramp across the samples biases the
    # 4-tap decoding by a few cm more: "clean" allows 10 cm; the smeared columns are metres off.
    d = frame.distance[4] * np.cos(alpha)
    clean = (np.abs(d - 2.0) < 0.1) | (np.abs(d - 4.0) < 0.1)
    swept = (alpha > thetas[0]) & (alpha < thetas[3])
    assert swept.sum() == 12  # 0.06 rad at 200 px/rad
    np.testing.assert_array_equal(~clean, swept)
    # Near the edge but outside the sweep every sample agrees; standing still, nothing smears.
    still = r.render_many(np.zeros((1, 3)), seed=0, sample_poses=np.zeros((1, 4, 3)))[0].distance[4]
    still = still * np.cos(alpha)
    assert np.all((np.abs(still - 2.0) < 0.001) | (np.abs(still - 4.0) < 0.001))


def test_the_samples_of_a_moving_frame_share_their_multipath_rays():
    # The interreflection is a smooth function of the pose; its Monte-Carlo estimate is not,
    # unless the four samples draw the same secondary rays. A frame whose samples move by
    # nanoradians (rendered once per sample: motion_tolerance 0) must then decode like the
    # frame at one pose, while four estimates drawn apart differ by their noise.
    from omnitof.sensor.tof_errors import ToFErrors

    sensor = SensorNoise(errors=ToFErrors(motion=True, multipath=True))
    r = Renderer(load_world("room"), camera=CAMERA, mirrors=MIRRORS, sensor=sensor,
                 settings=RenderSettings(sub_rays=1, motion_tolerance=0.0))
    pose = np.array([2.0, 1.8, 0.3])
    samples = np.tile(pose, (4, 1))
    samples[:, 2] += 1e-9 * np.arange(4)
    moving = r.render_many(pose[None], seed=0, sample_poses=samples[None])[0]
    still = r.render_many(pose[None], seed=0)[0]
    lit = np.abs(still.phasor) > 20.0
    assert lit.sum() > 1000
    rel = np.abs(moving.phasor - still.phasor)[lit] / np.abs(still.phasor)[lit]
    assert rel.max() < 1e-4
    # Each sample with rays of its own (keyed by its own pose) is another estimate.
    own = r.phasors(samples).phasor
    rel_own = np.abs(own[1] - own[0])[lit] / np.abs(own[0])[lit]
    assert np.mean(rel_own > 0.05) > 0.02


# --- multipath and the LEDs beside the lens ----------------------------------------------------------


def horizontal_camera(fx: float, width: int, height: int):
    """A distortion-free camera looking along the robot's +x, 1 m above the floor, and its mount."""
    from omnitof.sensor.camera import Camera

    cam = Camera(width=width, height=height, fx=fx, fy=fx, cx=(width - 1) / 2, cy=(height - 1) / 2)
    mount = np.eye(4)
    mount[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=float)  # camera z → robot x
    mount[2, 3] = 1.0
    return cam, mount


def corner_scene():
    """Two perpendicular matte walls (A: x = 3, B: y = 1), black floor and ceiling; a narrow
    lens at the origin, 1 m up, looking at P = (3, 0.5, 1) on A, 0.5 m from the corner (all
    pixels see P within 1 mm): (world, camera, mount, pose)."""
    w = world(walls=[(3.0, -5.0, 3.0, 1.0, "wall"), (-5.0, 1.0, 3.0, 1.0, "wall")], materials={"black": BLACK},
              floor_material="black", ceiling_material="black")
    cam, mount = horizontal_camera(fx=20000.0, width=16, height=16)
    return w, cam, mount, np.array([0.0, 0.0, math.atan2(0.5, 3.0)])


def corner_indirect(rays: int, window: int, sub_rays: int) -> np.ndarray:
    """Per pixel of `corner_scene`, the phasor the interreflection adds (complex128 (16, 16)),
    from a coaxial isotropic source (the quadrature of `corner_quadrature` has no profile)."""
    from omnitof.sensor.tof_errors import ToFErrors

    w, cam, mount, pose = corner_scene()

    def phasor(multipath: bool) -> np.ndarray:
        errors = ToFErrors(multipath=multipath, multipath_rays=rays, multipath_window=window,
                           led_profile_exponent=0.0, led_half_angle_deg=180.0)
        sensor = SensorNoise(electrons_per_unit=math.inf, read_noise=0.0, errors=errors)
        r = Renderer(w, camera=cam, mirrors=[], robot_T_camera=mount, sensor=sensor,
                     settings=RenderSettings(sub_rays=sub_rays, max_bounces=0, seed=3))
        return r.phasors(pose).phasor[0].astype(np.complex128)

    return phasor(True) - phasor(False)


def corner_quadrature() -> tuple[complex, float]:
    """The interreflection at P of `corner_scene` by a quadrature over B of
      A1m·ρ_A·ρ_B/π ∫ cosθ_P·cosθ_Q/|PQ|² · cosθ_S/|QS|² · e^{i·k·(r + |PQ| + |QS|)/2} dA,
    k = 4πf/c, r = |SP| (the camera side), θ_S the incidence of the source's light at Q; and
    the direct light's amplitude at P."""
    k = 4 * math.pi * SENSOR.f_mod / 299_792_458.0
    p, s = np.array([3.0, 0.5, 1.0]), np.array([0.0, 0.0, 1.0])
    r = np.linalg.norm(p - s)
    n = 1200
    xs = -5.0 + (np.arange(n) + 0.5) * 8.0 / n
    zs = (np.arange(n // 2) + 0.5) * 3.0 / (n // 2)
    qx, qz = np.meshgrid(xs, zs)
    q = np.stack([qx, np.ones_like(qx), qz], axis=-1)
    pq, qs = q - p, s - q
    d_pq, d_qs = np.linalg.norm(pq, axis=-1), np.linalg.norm(qs, axis=-1)
    cos_p = -pq[..., 0] / d_pq           # A's normal facing the camera: −x, towards Q
    cos_q = pq[..., 1] / d_pq            # B's normal facing the room: −y, towards P (−pq)
    cos_s = -qs[..., 1] / d_qs           # and towards the source
    area = (8.0 / n) * (3.0 / (n // 2))
    integrand = cos_p * cos_q / d_pq**2 * cos_s / d_qs**2 * np.exp(1j * k * (r + d_pq + d_qs) / 2)
    albedo = 0.6  # the bundled "wall"
    expected = SENSOR.amplitude_at_1m * albedo * albedo / math.pi * integrand.sum() * area
    return complex(expected), SENSOR.amplitude_at_1m * albedo * (3.0 / r) / r**2


def test_a_corner_adds_the_two_path_phasor_of_the_neighbouring_wall():
    # The interreflection's phasor, rendered with and without multipath, against the quadrature.
    expected, direct = corner_quadrature()
    indirect = corner_indirect(rays=256, window=0, sub_rays=16).mean()
    assert abs(expected) > 0.05 * direct  # the corner matters: > 5 % of the direct light
    # Monte-Carlo over 256 pixels × 256 rays: about 1 % noise (the spread of the estimator), 4 %
    # tolerance.
    assert abs(indirect - expected) < 0.04 * abs(expected)


def test_two_rays_averaged_over_the_pixels_that_see_the_surface_approach_the_quadrature():
    # Two secondary rays per pixel are a noisy estimate: each pixel's alone is off by about its
    # own size (the estimator's spread, about 2.6 per ray, over two rays). Averaged over the
    # 7 × 7 pixels around it that see the same surface (here all see P), about 98 rays: a
    # seventh of that spread, and no bias.
    expected, _ = corner_quadrature()
    alone = np.abs(corner_indirect(rays=2, window=0, sub_rays=2) - expected) / abs(expected)
    averaged = np.abs(corner_indirect(rays=2, window=3, sub_rays=2) - expected) / abs(expected)
    assert np.median(alone) > 0.5
    assert np.median(averaged) < 0.35 and np.median(averaged) < np.median(alone) / 3


# --- noise and decoding in the core ------------------------------------------------------------------


def test_core_frames_follow_the_numpy_sensor_model_exactly_without_noise():
    # Frames are made in the core (rust/src/tof_frames.rs); tof.synthesise + tof.decode, in numpy,
    # are the independent reference. Without noise both must give the same samples (to f32
    # rounding) and the same distances, with every systematic error on and for a frame whose
    # four samples are rendered at four poses (motion during the frame) as for a still one.
    from omnitof.sensor.tof_errors import ToFErrors

    sensor = SensorNoise(electrons_per_unit=math.inf, read_noise=0.0,
                         errors=ToFErrors.realistic(fixed_pattern_seed=2, multipath=False))
    r = Renderer(load_world("room"), camera=CAMERA, mirrors=MIRRORS, sensor=sensor,
                 settings=RenderSettings(sub_rays=1))
    poses = np.array([[1.5, 1.5, 0.0], [4.5, 3.0, 1.0]])
    turning = np.stack([poses[1] + [0.0, 0.0, 0.1 * k] for k in range(4)])
    sample_poses = np.stack([np.repeat(poses[:1], 4, axis=0), turning])
    frames = r.render_many(poses, seed=3, sample_poses=sample_poses)
    still = r.phasors(poses[0])
    moving = r.phasors(turning)
    want_still = sensor.synthesise(still.phasor[0], still.ambient[0], rng=0, active_offset=still.active_offset[0])
    want_moving = sensor.synthesise(moving.phasor, moving.ambient, rng=0, active_offset=moving.active_offset,
                                    per_sample=True)
    for frame, want in zip(frames, (want_still, want_moving)):
        np.testing.assert_allclose(frame.samples, np.stack(want[:4]), rtol=1e-6, atol=1e-3)
        np.testing.assert_array_equal(frame.tof.saturated, want[4])
        decoded = decode(*want[:4], SENSOR.f_mod)
        lit = decoded.amplitude > 1.0
        assert lit.mean() > 0.5
        np.testing.assert_allclose(wrapped_error(frame.distance[lit], decoded.distance[lit]), 0.0, atol=1e-5)
    np.testing.assert_allclose(frames[1].phasor, moving.phasor.mean(axis=0), rtol=1e-6)


def test_core_frame_noise_has_the_spread_of_the_sensor_model_and_no_thread_dependence():
    # A wall square-on through the front mirror, the same pose 200 times: each pixel's sample
    # spread over the frames against √(μ/g + σ_r²) of the model (μ from the noise-free samples).
    from omnitof.sensor.tof_errors import ToFErrors

    w = world([wall_across_x(2.5)])
    poses = np.zeros((200, 3))
    r = renderer(w, sub_rays=1)
    frames = r.render_many(poses, seed=11)
    samples = np.stack([f.samples for f in frames]).astype(np.float64)  # (200, 4, H, W)
    noise_free = Renderer(w, camera=CAMERA, mirrors=MIRRORS, settings=RenderSettings(sub_rays=1),
                          sensor=SensorNoise(electrons_per_unit=math.inf, read_noise=0.0))
    mu = noise_free.render_many(poses[:1], seed=0)[0].samples.astype(np.float64)
    seen = (LABELS >= 0) & (mu[0] > 100.0) & (mu.max(axis=0) < 0.9 * SENSOR.full_well)
    assert seen.sum() > 1000
    want = np.sqrt(mu / SENSOR.electrons_per_unit + SENSOR.read_noise**2)
    ratio = samples.std(axis=0, ddof=1)[:, seen] / want[:, seen]
    assert abs(np.median(ratio) - 1.0) < 0.02  # 200 draws: 5 % per pixel, 0.1 % for the median
    assert np.abs(samples.mean(axis=0)[:, seen] - mu[:, seen]).max() < 5 * want[:, seen].max() / math.sqrt(200)
    # Pixels draw independent noise: neighbours' deviations do not correlate.
    dev = samples[:, 0] - mu[0]
    a, b = dev[:, seen][:, :-1].ravel(), dev[:, seen][:, 1:].ravel()
    assert abs(np.corrcoef(a, b)[0, 1]) < 0.02
    # Every effect on (LEDs, multipath, motion): the same frames on one thread and on two.
    errors = ToFErrors.realistic()
    seq_poses = np.array([[1.5, 1.5, 0.0], [4.5, 3.0, 1.0]])
    timing = np.stack([seq_poses + [0.0, 0.0, 0.02 * k] for k in range(4)], axis=1)
    made = [Renderer(load_world("room"), camera=CAMERA, mirrors=MIRRORS, sensor=SensorNoise(errors=errors),
                     settings=RenderSettings(threads=t)).render_many(seq_poses, seed=4, sample_poses=timing)
            for t in (1, 2)]
    for one, two in zip(*made):
        assert np.array_equal(one.samples, two.samples) and np.array_equal(one.distance, two.distance)
