"""The published cloud: thinned along the line, grid kept, encoded once."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellctl.acquisition.assembly import AssembledScan, AssemblyError
from cellctl.acquisition.publish import PublishSettings, column_steps, encode_scan, publication_cloud
from cellctl.api.cloud_codec import CloudMeta, decode_cloud
from cellctl.config import CellConfig


def _scan(n: int = 12, w: int = 20, seed: int = 0) -> AssembledScan:
    rng = np.random.default_rng(seed)
    xyz = rng.normal(size=(n, w, 3)).astype(np.float32)
    valid = rng.random((n, w)) > 0.2
    xyz[~valid] = np.nan
    return AssembledScan(
        profile_index=np.arange(100, 100 + n, dtype=np.int64),
        frame_index=np.arange(n, dtype=np.uint64),
        pass_id=np.repeat(np.arange(-1, n // 4 - 1, dtype=np.int32), 4)[:n],
        t_ns=np.arange(n, dtype=np.int64) * 5_000_000,
        xyz_mm=xyz,
        valid=valid,
        sensor_pos_mm=np.zeros((n, 3), np.float32),
    )


def test_points_with_step_one_are_every_valid_point():
    sc = _scan()
    a, b = sc.points(), sc.points(1)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    assert len(a["xyz_mm"]) == sc.n_valid


@given(k=st.integers(1, 7), seed=st.integers(0, 1000))
@settings(max_examples=30, deadline=None)
def test_thinned_points_are_every_kth_column_renumbered_densely(k, seed):
    sc = _scan(seed=seed)
    pts = sc.points(k)
    r, c = np.nonzero(sc.valid)
    keep = c % k == 0
    np.testing.assert_array_equal(pts["xyz_mm"], sc.xyz_mm[r[keep], c[keep]])
    np.testing.assert_array_equal(pts["point_index"], c[keep] // k)
    np.testing.assert_array_equal(pts["profile_index"], sc.profile_index[r[keep]])
    # the same through the per-profile form
    per_row = sc.points(np.full(len(sc), k))
    for name in pts:
        np.testing.assert_array_equal(pts[name], per_row[name])


def test_per_profile_steps_thin_each_profile_by_its_own_step():
    sc = _scan(n=8, w=12)
    steps = np.array([1, 1, 3, 3, 2, 2, 4, 4])
    pts = sc.points(steps)
    for row in range(len(sc)):
        mine = pts["profile_index"] == sc.profile_index[row]
        cols = np.nonzero(sc.valid[row])[0]
        cols = cols[cols % steps[row] == 0]
        np.testing.assert_array_equal(pts["point_index"][mine], cols // steps[row])
        np.testing.assert_array_equal(pts["xyz_mm"][mine], sc.xyz_mm[row, cols])


@pytest.mark.parametrize("bad", [0, -2, np.array([1, 0]), np.ones(3, int)])
def test_points_refuse_a_step_below_one_or_of_the_wrong_shape(bad):
    with pytest.raises(AssemblyError, match="column_step"):
        _scan(n=2).points(bad)


def test_column_steps_give_edge_passes_their_own_pitch():
    s = PublishSettings(native_pitch_mm=0.1, pitch_mm=0.5, edge_pitch_mm=0.2)
    pid = np.array([-1, 0, 1, 2, 3, 4])
    np.testing.assert_array_equal(column_steps(pid, 3, s), [5, 5, 5, 5, 2, 2])
    np.testing.assert_array_equal(column_steps(pid, None, s), [5] * 6)
    assert PublishSettings(native_pitch_mm=0.1, pitch_mm=0.0).step(0.0) == 1  # 0: every point


def test_publish_settings_follow_the_sensor_and_the_scan_section():
    cfg = CellConfig.model_validate(
        {"laser": {"line_width_mm": 50.0, "points_per_profile": 501}, "scan": {"publish_pitch_mm": 0.3}}
    )
    s = PublishSettings.from_config(cfg)
    assert s.native_pitch_mm == pytest.approx(0.1) and s.step(s.pitch_mm) == 3
    with pytest.raises(ValueError, match="pitch_mm"):
        PublishSettings(pitch_mm=-1.0)


def test_encoded_scan_decodes_to_the_thinned_points_with_transit_in_pass_zero():
    sc = _scan(n=16, w=30, seed=3)
    payload, n = encode_scan(sc, job_id="j1", plate_id="p1", column_step=3, meta=CloudMeta(cell_id="c"))
    cloud = decode_cloud(payload)
    pts = sc.points(3)
    assert n == cloud.n_points == len(pts["xyz_mm"])
    assert (cloud.job_id, cloud.plate_id, cloud.meta.cell_id) == ("j1", "p1", "c")
    np.testing.assert_array_equal(cloud.xyz_mm, pts["xyz_mm"])
    np.testing.assert_array_equal(cloud.point_index, pts["point_index"])
    np.testing.assert_array_equal(cloud.pass_id, np.maximum(pts["pass_id"], 0))
    np.testing.assert_allclose(cloud.t_s, (pts["t_ns"] - sc.t_ns.min()) * 1e-9)  # s from the first profile
    assert publication_cloud(sc, job_id="j", plate_id="p").n_points == sc.n_valid
    # the worker's cloud is the analysis' type, with the same arrays as the acquisition's files
    same = sc.scan_cloud(3)
    got = cloud.scan_cloud()
    for name in ("xyz_mm", "pass_id", "profile_index", "point_index", "t_s"):
        np.testing.assert_array_equal(getattr(got, name), getattr(same, name))
