"""The simulated cell's truth check leaves out frames rendered at an extrapolated pose, but only a
few (issue 46: it dropped them with no bound). No simulator runs here: the frames' true exposure
times and the late poses are set by hand, the way SimCell records them during a run."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from tests.support.simcell import MAX_EXTRAPOLATED_SHARE, SimCell, SimCellConfig, SimulatorStarved


def _cell(late_frames: int, n: int = 1000, continued_s: float = 0.004) -> tuple[SimCell, np.ndarray]:
    cell = SimCell(scene=None, config=SimCellConfig(), settings=None, job_dir=None, q_start_deg=np.zeros(6))
    period_s = 0.005
    cell.sensor = SimpleNamespace(exposure_mid_true_s=lambda f: 10.0 + np.asarray(f) * period_s)
    frames = np.arange(n)
    cell.extrapolated_t_s = (10.0 + frames[:late_frames] * period_s).tolist()
    cell.poses_extrapolated = late_frames
    cell.max_extrapolation_s = continued_s if late_frames else 0.0
    return cell, frames


def test_a_few_late_frames_are_left_out_of_the_truth_check() -> None:
    cell, frames = _cell(late_frames=int(MAX_EXTRAPOLATED_SHARE * 1000))
    ok = cell.truth_reliable(frames)
    assert np.count_nonzero(~ok) == 50 and not ok[:50].any() and ok[50:].all()


def test_more_late_frames_than_the_bound_fail_with_the_counts() -> None:
    cell, frames = _cell(late_frames=int(MAX_EXTRAPOLATED_SHARE * 1000) + 1)
    with pytest.raises(SimulatorStarved, match=r"51 of 1000 frames .* starved"):
        cell.truth_reliable(frames)


def test_a_pose_continued_too_long_fails_even_for_one_frame() -> None:
    cell, frames = _cell(late_frames=1, continued_s=0.5)
    with pytest.raises(SimulatorStarved, match=r"500\.0 ms"):
        cell.truth_reliable(frames)


def test_a_run_that_kept_time_leaves_nothing_out() -> None:
    cell, frames = _cell(late_frames=0)
    assert cell.truth_reliable(frames).all()
