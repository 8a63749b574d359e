"""The locate run's passes along the bed (cellctl/daemon/locate.py): the fewest that still cross every
lay of the plate twice (issue 42: the 6 m plate's locate run), and the configured spacing kept where
that gives no fewer."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from analysis.contracts.placement import Placement, placement_transform
from analysis.design.plates import design_mesh, plate_spec
from cellctl.config import load_config
from cellctl.daemon.locate import LOCATE_MIN_CROSSINGS, _fewest_passes, _outline_vertices, next_locate_plans

REPO = Path(__file__).resolve().parents[2]


def _lays(cfg, design, n: int, yaw_spread_deg: float, rng) -> list[Placement]:
    """Random lays wholly on the [locate] bed, the design's x within ``yaw_spread_deg`` of the bed's
    long axis."""
    lo, hi = np.asarray(cfg.locate.bed_min_xy_mm), np.asarray(cfg.locate.bed_max_xy_mm)
    axis = 0.0 if (hi - lo)[0] >= (hi - lo)[1] else 90.0
    xy = design.vertices_mm[_outline_vertices(design), :2]
    out = []
    while len(out) < n:
        yaw = axis + rng.uniform(-yaw_spread_deg, yaw_spread_deg) + rng.choice([0.0, 180.0])
        a = np.deg2rad(yaw)
        R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        w = xy @ R.T
        span_lo, span_hi = lo - w.min(axis=0), hi - w.max(axis=0)
        if np.any(span_lo > span_hi):
            continue
        x, y = rng.uniform(span_lo, span_hi)
        out.append(Placement.on_bed(float(x), float(y), float(yaw), z_mm=600.0))
    return out


def test_a_6m_plate_on_the_long_bed_is_crossed_twice_by_two_passes_wherever_it_lies():
    cfg = load_config(REPO / "docs" / "examples" / "cell-track.toml")
    design = design_mesh(plate_spec("sail", length_mm=6000.0, width_mm=2000.0), pitch_mm=50.0)
    along = next_locate_plans(cfg, design, [], None)[0]
    assert len(along.plan.passes) == 2  # 6 at the configured 350 mm
    lo, hi = np.asarray(cfg.locate.bed_min_xy_mm), np.asarray(cfg.locate.bed_max_xy_mm)
    across_axis = int(np.argmin(hi - lo))
    pass_at = [float(np.median(p.pos_mm[:, across_axis])) for p in along.plan.passes]
    outline = design.vertices_mm[_outline_vertices(design)]
    for lay in _lays(cfg, design, 300, 5.0, np.random.default_rng(42)):
        T = placement_transform(lay)
        c = (outline @ T[:3, :3].T + T[:3, 3])[:, across_axis]
        crossed = sum(c.min() + 25.0 < p < c.max() - 25.0 for p in pass_at)
        assert crossed >= LOCATE_MIN_CROSSINGS, (lay, pass_at)


def test_the_sail_keeps_its_configured_passes_and_fewer_are_taken_only_where_they_suffice():
    cfg = load_config(REPO / "cell.toml")
    sail = design_mesh(plate_spec("sail"), pitch_mm=10.0)
    along = next_locate_plans(cfg, sail, [], None)[0]
    assert len(along.plan.passes) == 4  # 350 mm over the 1400 mm bed, as before
    assert _fewest_passes(1400.0, 350.0, 800.0) == (4, 350.0)
    assert _fewest_passes(500.0, 120.0, 200.0) == (5, 120.0)  # the e2e test's plate and bed
    n, w = _fewest_passes(2100.0, 350.0, 2000.0)
    assert n == 2 and 1050.0 <= w < 1050.1
    # a plate only a little wider than half the bed: the band every lay covers holds one pass
    n, _ = _fewest_passes(2100.0, 350.0, 1200.0)
    assert 2 < n < 6
