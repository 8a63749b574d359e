"""``[robot.track]``: present or absent, its limits and frame validated with a reason."""

from __future__ import annotations

import numpy as np
import pytest

from cellctl.config import ConfigError, parse_config

ROBOT = {"egm_max_pos_deviation_deg": 10_000.0}


def test_absent_track_means_a_fixed_base():
    assert parse_config({}).robot.track is None


def test_present_track_gives_the_kinematic_track_with_the_usable_travel():
    cfg = parse_config({"robot": {**ROBOT, "track": {"travel_min_mm": -200.0, "travel_max_mm": 5800.0,
                                                     "margin_mm": 20.0, "origin_mm": [100.0, 2500.0, 0.0],
                                                     "direction": [0.0, -3.0, 0.0]}}})  # fmt: skip
    track = cfg.robot.track.linear_track()
    assert (track.travel_min_mm, track.travel_max_mm) == (-180.0, 5780.0)
    np.testing.assert_array_equal(track.direction, [0.0, -1.0, 0.0])
    np.testing.assert_array_equal(track.base_pos_mm(1000.0), [100.0, 1500.0, 0.0])


@pytest.mark.parametrize(
    ("track", "expected"),
    [
        ({"travel_min_mm": 100.0, "travel_max_mm": 100.0}, "must be below travel_max_mm"),
        ({"travel_max_mm": 60_000.0}, "reaches beyond"),
        ({"margin_mm": 3000.0}, "margin_mm leaves no usable travel"),
        ({"direction": [0.0, 0.0, 0.0]}, "direction must not be the zero vector"),
        ({"speed_max_mm_s": 0.0}, "robot.track.speed_max_mm_s = 0"),
        ({"accel_max_mm_s2": 50_000.0}, "robot.track.accel_max_mm_s2"),
        ({"speed_max_mm_s": True}, "expected a number, got a boolean"),
        ({"travel": 5.0}, "robot.track.travel"),
    ],
)
def test_bad_track_is_refused_with_its_reason(track: dict, expected: str):
    with pytest.raises(ConfigError) as info:
        parse_config({"robot": {**ROBOT, "track": track}})
    assert expected in str(info.value)


def test_max_pos_deviation_below_the_track_travel_is_refused():
    with pytest.raises(ConfigError, match="MaxPosDeviation also bounds the track"):
        parse_config({"robot": {"egm_max_pos_deviation_deg": 1000.0, "track": {"travel_max_mm": 3000.0}}})


def test_simulated_track_start_outside_the_travel_is_refused():
    with pytest.raises(ConfigError, match="egm_track_start_mm"):
        parse_config(
            {"robot": {**ROBOT, "track": {"travel_max_mm": 3000.0}}, "sim": {"egm_track_start_mm": 3500.0}}
        )
    cfg = parse_config(
        {"robot": {**ROBOT, "track": {"travel_max_mm": 3000.0}}, "sim": {"egm_track_start_mm": 1500.0}}
    )
    assert cfg.sim.egm_track_start_mm == 1500.0
