"""ScanSequence with a fixed and with a per-scan beam geometry."""

from __future__ import annotations

import numpy as np
import pytest

from omnitof.types import ScanSequence, evenly_spaced_beams, pad_rows


def interlaced(n: int = 5) -> ScanSequence:
    """Scans of 3 beams from 0 rad and of 2 beams from 0.05 rad, in turn, 0.1 rad apart."""
    counts = np.where(np.arange(n) % 2 == 0, 3, 2)
    angles, beam_counts = evenly_spaced_beams(0.05 * (np.arange(n) % 2), np.full(n, 0.1), counts, tolerance=1e-9)
    ranges = pad_rows([np.arange(c, dtype=np.float32) + i for i, c in enumerate(counts)], np.inf, np.float32)
    return ScanSequence(np.arange(n) * 0.1, ranges, angles, np.zeros((n, 3)), beam_counts=beam_counts,
                        remissions=np.ones_like(ranges))


def test_fixed_geometry_is_unchanged():
    scans = ScanSequence(np.arange(3.0), np.ones((3, 4)), np.linspace(-1, 1, 4), np.zeros((3, 3)))
    assert not scans.per_scan_geometry and scans.beam_counts is None and scans.n_beams == 4
    assert scans.scan_angles(2) is scans.angles
    np.testing.assert_array_equal(scans.scan_ranges(1), np.ones(4, np.float32))
    assert scans.beam_mask.all() and scans.beam_mask.shape == (3, 4)


def test_per_scan_geometry_accessors_and_padding():
    scans = interlaced()
    assert scans.per_scan_geometry and scans.n_beams == 3
    np.testing.assert_array_equal(scans.beam_counts, [3, 2, 3, 2, 3])
    np.testing.assert_allclose(scans.scan_angles(0), [0.0, 0.1, 0.2])
    np.testing.assert_allclose(scans.scan_angles(1), [0.05, 0.15])
    np.testing.assert_array_equal(scans.scan_ranges(1), [1.0, 2.0])
    # Padding: NaN angles, +inf ranges, 0 remissions; the mask marks the beams.
    assert np.isnan(scans.angles[1, 2]) and scans.ranges[1, 2] == np.inf and scans.remissions[1, 2] == 0
    assert scans.beam_mask.sum() == 13
    part = scans.slice(1, 3)
    np.testing.assert_array_equal(part.beam_counts, [2, 3])
    np.testing.assert_array_equal(part.scan_ranges(0), scans.scan_ranges(1))
    np.testing.assert_array_equal(part.scan_angles(1), scans.scan_angles(2))


def test_padding_is_normalised_on_a_copy():
    angles = np.tile([0.0, 0.1, 0.2], (2, 1))
    ranges = np.ones((2, 3), np.float32)
    scans = ScanSequence([0.0, 1.0], ranges, angles, np.zeros((2, 3)), beam_counts=[3, 1])
    assert np.isnan(scans.angles[1, 1:]).all() and np.isinf(scans.ranges[1, 1:]).all()
    assert np.all(ranges == 1.0) and not np.isnan(angles).any()  # the caller's arrays stay


def test_per_scan_geometry_is_checked():
    angles = np.tile([0.0, 0.1, 0.2], (2, 1))
    ranges = np.ones((2, 3))
    with pytest.raises(ValueError, match="beam_counts must lie in 0..3"):
        ScanSequence([0.0, 1.0], ranges, angles, np.zeros((2, 3)), beam_counts=[3, 4])
    with pytest.raises(ValueError, match=r"beam_counts must be \(2,\)"):
        ScanSequence([0.0, 1.0], ranges, angles, np.zeros((2, 3)), beam_counts=[3])
    with pytest.raises(ValueError, match="needs per-scan angles"):
        ScanSequence([0.0, 1.0], ranges, angles[0], np.zeros((2, 3)), beam_counts=[3, 3])
    with pytest.raises(ValueError, match="finite for every beam"):
        ScanSequence([0.0, 1.0], ranges, np.where(angles > 0.15, np.nan, angles), np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"per-scan angles must have shape \(scans, beams\) = \(2, B\)"):
        ScanSequence([0.0, 1.0], ranges, angles[:1], np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"ranges must have shape \(scans, beams\) = \(2, 3\)"):
        ScanSequence([0.0, 1.0], ranges[:, :2], angles, np.zeros((2, 3)))


def test_stamps_and_poses_that_are_not_finite_are_refused():
    # A NaN stamp made in Python ran through SLAM into the trajectory, where only the TUM file
    # written at the end refused it.
    ranges, angles = np.ones((2, 3)), [0.0, 0.1, 0.2]
    with pytest.raises(ValueError, match="timestamps must be finite; entry 1 is nan"):
        ScanSequence([0.0, np.nan], ranges, angles, np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"odometry must be finite; entry 0 is \[inf"):
        ScanSequence([0.0, 1.0], ranges, angles, [[np.inf, 0, 0], [0, 0, 0]])
    with pytest.raises(ValueError, match="ground_truth must be finite"):
        ScanSequence([0.0, 1.0], ranges, angles, np.zeros((2, 3)), ground_truth=[[0, 0, 0], [0, np.nan, 0]])


def test_evenly_spaced_beams_keeps_one_geometry_where_all_share_it():
    angles, counts = evenly_spaced_beams([-1.0, -1.0 + 1e-8], [0.5, 0.5], [4, 4], tolerance=1e-6)
    assert counts is None
    np.testing.assert_array_equal(angles, -1.0 + 0.5 * np.arange(4))
    angles, counts = evenly_spaced_beams([-1.0, -1.0], [0.5, 0.5], [4, 3], tolerance=1e-6)
    np.testing.assert_array_equal(counts, [4, 3])
    assert angles.shape == (2, 4) and np.isnan(angles[1, 3])
    # A step that differs a little adds up over the beams: the last beam decides.
    _, counts = evenly_spaced_beams([0.0, 0.0], [0.01, 0.01 + 1e-7], [181, 181], tolerance=1e-6)
    assert counts is not None
