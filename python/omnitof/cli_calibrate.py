"""`omnitof calibrate ...`: intrinsics, mirrors, masks, checks and simulated target images.

    omnitof calibrate plan-boards --out DIR [--calibration cal.yaml] [--boards N]
    omnitof calibrate render-targets --out DIR [--world W] [--seed S] [--placements N] [--walls]
    omnitof calibrate intrinsics DIR/intrinsics --out cal.yaml
    omnitof calibrate mirrors DIR/mirrors --calibration cal.yaml
    omnitof calibrate refine DIR --calibration cal.yaml [--out refined.yaml]
    omnitof calibrate distance DIR/walls/walls.yaml --calibration refined.yaml
    omnitof calibrate report cal.yaml --out REPORT_DIR [--truth DIR/truth.yaml]
    omnitof calibrate check cal.yaml [--truth DIR/truth.yaml] [--figure side.png]
    omnitof calibrate masks cal.yaml --export regions.yaml | --polygons regions.yaml

The command functions parse nothing themselves beyond argparse and call the library.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

WALLS_FILE_HELP = """\
walls:                      # one entry per position of the rig before a flat matte wall
  - frames: wall_0.50_front # .npz files (amplitude + distance), a folder of them, or a ToF bag,
                            # relative to this file; all its frames are averaged
    mirror: front           # the mirror whose view the wall fills (its name in the calibration)
    distance: 0.50          # metres, the shortest horizontal distance from the camera's optical
                            # centre to the wall, which faces that mirror (its turn off square
                            # is fitted to the frames)"""


def add_calibrate_parser(sub) -> None:
    """Register `calibrate` and its subcommands on the `omnitof` subparsers."""
    from omnitof.cli import _add_tof_bag_options, _image_count, _number, _seed  # the command's argument types

    p = sub.add_parser("calibrate", help="calibrate the camera and the mirrors (paper sec. II-C)")
    csub = p.add_subparsers(dest="calibrate_command", required=True)

    c = csub.add_parser("intrinsics", help="camera matrix and distortion from checkerboard images")
    c.add_argument("images", nargs="+", type=Path, help="PNG/.npz images, folders of them, or ROS bags")
    c.add_argument("--out", type=Path, required=True, help="calibration YAML to write (updated if it exists)")
    c.add_argument("--board", default="8x6", help="squares across x down (default 8x6)")
    c.add_argument("--square", type=_number(above=0), default=0.035, help="square side in metres (default 0.035)")
    c.add_argument("--fit-k3", action="store_true", help="also fit k3 (default: k3 = 0)")
    _add_tof_bag_options(c, "ROS bags: ")
    c.set_defaults(func=cmd_intrinsics)

    c = csub.add_parser("mirrors", help="mirror planes from four-dot target images (Hu, Brown, Nelson)")
    c.add_argument("images", nargs="+", type=Path, help=".npz/PNG images, folders of them, or ROS bags")
    c.add_argument("--calibration", type=Path, required=True,
                   help="calibration YAML with the intrinsics (from `calibrate intrinsics`)")
    c.add_argument("--out", type=Path, help="where to write (default: update --calibration)")
    c.add_argument("--spacing", type=_number(above=0), default=0.012, help="side of the square of dots, metres")
    c.add_argument("--scale", choices=["dots", "tof"], default="dots",
                   help="metric scale from the dot spacing or from the ToF distances")
    c.add_argument("--mirror", help="the mirror all images show (default: found from the image)")
    c.add_argument("--margin", type=_number(at_least=0), help="mask edge margin in pixels (default: the file's)")
    _add_tof_bag_options(c, "ROS bags: ")
    c.set_defaults(func=cmd_mirrors)

    c = csub.add_parser("refine", help="refine intrinsics, mirrors and target poses jointly from all images "
                        "(ToF path lengths, two-mirror boards)")
    c.add_argument("folder", type=Path, help="folder with intrinsics/, mirrors/ and (optional) pairs/ images, "
                   "as render-targets writes it")
    c.add_argument("--calibration", type=Path, required=True,
                   help="the closed-form calibration to start from (`calibrate intrinsics` then `mirrors`)")
    c.add_argument("--out", type=Path, help="where to write (default: update --calibration)")
    c.add_argument("--board", default="8x6", help="checkerboard squares across x down (default 8x6)")
    c.add_argument("--square", type=_number(above=0), default=0.035, help="square side in metres (default 0.035)")
    c.add_argument("--spacing", type=_number(above=0), default=0.012, help="side of the square of dots, metres")
    _add_tof_bag_options(c, "ROS bags: ")
    c.set_defaults(func=cmd_refine)

    c = csub.add_parser("report", help="write a report (Markdown + PNG) of a calibration: uncertainties, "
                        "residuals, distance correction, the Fig. 6 check")
    c.add_argument("calibration", type=Path)
    c.add_argument("--out", type=Path, required=True, help="folder for report.md and its figures")
    c.add_argument("--truth", type=Path, help="true calibration of a simulated rig (adds error columns)")
    c.add_argument("--frame", type=Path, help="a recorded frame among equal-height objects (.npz or bag) "
                   "for the Fig. 6 check (default: the simulated scene)")
    _add_tof_bag_options(c, "ROS bags: ")
    c.set_defaults(func=cmd_report)

    c = csub.add_parser("plan-boards", help="where to hold the checkerboard: poses planned for the intrinsics, "
                        "as YAML and a figure of where each board should appear in the image")
    c.add_argument("--out", type=Path, required=True, help="folder for boards.yaml and boards.png")
    camera_from = c.add_mutually_exclusive_group()
    camera_from.add_argument("--calibration", type=Path,
                             help="take the nominal camera from this calibration YAML (default: the rig design's)")
    camera_from.add_argument("--taken", type=Path, nargs="+", metavar="IMAGES",
                             help="checkerboard images already taken (files, folders, bags): calibrate from "
                                  "them and plan the boards that add most to them")
    c.add_argument("--boards", type=_image_count, default=30, help="boards to plan")
    c.add_argument("--board", default="8x6", help="squares across x down (default 8x6)")
    c.add_argument("--square", type=_number(above=0), default=0.035, help="square side in metres (default 0.035)")
    c.add_argument("--seed", type=_seed, default=0, help="fixes the candidate poses drawn")
    _add_tof_bag_options(c, "ROS bags: ")
    c.set_defaults(func=cmd_plan_boards)

    c = csub.add_parser("render-targets", help="simulate checkerboard and dot-target images")
    c.add_argument("--out", type=Path, required=True, help="folder to write into")
    c.add_argument("--world", help="bundled world name or YAML: its ceiling, floor and light")
    c.add_argument("--seed", type=_seed, default=0)
    c.add_argument("--placements", type=_image_count, default=8, help="dot-target placements per mirror")
    c.add_argument("--boards", type=_image_count, default=15, help="checkerboard images")
    c.add_argument("--random-boards", action="store_true",
                   help="checkerboards at random poses (default: poses planned for the intrinsics)")
    c.add_argument("--pair-boards", type=_image_count, default=2,
                   help="plain boards seen through each two neighbouring mirrors (for `calibrate refine`)")
    c.add_argument("--walls", action="store_true",
                   help="also a flat wall facing each mirror at 0.5-6.5 m, with the camera's systematic distance "
                        "errors, and walls/walls.yaml (for `calibrate distance`)")
    c.set_defaults(func=cmd_render_targets)

    c = csub.add_parser("distance", help="fit the distance correction (wiggling, amplitude, per-pixel offsets) "
                        "to frames of a flat wall at measured distances",
                        epilog="the walls file:\n" + WALLS_FILE_HELP, formatter_class=argparse.RawDescriptionHelpFormatter)
    c.add_argument("walls", type=Path, help="YAML listing the wall positions (frames, mirror, distance; below)")
    c.add_argument("--calibration", type=Path, required=True,
                   help="the calibration whose geometry gives the true paths (`calibrate mirrors` or `refine`)")
    c.add_argument("--out", type=Path, help="where to write (default: update --calibration)")
    c.set_defaults(func=cmd_distance)

    c = csub.add_parser("check", help="equal-height objects seen in every mirror (paper Fig. 6)")
    c.add_argument("calibration", type=Path)
    c.add_argument("--truth", type=Path, help="true calibration of the simulated rig (default: the design)")
    c.add_argument("--frame", type=Path,
                   help="a recorded frame (.npz with distance, or a ROS bag: its first frame) of the "
                        "rig among equal-height objects, instead of the simulated scene")
    c.add_argument("--band", type=_number(above=0), nargs=2, metavar=("NEAR", "FAR"),
                   help="horizontal range band of the objects' faces, metres (default 1.95 2.15)")
    c.add_argument("--min-height", type=_number(), help="ignore points lower than this (m; default 0.3)")
    c.add_argument("--figure", type=Path, help="side view PNG")
    c.add_argument("--seed", type=_seed, default=0)
    _add_tof_bag_options(c, "ROS bags: ")
    c.set_defaults(func=cmd_check)

    c = csub.add_parser("masks", help="export the mirror regions as polygons, or redraw them from polygons")
    c.add_argument("calibration", type=Path)
    c.add_argument("--export", type=Path, help="write the regions as an editable polygon YAML")
    c.add_argument("--polygons", type=Path, help="redraw the masks from this polygon YAML")
    c.add_argument("--margin", type=_number(at_least=0), help="edge margin in pixels (default: the file's)")
    c.add_argument("--figure", type=Path, help="draw the masks (PNG)")
    c.add_argument("--out", type=Path, help="where to write (default: update the calibration)")
    c.set_defaults(func=cmd_masks)


def _board(text: str):
    from omnitof.calibration import CalibrationError

    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise CalibrationError(f"--board: expected COLSxROWS squares, e.g. 8x6, got {text!r}") from None
    if min(cols, rows) < 4:
        # OpenCV's detectors need more than two inner corners each way (cols - 1, rows - 1).
        raise CalibrationError(f"--board: needs at least 4x4 squares (3x3 inner corners), got {text!r}")
    return cols, rows


def _design_outside(camera) -> np.ndarray:
    """Pixels that see past the default rig's mirrors (the mirrors' outer edges)."""
    from omnitof.sensor.design import default_rig
    from omnitof.sensor.mirrors import assign_pixels

    return assign_pixels(camera, default_rig().mirrors) < 0


def cmd_intrinsics(args: argparse.Namespace) -> int:
    from omnitof.calibration import MIRRORS_NOT_CALIBRATED, Calibration, load_calibration, save_calibration
    from omnitof.calibration.images import load_images
    from omnitof.calibration.intrinsics import calibrate_intrinsics
    from omnitof.calibration.masks import labels_from_planes
    from omnitof.calibration.targets import Checkerboard
    from omnitof.sensor.design import default_rig

    cols, rows = _board(args.board)
    board = Checkerboard(cols=cols, rows=rows, square=args.square)
    started = time.perf_counter()
    images = load_images(args.images, **_bag_format(args))
    result = calibrate_intrinsics(images, board, fix_k3=not args.fit_k3)
    camera = result.camera
    if args.out.exists():
        cal = load_calibration(args.out)
        cal = cal.with_rig(replace(cal.rig, camera=camera))
    else:
        cal = Calibration.from_rig(replace(default_rig(), camera=camera))
        cal.provenance = {"mirrors": MIRRORS_NOT_CALIBRATED}
    cal.labels = labels_from_planes(camera, cal.planes, _design_outside(camera), cal.edge_margin_px)
    cal.quality.update(result.quality())
    cal.provenance["intrinsics"] = f"{len(result.used)} checkerboard images ({cols}x{rows}, {args.square} m)"
    save_calibration(cal, args.out)
    print(f"intrinsics from {len(result.used)} of {len(images)} images: RMS reprojection error "
          f"{result.rms_px:.3f} px ({time.perf_counter() - started:.1f} s)")
    print(f"  fx {camera.fx:.2f}  fy {camera.fy:.2f}  cx {camera.cx:.2f}  cy {camera.cy:.2f} px")
    print("  dist (k1 k2 p1 p2 k3) " + " ".join(f"{v:+.5f}" for v in camera.dist))
    for name in result.skipped:
        print(f"  no checkerboard found: {name}")
    for text in result.rejected:
        print(f"  rejected as an outlier: {text}")
    print(f"wrote {args.out}")
    return 0


def cmd_mirrors(args: argparse.Namespace) -> int:
    from omnitof.calibration import load_calibration, save_calibration
    from omnitof.calibration.images import load_images
    from omnitof.calibration.masks import labels_from_planes
    from omnitof.calibration.mirror_planes import calibrate_mirrors
    from omnitof.calibration.targets import DotTarget

    cal = load_calibration(args.calibration)
    started = time.perf_counter()
    images = load_images(args.images, **_bag_format(args))
    outside = _design_outside(cal.camera)
    regions = labels_from_planes(cal.camera, cal.planes, outside, 0.0)
    target = DotTarget(spacing=args.spacing)
    result = calibrate_mirrors(cal.camera, images, cal.names, cal.planes, regions,
                               target=target, scale=args.scale, mirror=args.mirror)
    mirror_quality = dict(cal.quality.get("mirrors", {}))
    planes = list(cal.planes)
    for estimate in result.estimates:
        planes[cal.names.index(estimate.name)] = estimate.plane
        mirror_quality[estimate.name] = estimate.quality()
    cal = cal.with_rig(replace(cal.rig, planes=tuple(planes)))
    cal.quality["mirrors"] = mirror_quality
    if args.margin is not None:
        cal.edge_margin_px = args.margin
    cal.labels = labels_from_planes(cal.camera, cal.planes, outside, cal.edge_margin_px)
    cal.polygons = {}
    cal.provenance["mirrors"] = (
        f"four-dot target, {len(images)} images, spacing {args.spacing} m, scale from {args.scale}"
    )
    out = args.out or args.calibration
    save_calibration(cal, out)
    for line in result.report():
        print(line)
    print(f"wrote {out} ({time.perf_counter() - started:.1f} s)")
    return 0


def cmd_refine(args: argparse.Namespace) -> int:
    from omnitof.calibration import load_calibration, save_calibration
    from omnitof.calibration.images import load_images
    from omnitof.calibration.observations import refine_calibration
    from omnitof.calibration.targets import Checkerboard, DotTarget

    cal = load_calibration(args.calibration)
    cols, rows = _board(args.board)
    started = time.perf_counter()
    folder = args.folder
    boards = load_images([folder / "intrinsics"], **_bag_format(args))
    dots = load_images([folder / "mirrors"], **_bag_format(args))
    pairs = load_images([folder / "pairs"], **_bag_format(args)) if (folder / "pairs").is_dir() else []
    refined, result = refine_calibration(
        cal, boards, dots, pairs, outside=_design_outside(cal.camera),
        board=Checkerboard(cols=cols, rows=rows, square=args.square), target=DotTarget(spacing=args.spacing),
    )
    out = args.out or args.calibration
    save_calibration(refined, out)
    cam, sd = result.camera, result.std["camera"]
    used = refined.quality["refinement"]["views_used"]
    print(f"refined from {used['boards']} of {len(boards)} board, {used['dot_targets']} of {len(dots)} dot-target "
          f"and {used['two_mirror_boards']} of {len(pairs)} two-mirror images "
          f"({time.perf_counter() - started:.1f} s, {result.iterations} iterations)")
    print(f"  fx {cam.fx:.3f} ± {sd['fx']:.3f}  fy {cam.fy:.3f} ± {sd['fy']:.3f}  "
          f"cx {cam.cx:.3f} ± {sd['cx']:.3f}  cy {cam.cy:.3f} ± {sd['cy']:.3f} px")
    for name, plane in zip(result.names, result.planes):
        s = result.std["mirrors"][name]
        n = plane.normal
        print(f"  mirror {name}: n = [{n[0]:+.5f} {n[1]:+.5f} {n[2]:+.5f}] ± {s['normal_deg']:.3f}°, "
              f"d = {1000 * plane.d:.2f} ± {s['d_mm']:.2f} mm")
    print(f"  noise: corners {result.sigma['corner_px']:.3f} px, dots {result.sigma['dot_px']:.3f} px, "
          f"path lengths {result.sigma['path_mm']:.2f} mm")
    for note in refined.quality["refinement"]["skipped"]:
        print(f"  not used: {note}")
    for name, rms in result.rejected.items():
        print(f"  left out as an outlier: {name} (view RMS {rms:.3f} px)")
    print(f"wrote {out}")
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from omnitof.calibration import load_calibration
    from omnitof.calibration_report import write_report

    cal = load_calibration(args.calibration)
    truth = load_calibration(args.truth) if args.truth is not None else None
    distance = None
    if args.frame is not None:
        from omnitof.calibration import CalibrationError
        from omnitof.calibration.images import load_images

        frames = load_images([args.frame], **_bag_format(args))
        if not frames or frames[0].distance is None:
            raise CalibrationError("the check needs a distance image (.npz or a ROS bag)", args.frame)
        distance = frames[0].distance
    written = write_report(cal, args.out, distance=distance, truth=truth)
    spread = written["fig6_spread_mm"]
    print(f"Fig. 6 check: upper edges of the mirrors within {spread:.1f} mm" if math.isfinite(spread)
          else "Fig. 6 check: not measured (fewer than two mirrors saw an upper edge in the frame; report.md)")
    print(f"wrote {written['report']} and " + ", ".join(str(v) for k, v in written.items()
                                                       if k not in ("report", "fig6_spread_mm")))
    return 0


def cmd_plan_boards(args: argparse.Namespace) -> int:
    from omnitof.calibration import load_calibration
    from omnitof.calibration.planning import board_plan
    from omnitof.calibration.targets import Checkerboard
    from omnitof.errors import dump_yaml
    from omnitof.io.atomic import atomic_write
    from omnitof.sensor.design import default_rig
    from omnitof.viz.calibration import plot_board_plan

    cols, rows = _board(args.board)
    board = Checkerboard(cols=cols, rows=rows, square=args.square)
    # The saddle detector's scatter on rendered boards is 0.0165 px; a real camera's is the
    # user's to measure (the RMS of `calibrate intrinsics`): 0.05 px is a round figure between.
    sigma_px, taken = 0.05, None
    if args.taken:
        from omnitof.calibration.images import load_images
        from omnitof.calibration.intrinsics import calibrate_intrinsics

        first = calibrate_intrinsics(load_images(args.taken, **_bag_format(args)), board)
        camera, taken = first.camera, first.poses
        # OpenCV's RMS is of the 2D error; the plan's σ is per coordinate.
        sigma_px = first.rms_px / math.sqrt(2.0)
        print(f"calibrated from {len(first.used)} boards taken (RMS {first.rms_px:.3f} px): "
              f"fx {camera.fx:.2f}  cx {camera.cx:.2f}  cy {camera.cy:.2f} px")
    elif args.calibration:
        camera = load_calibration(args.calibration).camera
    else:
        camera = default_rig().camera
    plan = board_plan(camera, board, args.boards, args.seed, sigma_px=sigma_px, taken=taken)
    args.out.mkdir(parents=True, exist_ok=True)
    with atomic_write(args.out / "boards.yaml", "w") as handle:
        dump_yaml(plan, handle, sort_keys=False)
    boards = plan["boards"]
    plot_board_plan(args.out / "boards.png", camera.width, camera.height,
                    [np.array(b["outline_px"]) for b in boards], np.array([b["first_corner_px"] for b in boards]),
                    taken=[np.array(b["outline_px"]) for b in plan.get("taken", [])])
    spread = plan["predicted_std"]

    def sigmas(key: str) -> str:
        s = spread[key]
        return f"cx {s['cx_px']:.3f}, cy {s['cy_px']:.3f} px, fx {s['fx_pct']:.3f} %"

    print(f"planned {len(boards)} board poses ({cols}x{rows} squares of {args.square} m): "
          f"{args.out / 'boards.yaml'}, {args.out / 'boards.png'}")
    print(f"  predicted σ at {spread['corner_error_px']:.3g} px corner error: {sigmas('planned')} "
          f"(random poses: {sigmas('random')})")
    if taken:
        print(f"  the {len(taken)} boards taken alone: {sigmas('taken')}; both figures above count them")
    return 0


def cmd_render_targets(args: argparse.Namespace) -> int:
    from omnitof.calibration.targets import render_calibration_images
    from omnitof.io.atomic import atomic_folder

    started = time.perf_counter()
    # Built under a hidden name and put in place whole (as a results folder is): an interrupted
    # run left empty folders, and a second run into the same folder kept the first one's extra
    # boards beside its truth.yaml. A folder that is not a set of target images is not replaced.
    with atomic_folder(args.out, may_replace=_only_target_images) as folder:
        summary = render_calibration_images(
            folder, world=args.world, seed=args.seed, placements=args.placements, boards=args.boards,
            pair_boards=args.pair_boards, planned_boards=not args.random_boards,
        )
        walls = None
        if args.walls:
            from omnitof.calibration.walls import render_wall_recordings, write_wall_recordings
            from omnitof.sensor.design import default_rig
            from omnitof.sensor.tof import SensorNoise
            from omnitof.sensor.tof_errors import ToFErrors

            rig = default_rig()
            # The camera's systematic errors (`simulate calibration --tof-errors`; the simulator's
            # default for `calibrate render-targets`): what the correction is for.
            errors = getattr(args, "tof_errors", None)
            sensor = SensorNoise(errors=ToFErrors.parse(errors) if errors else ToFErrors.simulation_default())
            # Set up by hand: each wall a little off square (`calibrate distance` fits the turn).
            turns = (1.5, -1.0, 0.5, -2.0, 0.0, 2.5, -0.5)
            recordings = [r for r, _ in render_wall_recordings(rig.camera, rig.mirrors, args.seed, sensor=sensor,
                                                               turns_deg=turns)]
            listing = write_wall_recordings(folder / "walls", recordings, [m.name for m in rig.mirrors])
            walls = (len(recordings), args.out / "walls" / listing.name)
    print(f"wrote {summary['boards']} checkerboard images to {args.out / 'intrinsics'}, "
          f"{summary['dot_images']} dot-target images ({args.placements} per mirror: "
          f"{', '.join(summary['mirrors'])}) to {args.out / 'mirrors'}, "
          f"{summary['pair_images']} two-mirror board images to {args.out / 'pairs'}, "
          f"and the true calibration {args.out / 'truth.yaml'} ({time.perf_counter() - started:.1f} s)")
    if walls is not None:
        print(f"wrote {walls[0]} wall positions to {walls[1]} ({time.perf_counter() - started:.1f} s)")
    return 0


def _only_target_images(path: Path) -> None:
    """`render-targets --out` replaces an empty folder or one it wrote before (its truth.yaml
    beside intrinsics/), never a user's other folder."""
    from omnitof.errors import OutputError

    if any(path.iterdir()) and not ((path / "truth.yaml").is_file() and (path / "intrinsics").is_dir()):
        raise OutputError(f"{path}: holds files that are not calibration target images (no truth.yaml and "
                          "intrinsics/): give a new or empty folder")


def cmd_distance(args: argparse.Namespace) -> int:
    from omnitof.calibration import load_calibration, save_calibration
    from omnitof.calibration.walls import fit_from_recordings, read_wall_recordings

    cal = load_calibration(args.calibration)
    started = time.perf_counter()
    recordings = read_wall_recordings(args.walls, cal)
    dc, views = fit_from_recordings(cal, recordings)
    cal.distance_correction = dc
    cal.provenance["distance_correction"] = f"{len(views)} wall positions from {args.walls}"
    out = args.out or args.calibration
    save_calibration(cal, out)
    print(f"fitted the distance correction to {dc.samples} wall pixels of {len(views)} positions "
          f"({sum(len(r.distances) for r in recordings)} frames): rms error {1000 * dc.rms_before:.1f} mm "
          f"before, {1000 * dc.rms_after:.1f} mm after ({time.perf_counter() - started:.1f} s)")
    turns = [v.turn_deg for v in views if v.turn_deg is not None]
    square = len(views) - len(turns)
    if turns:
        print(f"  the walls stood {min(turns):+.2f}° to {max(turns):+.2f}° off square (fitted to their points)"
              + (f"; {square} too dark to fit, taken as square" if square else ""))
    print(f"wrote {out}")
    return 0


def cmd_check(args: argparse.Namespace) -> int:
    from omnitof.calibration import load_calibration
    from omnitof.calibration.check import edge_heights, plane_errors, render_check_frame
    from omnitof.viz.calibration import plot_side_view
    from omnitof.errors import OmnitofError
    from omnitof.sensor.design import default_rig

    if args.band is not None and not args.band[0] < args.band[1]:  # else nothing is measured, and it said so with exit 0
        raise OmnitofError(f"--band NEAR FAR: NEAR must be less than FAR, got {args.band[0]:g} {args.band[1]:g}")
    cal = load_calibration(args.calibration)
    truth = load_calibration(args.truth) if args.truth is not None else None
    if args.frame is not None:
        from omnitof.calibration import CalibrationError
        from omnitof.calibration.images import load_images

        frames = load_images([args.frame], **_bag_format(args))
        if not frames or frames[0].distance is None:
            raise CalibrationError("the check needs a distance image (.npz or a ROS bag)", args.frame)
        distance = frames[0].distance
    else:
        rig = default_rig()
        camera, mirrors = rig.camera, rig.mirrors
        if truth is not None:
            camera = truth.camera  # the simulated rig is the design's (render-targets renders it)
        distance = render_check_frame(camera, mirrors, seed=args.seed).distance
    options = {}
    if args.band is not None:
        options["band"] = tuple(args.band)
    if args.min_height is not None:
        options["min_height"] = args.min_height
    check = edge_heights(cal, distance, **options)
    print("upper edges of objects of equal height, seen through each mirror (paper Fig. 6):")
    for line in check.report(list(cal.names)):
        print("  " + line)
    if truth is not None:
        for name, (angle, dd) in plane_errors(cal, truth).items():
            print(f"  {name:>12}: normal error {angle:.3f} deg, distance error {dd:+.2f} mm")
    if args.figure:
        plot_side_view(args.figure, check, cal.names)
        print(f"wrote {args.figure}")
    if not check.measured:
        from omnitof.errors import OmnitofError

        raise OmnitofError(f"the frame shows an upper edge through {len(check.per_mirror)} of {len(cal.names)} "
                           "mirrors, so the check compares nothing: it needs objects of equal height around the "
                           "rig (--band: their near faces' range, --min-height: below their tops)")
    return 0


def cmd_masks(args: argparse.Namespace) -> int:
    from omnitof.calibration import load_calibration, save_calibration
    from omnitof.calibration.masks import (
        labels_from_polygons,
        polygons_from_labels,
        read_polygon_file,
        write_polygon_file,
    )

    cal = load_calibration(args.calibration)
    changed = False
    eroded_by = cal.edge_margin_px  # the margin the stored labels were made with
    if args.margin is not None:
        cal.edge_margin_px = args.margin
    if args.export:
        polygons = cal.polygons or polygons_from_labels(cal.labels, cal.names, margin_px=eroded_by)
        write_polygon_file(args.export, polygons)
        print(f"wrote {args.export}: {len(polygons)} polygons; edit and redraw with --polygons")
    if args.polygons:
        polygons = read_polygon_file(args.polygons)
        cal.labels = labels_from_polygons(cal.camera, cal.names, polygons, cal.edge_margin_px, args.polygons)
        cal.polygons = polygons
        changed = True
    if args.figure:
        from omnitof.viz.calibration import plot_calibration_masks

        plot_calibration_masks(args.figure, cal)
        print(f"wrote {args.figure}")
    counts = {name: int((cal.labels == k).sum()) for k, name in enumerate(cal.names)}
    print("pixels per mirror: " + ", ".join(f"{k} {v}" for k, v in counts.items()))
    if changed or args.out:
        out = args.out or args.calibration
        save_calibration(cal, out)
        print(f"wrote {out}")
    return 0


def _bag_format(args: argparse.Namespace) -> dict:
    """How to read the ROS bags among the images (--tof-topics, --tof-distance)."""
    return {"topics": args.tof_topics, "depth": args.tof_distance == "depth"}
