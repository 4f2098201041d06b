"""omnitof.sensor.illumination and the renderer's LEDs (rust/src/light.rs): a geometry whose lit
share is worked out by hand, the renderer's dark pixels against the numpy model, and the
paper's remark that closer mirrors are worse."""

from __future__ import annotations

import math

import numpy as np

from omnitof.sensor.camera import Camera
from omnitof.sensor.design import default_rig
from omnitof.sensor.illumination import lit_pixels, lit_share
from omnitof.sensor.mirrors import Mirror, MirrorPlane, masks, pyramid
from omnitof.sensor.tof import SensorNoise
from omnitof.sensor.tof_errors import ToFErrors
from omnitof.sim.render import Renderer, RenderSettings
from omnitof.sim.worlds import load_world


def test_one_led_beside_a_tilted_mirror_misses_a_strip_as_wide_as_its_offset():
    # One 45° mirror facing −y (normal (0, −1, 1)/√2, 0.2 m up the axis), a rectangle spanning
    # x ∈ [−a, a] on it; one LED at (δ, 0, 0). The offset is parallel to the mirror, so the LED's
    # ray parallel to a pixel's ray meets the mirror δ further along x, and after the mirror it
    # runs parallel to the pixel's reflected ray: for a point at infinity along that ray, the
    # pixel is lit iff its own mirror point has x <= a − δ.
    cam = Camera(width=40, height=30, fx=60.0, fy=60.0, cx=19.5, cy=14.5)
    n = np.array([0.0, -1.0, 1.0]) / math.sqrt(2)
    d = 0.2 / math.sqrt(2)
    a, delta = 0.05, 0.01
    polygon = np.array([[x, y, y + 0.2] for x, y in [(-a, -0.3), (a, -0.3), (a, 0.3), (-a, 0.3)]])
    mirror = Mirror(MirrorPlane(n, d), polygon, "one")
    errors = ToFErrors(illumination=True, led_count=1, led_radius=delta)  # the LED at (δ, 0, 0)
    lit = lit_pixels(cam, [mirror], errors, distance=1e6)
    seen = masks(cam, [mirror], 0.0) >= 0
    rays = cam.pixel_grid_rays()
    x = (rays * (d / (rays @ n))[..., None])[..., 0]
    expected = seen & (x <= a - delta)
    assert seen.sum() > 300 and 0.05 < (seen & ~expected).sum() / seen.sum() < 0.4
    np.testing.assert_array_equal(lit[seen], expected[seen])


def test_renderer_dark_pixels_are_those_the_leds_do_not_reach():
    # Mirrors 4 cm above the lens: close enough that the LEDs miss part of the view.
    from omnitof.sensor.rig import Rig

    base = default_rig()
    rig = Rig.from_mirrors(base.camera, pyramid(4, 56.0, 0.04, yaw_deg=0.0, camera=base.camera), base.robot_T_camera)
    errors = ToFErrors(illumination=True)
    world = load_world("room")
    pose = np.array([world.waypoints[0][0], world.waypoints[0][1], 0.3])
    quiet = dict(electrons_per_unit=math.inf, read_noise=0.0)
    settings = RenderSettings(sub_rays=1, max_bounces=0)

    def phasor(errs: ToFErrors) -> np.ndarray:
        r = Renderer(world, rig.camera, rig.mirrors, rig.robot_T_camera, SensorNoise(**quiet, errors=errs), settings)
        return r.phasors(pose).phasor[0].astype(np.complex128)

    plain, lit_render = phasor(ToFErrors()), phasor(errors)
    distance = np.mod(np.angle(plain), 2 * math.pi) * 299_792_458.0 / (4 * math.pi * 20e6)
    seen = masks(rig.camera, rig.mirrors, 2.0) >= 0
    seen &= np.abs(plain) > 0
    dark = np.abs(lit_render) < 1e-6 * np.median(np.abs(plain[seen]))
    expected = lit_pixels(rig.camera, rig.mirrors, errors, distance)
    assert (~expected[seen]).sum() > 50  # the rig has unlit pixels at all
    assert (dark[seen] == ~expected[seen]).mean() > 0.99
    # Lit pixels keep the distance: the light path differs from the view path by centimetres.
    both = seen & ~dark
    gap = np.mod(np.angle(lit_render[both]) - np.angle(plain[both]) + math.pi, 2 * math.pi) - math.pi
    assert np.percentile(np.abs(gap) * 299_792_458.0 / (4 * math.pi * 20e6), 95) < 0.05


def test_closer_mirrors_leave_more_of_the_view_unlit():
    # The paper's remark (sec. VI): the lit share falls as the apex comes down to the lens.
    cam = default_rig().camera
    errors = ToFErrors.realistic()
    shares = [lit_share(cam, pyramid(4, 56.0, apex, yaw_deg=0.0, camera=cam), errors) for apex in (0.03, 0.04, 0.10)]
    assert shares[0] < shares[1] < shares[2]
    # The default 40° cone leaves the corners of the wide lens's view (rays beyond ~38°) dark
    # at any apex height: 2.5 %.
    assert shares[0] < 0.9 and shares[2] > 0.95
