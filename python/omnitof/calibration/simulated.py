"""The whole calibration of a simulated rig in one call, as `omnitof demo` runs it.

Renders checkerboard images (no mirrors) and four-dot target images at every mirror with the
sensor's noise (`calibration.targets`), calibrates the intrinsics from the boards
(`calibrate_intrinsics`, OpenCV) and then the mirror planes from the dots with those intrinsics
(`calibrate_mirrors`, paper sec. II-C, eq. 5), draws the masks from the estimated planes
(`masks.labels_from_planes`; the outer edge of the mirrors, which no plane tells, from the
rig's design), and reports how far every estimate is from the truth.

With `refine` (the default) it also renders a plain board seen through each two neighbouring
mirrors (`targets.render_pair_images`) and refines everything jointly from all the images
(`observations.refine_calibration`, issue 16), starting from the closed-form estimates.

When the simulated sensor makes systematic distance errors (issue 15's wiggling, amplitude
offset, fixed pattern: `sensor.tof_errors`), it fits the distance correction
(`calibration.distance.DistanceCorrection`) to flat walls at known distances, a few frames
averaged per position (`calibration.walls`), with the true paths from the (refined) geometry,
and stores it in the calibration, so the scan extraction of the demo, the bench inputs and
`omnitof slam --calibration` removes those errors. The refinement itself leaves the ToF path
lengths out in that case (uncorrected they pulled the focal length 10 %); with
`corrected_path_lengths` it refines once more with the path lengths of the corrected distances.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from omnitof.calibration import Calibration
from omnitof.calibration.intrinsics import calibrate_intrinsics
from omnitof.calibration.masks import labels_from_planes
from omnitof.calibration.mirror_planes import calibrate_mirrors
from omnitof.calibration.targets import render_checkerboard_images, render_dot_images
from omnitof.sensor.mirrors import assign_pixels

# 30 boards at planned poses pin the principal point to 0.02–0.08 px at 176×144 (closed form,
# seeds 0–14; random poses: 0.03–0.16 px, and 60 random boards did not remove the worst seeds'
# error). benchmarks/calibration_planning.py; BENCHMARKS.md, "Calibration".
DEFAULT_BOARDS = 30
# 14 dot-card placements per mirror: with 8 the worst mirror normal was within 0.05° in 14 of
# 15 seeds (reported σ 0.024°); with 14 in every seed measured (BENCHMARKS.md, "Board poses
# planned for the intrinsics").
DEFAULT_PLACEMENTS = 14
# Two-mirror boards per pair of neighbouring mirrors (refinement only).
DEFAULT_PAIR_BOARDS = 2
# The systematic errors a distance correction removes (ToFErrors switches).
DISTANCE_ERRORS = ("wiggling", "amplitude_offset", "fixed_pattern")


def calibrate_from_simulation(
    renderer: Any,
    *,
    seed: int = 0,
    truth: Calibration | None = None,
    boards: int = DEFAULT_BOARDS,
    placements: int = DEFAULT_PLACEMENTS,
    edge_margin_px: float = 2.0,
    refine: bool = True,
    pair_boards: int = DEFAULT_PAIR_BOARDS,
    distance_correction: bool = True,
    corrected_path_lengths: bool = False,
    planned_boards: bool = True,
) -> tuple[Calibration, dict[str, Any]]:
    """(estimated Calibration, report) for the rig of a `sim.render.Renderer`.

    The report holds the intrinsics' RMS reprojection error and focal-length error, and per
    mirror the angle between the estimated and the true normal (degrees) and the error of the
    plane distance (mm), with what the robust steps rejected, and the distance correction's fit.
    distance_correction: fit one when the sensor has systematic distance errors (module
    docstring). corrected_path_lengths: with a correction, refine again with the path lengths
    of the corrected distances. planned_boards: the checkerboards at planned poses
    (`targets.planned_checkerboard_poses`), else at random ones.
    """
    camera, mirrors = renderer.camera, list(renderer.mirrors)
    truth = truth or Calibration.from_rig(renderer.rig, edge_margin_px)
    board_images, _ = render_checkerboard_images(camera, boards, seed, sensor=renderer.sensor, planned=planned_boards)
    intrinsics = calibrate_intrinsics(board_images)
    dot_images, _ = render_dot_images(camera, mirrors, placements, seed, sensor=renderer.sensor)
    design_labels = assign_pixels(camera, mirrors)
    result = calibrate_mirrors(
        intrinsics.camera, dot_images, [m.name for m in mirrors], [m.plane for m in mirrors], design_labels
    )
    labels = labels_from_planes(intrinsics.camera, result.planes, outside=design_labels < 0,
                                edge_margin_px=edge_margin_px)
    calibration = Calibration.estimated(
        intrinsics.camera, result.planes, [m.name for m in mirrors], np.asarray(renderer.robot_T_camera),
        labels, edge_margin_px=edge_margin_px,
        quality={**intrinsics.quality(), "mirrors": result.report()},
        provenance={"source": f"simulated targets, seed {seed}: {boards} {'planned' if planned_boards else 'random'} "
                              f"boards, {placements} placements per mirror"},
    )
    closed_form = None
    distance_errors = set(getattr(getattr(renderer.sensor, "errors", None), "switched_on", ())) & set(DISTANCE_ERRORS)
    if refine:
        from omnitof.calibration.observations import refine_calibration
        from omnitof.calibration.targets import render_pair_images

        closed_form = _errors(calibration, truth)
        pair_images, _ = render_pair_images(camera, mirrors, pair_boards, seed, sensor=renderer.sensor)
        # The path lengths only if the simulated distances carry no systematic error (issue 15's
        # ToFErrors): uncorrected, such errors pull the focal length and the planes.
        unbiased = not getattr(getattr(renderer.sensor, "errors", None), "switched_on", ())
        calibration, _ = refine_calibration(calibration, board_images, dot_images, pair_images,
                                            outside=design_labels < 0, seed=seed, path_lengths=unbiased)
        calibration.provenance["source"] += f", {pair_boards} two-mirror boards per pair, refined jointly"
    correction_report = None
    if distance_correction and distance_errors:
        from omnitof.calibration.walls import render_wall_views, fit_from_walls

        walls = render_wall_views(camera, mirrors, seed, sensor=renderer.sensor)
        calibration.distance_correction = fit_from_walls(calibration, walls)
        dc = calibration.distance_correction
        calibration.provenance["source"] += f", distance correction from {len(walls)} wall views"
        correction_report = {"walls": len(walls), "samples": dc.samples,
                             "rms_before_mm": round(1000.0 * dc.rms_before, 2),
                             "rms_after_mm": round(1000.0 * dc.rms_after, 2)}
        if refine and corrected_path_lengths:
            before_path_lengths = _errors(calibration, truth)
            fixed = [corrected_image(im, dc) for im in (*board_images, *dot_images, *pair_images)]
            nb, nd = len(board_images), len(dot_images)
            calibration, _ = refine_calibration(calibration, fixed[:nb], fixed[nb:nb + nd], fixed[nb + nd:],
                                                outside=design_labels < 0, seed=seed, path_lengths=True)
            calibration.provenance["source"] += ", refined again with the corrected path lengths"
            correction_report["refined_without_path_lengths"] = before_path_lengths
    est, true = calibration.camera, truth.camera
    report: dict[str, Any] = {
        "source": calibration.provenance["source"],
        "refined": bool(refine),
        "intrinsics": {
            "rms_px": round(float(intrinsics.rms_px), 4),
            "fx_error_pct": round(100.0 * (est.fx - true.fx) / true.fx, 3),
            "fy_error_pct": round(100.0 * (est.fy - true.fy) / true.fy, 3),
            "principal_point_error_px": round(math.hypot(est.cx - true.cx, est.cy - true.cy), 3),
            "views": len(intrinsics.used),
        },
        "mirrors": {},
    }
    for name, got, want in zip(calibration.names, calibration.planes, truth.planes):
        cos = float(np.clip(np.dot(got.normal, want.normal), -1.0, 1.0))
        report["mirrors"][name] = {
            "normal_error_deg": round(math.degrees(math.acos(cos)), 4),
            "distance_error_mm": round(1000.0 * (got.d - want.d), 3),
        }
    worst_angle = max(m["normal_error_deg"] for m in report["mirrors"].values())
    worst_d = max(abs(m["distance_error_mm"]) for m in report["mirrors"].values())
    report["summary"] = (f"intrinsics RMS {report['intrinsics']['rms_px']:.3f} px, fx error "
                         f"{report['intrinsics']['fx_error_pct']:+.2f} %; mirrors: normals within "
                         f"{worst_angle:.3f}°, plane distances within {worst_d:.2f} mm")
    report["mask_pixels_differing_from_truth"] = int(np.sum(calibration.labels != truth.labels))
    if correction_report is not None:
        report["distance_correction"] = correction_report
        report["summary"] += (f"; distance correction from {correction_report['walls']} wall views "
                              f"(fit RMS {correction_report['rms_before_mm']:.1f} → "
                              f"{correction_report['rms_after_mm']:.1f} mm)")
    if closed_form is not None:
        report["closed_form"] = closed_form
        report["std"] = calibration.quality["refinement"]["std"]
        report["summary"] += f" (closed form: {closed_form['summary']})"
    return calibration, report


def corrected_image(image: Any, correction: Any) -> Any:
    """An AmplitudeImage with its distances corrected (`DistanceCorrection.correct`)."""
    from dataclasses import replace

    if image.distance is None:
        return image
    return replace(image, distance=correction.correct(image.distance, image.amplitude).astype(np.float32))


def _errors(calibration: Calibration, truth: Calibration) -> dict[str, Any]:
    """The errors of the closed-form estimate (before the refinement), in brief."""
    est, true = calibration.camera, truth.camera
    angles, dds = [], []
    for got, want in zip(calibration.planes, truth.planes):
        angles.append(math.degrees(math.acos(float(np.clip(np.dot(got.normal, want.normal), -1.0, 1.0)))))
        dds.append(abs(1000.0 * (got.d - want.d)))
    fx = 100.0 * (est.fx - true.fx) / true.fx
    pp = math.hypot(est.cx - true.cx, est.cy - true.cy)
    return {
        "fx_error_pct": round(fx, 3),
        "principal_point_error_px": round(pp, 3),
        "worst_normal_error_deg": round(max(angles), 4),
        "worst_distance_error_mm": round(max(dds), 3),
        "summary": f"fx {fx:+.2f} %, principal point {pp:.2f} px, normals within {max(angles):.3f}°, "
                   f"distances within {max(dds):.2f} mm",
    }
