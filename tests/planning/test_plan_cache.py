"""The plan cache (cellctl.planning.cache): hits, misses, corrupt and stale entries, and the envelope
check a cached plan passes against the current settings before it is returned."""

from __future__ import annotations

import numpy as np
import pytest
from structlog.testing import capture_logs

from analysis.contracts.placement import Placement
from analysis.design.plates import design_mesh, plate_spec
from cellctl.planning.cache import PLAN_CACHE_VERSION, PlanCache, _entry_bytes, _read_entry, plan_key
from drivers.abb_egm.limits import LinearTrack
from tests.support.plans import SMALL_PLACEMENT, SMALL_SETTINGS


@pytest.fixture(scope="module")
def design():
    return design_mesh(plate_spec("sail", length_mm=200.0, width_mm=150.0), pitch_mm=5.0)


@pytest.fixture
def cache(tmp_path):
    return PlanCache(tmp_path / "plan-cache")


def _ignored(logs) -> list[str]:
    return [e["reason"] for e in logs if e["event"] == "plan_cache_ignored"]


def _rewrite(path, edit) -> None:
    """Read an entry, let ``edit(header, arrays)`` change it, write it back as a valid entry."""
    header, arrays = _read_entry(path.read_bytes())
    edit(header, arrays)
    path.write_bytes(_entry_bytes(header, arrays))


def test_the_second_plan_of_the_same_inputs_is_a_hit_and_equal(cache, design):
    first = cache.plan(design, SMALL_PLACEMENT, SMALL_SETTINGS, with_coverage=False)
    assert not first.hit and cache.path(first.key).exists()
    with capture_logs() as logs:
        second = cache.plan(design, SMALL_PLACEMENT, SMALL_SETTINGS, with_coverage=False)
    assert second.hit and second.key == first.key
    assert any(e["event"] == "plan_cache_hit" for e in logs)
    assert second.plan.summary() == first.plan.summary()
    assert [s.label for s in second.plan.segments] == [s.label for s in first.plan.segments]
    np.testing.assert_allclose(second.plan.trajectory.t_s, first.plan.trajectory.t_s, atol=1e-6)
    np.testing.assert_allclose(second.plan.trajectory.q_deg, first.plan.trajectory.q_deg, atol=1e-6)


def test_a_changed_placement_setting_or_design_is_another_key(design):
    def key(
        mesh=design, placement=SMALL_PLACEMENT, settings=SMALL_SETTINGS, coverage=False, cycle_s=0.004032
    ):
        return plan_key(mesh, placement, settings, with_coverage=coverage, cycle_s=cycle_s)

    track = LinearTrack(
        origin_mm=[0.0, 0.0, 0.0], direction=[0.0, 1.0, 0.0], travel_min_mm=0.0, travel_max_mm=4000.0,
        speed_max_mm_s=500.0,
    )  # fmt: skip
    other_track = LinearTrack(
        origin_mm=[0.0, 0.0, 0.0], direction=[0.0, 1.0, 0.0], travel_min_mm=0.0, travel_max_mm=3999.0,
        speed_max_mm_s=500.0,
    )  # fmt: skip
    bent = design_mesh(plate_spec("sail", length_mm=200.0, width_mm=150.0, radius_x_mm=3000.0), pitch_mm=5.0)
    same = design_mesh(plate_spec("sail", length_mm=200.0, width_mm=150.0), pitch_mm=5.0)
    assert key() == key(mesh=same)  # the design's content, not the object
    others = [
        key(placement=Placement.on_bed(1600.0, 100.5, 3.0, z_mm=300.0)),
        key(settings=SMALL_SETTINGS.with_(overlap_fraction=0.3)),
        key(settings=SMALL_SETTINGS.with_(tcp_speed_max_mm_s=240.0)),
        key(coverage=True),
        key(cycle_s=0.008),
        key(settings=SMALL_SETTINGS.with_(track=track)),
        key(settings=SMALL_SETTINGS.with_(track=other_track)),
        key(mesh=bent),
    ]
    assert len({key(), *others}) == len(others) + 1


def test_a_changed_placement_is_a_miss(cache, design):
    cache.plan(design, SMALL_PLACEMENT, SMALL_SETTINGS, with_coverage=False)
    moved = Placement.on_bed(1600.0, 110.0, 3.0, z_mm=300.0)
    again = cache.plan(design, moved, SMALL_SETTINGS, with_coverage=False)
    assert not again.hit
    assert again.plan.placement == moved
    assert len(list(cache.root.glob("*.npz"))) == 2


def test_a_corrupt_entry_is_a_miss_with_a_log_line_and_is_replanned(cache, design):
    first = cache.plan(design, SMALL_PLACEMENT, SMALL_SETTINGS, with_coverage=False)
    path = cache.path(first.key)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])  # cut short, as by a crash
    with capture_logs() as logs:
        again = cache.plan(design, SMALL_PLACEMENT, SMALL_SETTINGS, with_coverage=False)
    assert not again.hit
    assert any(r.startswith("corrupt") for r in _ignored(logs)), logs
    assert cache.plan(design, SMALL_PLACEMENT, SMALL_SETTINGS, with_coverage=False).hit  # rewritten


def test_a_stale_version_or_another_keys_entry_is_ignored(cache, design):
    first = cache.plan(design, SMALL_PLACEMENT, SMALL_SETTINGS, with_coverage=False)
    path = cache.path(first.key)
    good = path.read_bytes()
    stale = "cellctl.plan_cache/7+cellctl.scan_plan/1"
    assert stale != PLAN_CACHE_VERSION
    _rewrite(path, lambda h, a: h.update(version=stale))
    with capture_logs() as logs:
        assert cache.load(first.key, SMALL_PLACEMENT, SMALL_SETTINGS) is None
    assert any(r.startswith("stale") for r in _ignored(logs))
    assert not path.exists()
    path.write_bytes(good)
    _rewrite(path, lambda h, a: h.update(key="0" * 64))
    with capture_logs() as logs:
        assert cache.load(first.key, SMALL_PLACEMENT, SMALL_SETTINGS) is None
    assert any("another key" in r for r in _ignored(logs))


def test_a_cached_plan_is_refused_by_the_envelope_of_a_tighter_config(cache, design):
    first = cache.plan(design, SMALL_PLACEMENT, SMALL_SETTINGS, with_coverage=False)
    # the same entry checked against settings whose TCP speed cap is below the plan's sweep speed
    tighter = SMALL_SETTINGS.with_(tcp_speed_max_mm_s=150.0)
    with capture_logs() as logs:
        assert cache.load(first.key, SMALL_PLACEMENT, tighter) is None
    reasons = _ignored(logs)
    assert reasons and "envelope" in reasons[0] and "tcp" in reasons[0].lower(), reasons
    assert not cache.path(first.key).exists()


def test_an_entry_edited_outside_the_joint_limits_is_refused_on_a_hit(cache, design):
    first = cache.plan(design, SMALL_PLACEMENT, SMALL_SETTINGS, with_coverage=False)
    path = cache.path(first.key)

    def beyond(header, arrays):  # a valid entry, same key: joint 1 far beyond its limit
        arrays["q_deg"][len(arrays["q_deg"]) // 2 :, 0] += 400.0

    _rewrite(path, beyond)
    with capture_logs() as logs:
        again = cache.plan(design, SMALL_PLACEMENT, SMALL_SETTINGS, with_coverage=False)
    assert not again.hit
    assert any("envelope" in r for r in _ignored(logs))
    np.testing.assert_allclose(again.plan.trajectory.q_deg, first.plan.trajectory.q_deg, atol=1e-6)


def test_a_track_plan_is_cached_with_its_seven_axes(cache):
    track = LinearTrack(
        origin_mm=[0.0, 0.0, 0.0], direction=[0.0, 1.0, 0.0], travel_min_mm=0.0, travel_max_mm=4000.0,
        speed_max_mm_s=500.0, accel_max_mm_s2=1000.0, jerk_max_mm_s3=10000.0,
    )  # fmt: skip
    settings = SMALL_SETTINGS.with_(track=track)
    placement = Placement.on_bed(1500.0, 2000.0, 90.0, z_mm=300.0)
    mesh = design_mesh(plate_spec("sail", length_mm=300.0, width_mm=150.0), pitch_mm=5.0)
    first = cache.plan(mesh, placement, settings, with_coverage=False)
    second = cache.plan(mesh, placement, settings, with_coverage=False)
    assert second.hit and second.plan.trajectory.q_deg.shape[1] == 7
    np.testing.assert_allclose(second.plan.trajectory.q_deg, first.plan.trajectory.q_deg, atol=1e-6)


def test_the_cache_keeps_at_most_max_entries(tmp_path, design):
    cache = PlanCache(tmp_path / "c", max_entries=1)
    a = cache.plan(design, SMALL_PLACEMENT, SMALL_SETTINGS, with_coverage=False)
    b = cache.plan(
        design, Placement.on_bed(1600.0, 110.0, 3.0, z_mm=300.0), SMALL_SETTINGS, with_coverage=False
    )
    assert not cache.path(a.key).exists() and cache.path(b.key).exists()


_ARRAY_FIELDS = ("t_s", "q_deg", "qd_deg_s", "qdd_deg_s2", "segment")


def test_a_track_plan_round_trips_bit_for_bit_in_the_binary_entry(cache):
    track = LinearTrack(
        origin_mm=[0.0, 0.0, 0.0], direction=[0.0, 1.0, 0.0], travel_min_mm=0.0, travel_max_mm=4000.0,
        speed_max_mm_s=500.0, accel_max_mm_s2=1000.0, jerk_max_mm_s3=10000.0,
    )  # fmt: skip
    settings = SMALL_SETTINGS.with_(track=track)
    placement = Placement.on_bed(1500.0, 2000.0, 90.0, z_mm=300.0)
    mesh = design_mesh(plate_spec("sail", length_mm=300.0, width_mm=150.0), pitch_mm=5.0)
    fresh = cache.plan(mesh, placement, settings, with_coverage=True)
    hit = cache.plan(mesh, placement, settings, with_coverage=True)
    assert not fresh.hit and hit.hit and cache.path(hit.key).suffix == ".npz"
    a, b = fresh.plan, hit.plan
    assert b.trajectory.q_deg.shape[1] == 7
    for name in _ARRAY_FIELDS:  # not within a tolerance: the same numbers
        x, y = getattr(a.trajectory, name), getattr(b.trajectory, name)
        assert x.dtype == y.dtype and np.array_equal(x, y), name
    assert len(a.segments) == len(b.segments)
    for s, t in zip(a.segments, b.segments, strict=True):
        assert (s.kind, s.label, s.flying, s.joint_line) == (t.kind, t.label, t.flying, t.joint_line)
        assert (s.t_start_s, s.duration_s, s.length_mm) == (t.t_start_s, t.duration_s, t.length_mm)
        assert np.array_equal(s.pos_mm, t.pos_mm) and np.array_equal(s.R_base_sensor, t.R_base_sensor)
        assert np.array_equal(s.q_deg, t.q_deg)
    assert b.summary() == a.summary() and b.coverage == a.coverage and b.placement == a.placement
    assert (b.scan_time_s, b.toppra_time_s, b.footprint_mm) == (
        a.scan_time_s,
        a.toppra_time_s,
        a.footprint_mm,
    )


def test_a_flipped_byte_in_an_array_is_refused_as_corrupt(cache, design):
    first = cache.plan(design, SMALL_PLACEMENT, SMALL_SETTINGS, with_coverage=False)
    path = cache.path(first.key)
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x01  # one bit, inside an array's data: the archive still opens
    path.write_bytes(bytes(data))
    with capture_logs() as logs:
        again = cache.plan(design, SMALL_PLACEMENT, SMALL_SETTINGS, with_coverage=False)
    assert not again.hit
    assert any(r.startswith("corrupt") for r in _ignored(logs)), _ignored(logs)


def test_an_entry_of_the_json_format_is_not_read_and_is_removed(cache, design):
    first = cache.plan(design, SMALL_PLACEMENT, SMALL_SETTINGS, with_coverage=False, store=False)
    old = cache.root / f"{first.key}.json"  # where version 7 kept it
    old.write_text(first.plan.to_json())
    assert cache.load(first.key, SMALL_PLACEMENT, SMALL_SETTINGS) is None  # not read: a miss
    cache.store(first.key, first.plan)
    assert not old.exists() and cache.path(first.key).exists()


def test_a_foreign_archive_or_file_is_refused_as_foreign_and_replanned(cache, design):
    first = cache.plan(design, SMALL_PLACEMENT, SMALL_SETTINGS, with_coverage=False)
    path = cache.path(first.key)
    good = path.read_bytes()
    np.savez(path.with_suffix(".tmp.npz"), points=np.zeros((4, 3)))  # another program's numpy archive
    path.with_suffix(".tmp.npz").replace(path)
    with capture_logs() as logs:
        again = cache.plan(design, SMALL_PLACEMENT, SMALL_SETTINGS, with_coverage=False)
    assert not again.hit
    assert any(r.startswith("foreign") and "header" in r for r in _ignored(logs)), _ignored(logs)
    path.write_text("not an archive at all\n")
    with capture_logs() as logs:
        assert cache.load(first.key, SMALL_PLACEMENT, SMALL_SETTINGS) is None
    assert any(r.startswith("corrupt") for r in _ignored(logs)), _ignored(logs)
    assert not path.exists()
    path.write_bytes(good)
    assert cache.load(first.key, SMALL_PLACEMENT, SMALL_SETTINGS) is not None


def test_a_header_with_an_unknown_or_wrongly_typed_field_is_refused_as_corrupt(cache, design):
    first = cache.plan(design, SMALL_PLACEMENT, SMALL_SETTINGS, with_coverage=False)
    path = cache.path(first.key)
    good = path.read_bytes()
    _rewrite(path, lambda h, a: h["plan"]["segments"][0].update(extra_field=1))
    with capture_logs() as logs:
        assert cache.load(first.key, SMALL_PLACEMENT, SMALL_SETTINGS) is None
    assert any(r.startswith("corrupt: ValidationError") for r in _ignored(logs)), _ignored(logs)
    path.write_bytes(good)
    _rewrite(path, lambda h, a: h["plan"]["segments"][0].update(n="many"))
    with capture_logs() as logs:
        assert cache.load(first.key, SMALL_PLACEMENT, SMALL_SETTINGS) is None
    assert any(r.startswith("corrupt: ValidationError") for r in _ignored(logs)), _ignored(logs)
