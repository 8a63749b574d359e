"""Stage 3 of the registration: the non-penetrating (one-sided) fit (2.2.3).

:func:`nonpenetrating_fit` rests the design on the measured plate like a worker's template, on or
above every measured point in the deflection direction, as close as possible in the least-squares
sense. Solved on every surface point: linearised rotation, six unknowns, one linear constraint per
point with its exact Jacobian, an exact active-set solution of that small quadratic programme
(:func:`solve_onesided_qp`), correspondences renewed in an outer loop. :func:`deflection_gaps` are
the gaps along the deflection direction (+z of the measurement frame) it constrains.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from itertools import pairwise

import numpy as np
import structlog

from analysis.register.height_field import HeightField
from analysis.register.icp import BOUNDARY_WEIGHT, CORNER_SIGMA_MM, _corner_terms, _matched_corners
from analysis.register.transforms import (
    RegistrationError,
    _check_points,
    _check_transform,
    invert_transform,
    make_transform,
    rotation_from_vector,
)

log = structlog.get_logger(__name__)


# --------------------------------------------------------------------------------------------------
# 3. non-penetrating fit (2.2.3)


@dataclass(frozen=True)
class NonPenetratingResult:
    """One-sided (template-resting) fit of the design onto the measured surface.

    transform: (4, 4) design -> measured, mm.
    objective_mm2: sum of squared gaps (design minus measured, along +z of the measured frame).
    rms_mm: sqrt(objective / points). min_gap_mm: smallest gap (>= 0 after the fit).
    iterations: outer (correspondence) iterations. qp_iterations: active-set steps, all together.
    points: measured points constrained (on the design's footprint, within the rejection distance).
    penetrating_before / penetrating_after: points with a negative gap at the start / the end.
    active_points: constraints active (gap 0) at the solution.
    """

    transform: np.ndarray
    objective_mm2: float
    rms_mm: float
    min_gap_mm: float
    iterations: int
    qp_iterations: int
    points: int
    penetrating_before: int
    penetrating_after: int
    active_points: int
    converged: bool


def deflection_gaps(
    surface: HeightField,
    measured_points_mm: np.ndarray,
    T_meas_design: np.ndarray,
    up: np.ndarray = np.array([0.0, 0.0, 1.0]),
    newton_steps: int = 2,
    geometry: bool = True,
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray]:
    """Gap from each measured point to the moved design surface along the deflection direction.

    measured_points_mm: (n, 3) mm, measured frame; up: (3,) deflection direction, measured frame.
    Returns ``(gap_mm (n,), surface_point_mm (n, 3) design frame, normal (n, 3) design frame,
    valid (n,) bool)``. The gap is positive when the design lies above the point (no penetration).
    The intersection of the ray ``p + s * up`` with z = f(x, y) is found by Newton's method.
    ``geometry=False`` skips the surface points and normals (returned as None) when only the gaps
    are wanted. Large clouds are split over a small thread pool: numpy releases the GIL on whole
    arrays, so both cores work, and the answer is the same.
    """
    g = _ray_gaps(surface, measured_points_mm, T_meas_design, up, newton_steps, geometry)
    if not geometry:
        return g.gap_mm, None, None, g.valid
    m = g.tilt.T
    return g.gap_mm, g.q_design_mm.T, m / np.linalg.norm(m, axis=1, keepdims=True), g.valid


@dataclass(frozen=True)
class _RayGaps:
    """Gaps along the deflection direction in the column layout the fit works in.

    gap_mm (n,); valid (n,) bool; q_design_mm (3, n) the ray/surface intersections, design frame;
    tilt (3, n) the surface normals scaled to a unit z component, ``(-dz/dx, -dz/dy, 1)`` (the
    Jacobian needs only their direction over their projection on the ray, so no square root).
    The geometry rows are None when not asked for.
    """

    gap_mm: np.ndarray
    valid: np.ndarray
    q_design_mm: np.ndarray | None = None
    tilt: np.ndarray | None = None


def _ray_gaps(
    surface: HeightField,
    measured_points_mm: np.ndarray,
    T_meas_design: np.ndarray,
    up: np.ndarray,
    newton_steps: int,
    geometry: bool,
) -> _RayGaps:
    """:func:`deflection_gaps` in column layout, split over the thread pool for large clouds."""
    n = len(measured_points_mm)
    T_inv = invert_transform(np.asarray(T_meas_design, dtype=np.float64))
    up = np.asarray(up, dtype=np.float64)
    u = T_inv[:3, :3] @ (up / np.linalg.norm(up))
    _ = surface.cells  # build the shared table once, before the threads read it
    workers = _gap_workers()
    if workers < 2 or n < 2 * _PARALLEL_MIN_POINTS:
        return _ray_gaps_serial(surface, measured_points_mm, T_inv, u, newton_steps, geometry)
    # blocks of at most _GAP_BLOCK_POINTS, two at a time: the per-point temporaries of a block (about
    # 40 float64 columns) stay bounded whatever the cloud (a 6 m plate's 28 M points: ~9 GB at once)
    bounds = np.linspace(0, n, max(workers, -(-n // _GAP_BLOCK_POINTS)) + 1).astype(int)
    parts = list(
        _gap_pool().map(
            lambda ab: _ray_gaps_serial(
                surface, measured_points_mm[ab[0] : ab[1]], T_inv, u, newton_steps, geometry
            ),
            pairwise(bounds),
        )
    )
    s = np.concatenate([p.gap_mm for p in parts])
    valid = np.concatenate([p.valid for p in parts])
    if not geometry:
        return _RayGaps(s, valid)
    q = np.concatenate([p.q_design_mm for p in parts], axis=1)
    return _RayGaps(s, valid, q, np.concatenate([p.tilt for p in parts], axis=1))


_PARALLEL_MIN_POINTS = 100_000
_GAP_BLOCK_POINTS = 1_000_000
_POOL: ThreadPoolExecutor | None = None


def _gap_workers() -> int:
    return min(os.cpu_count() or 1, 4)


def _gap_pool() -> ThreadPoolExecutor:
    global _POOL
    if _POOL is None:
        _POOL = ThreadPoolExecutor(max_workers=_gap_workers(), thread_name_prefix="gaps")
    return _POOL


def _ray_gaps_serial(
    surface: HeightField,
    measured_points_mm: np.ndarray,
    T_inv: np.ndarray,
    u: np.ndarray,
    newton_steps: int,
    geometry: bool,
) -> _RayGaps:
    """Gaps of one block of points, in the calling thread. T_inv: (4, 4) measured -> design;
    u: (3,) the unit deflection direction in the design frame."""
    # (3, 3) @ (3, n): one BLAS call, and each coordinate row comes out contiguous
    p = T_inv[:3, :3] @ np.asarray(measured_points_mm, dtype=np.float64).T
    p += T_inv[:3, 3:4]
    px, py, pz = p
    ux, uy, uz = float(u[0]), float(u[1]), float(u[2])
    # Newton on F(s) = f(p_xy + s u_xy) - (p_z + s u_z) from s = 0; the ray is within a few degrees
    # of the design's z, so two steps leave an error of order slope change * tilt^2, far below a
    # nanometre. The first step reads the surface at p_xy itself.
    z, sx, sy, valid = surface.lookup(px, py)
    F = z - pz
    den = sx * ux
    den += sy * uy
    den -= uz
    s = F / den
    np.negative(s, out=s)
    for _ in range(1, newton_steps):
        z, sx, sy, ok = surface.lookup(px + s * ux, py + s * uy)
        valid &= ok
        F = z - (pz + s * uz)
        den = sx * ux
        den += sy * uy
        den -= uz
        s -= F / den
    if not geometry:
        return _RayGaps(s, valid)
    q = p + np.outer(u, s)
    tilt = np.empty_like(p)
    np.negative(sx, out=tilt[0])
    np.negative(sy, out=tilt[1])
    tilt[2] = 1.0
    return _RayGaps(s, valid, q, tilt)


def _active_set_qp(
    H: np.ndarray, g: np.ndarray, A: np.ndarray, b: np.ndarray, x0: np.ndarray, max_iter: int = 200
) -> tuple[np.ndarray, int, np.ndarray]:
    """Exact primal active-set solution of min 1/2 x'Hx + g'x subject to A x >= b (Nocedal-Wright 16.3).

    H (k, k) positive definite, A (m, k), b (m,), x0 (k,) feasible. k is 6 here and m may be 10^6:
    each step solves a KKT system of at most 6 + 6 unknowns and scans all constraints once for the
    blocking one. Returns ``(x, iterations, working set indices)``.
    """
    k = len(g)
    x = x0.copy()
    W: list[int] = []
    for it in range(1, max_iter + 1):
        grad = H @ x + g
        # equality-constrained step in the null space of the working constraints: A_W p = 0 holds
        # to round-off, which a full KKT solve of this badly scaled system does not guarantee
        if W:
            _, sv, Vt = np.linalg.svd(A[W])
            rank = int((sv > 1e-12 * sv[0]).sum())
            Z = Vt[rank:].T
        else:
            Z = np.eye(k)
        if Z.shape[1]:
            p = Z @ np.linalg.solve(Z.T @ H @ Z, -(Z.T @ grad))
        else:
            p = np.zeros(k)
        # p is "zero" when it would not lower the objective measurably (scale-free test)
        gain = -(grad @ p) - 0.5 * (p @ H @ p)
        f = 0.5 * (x @ H @ x) + g @ x
        if gain <= 1e-12 * (1.0 + abs(f)):
            if not W:
                return x, it, np.asarray(W, dtype=np.intp)
            lam = np.linalg.lstsq(A[W].T, H @ (x + p) + g, rcond=None)[0]
            if lam.min() >= -1e-9 * (1.0 + np.abs(lam).max()):
                return x, it, np.asarray(W, dtype=np.intp)
            W.pop(int(np.argmin(lam)))
            continue
        Ap = A @ p
        slack = np.maximum(A @ x - b, 0.0)
        blocking = Ap < 0.0
        if W:
            blocking[W] = False
        alpha, j = 1.0, -1
        if blocking.any():
            idx = np.flatnonzero(blocking)
            ratios = slack[idx] / -Ap[idx]
            m = int(np.argmin(ratios))
            if ratios[m] < 1.0:
                alpha, j = float(ratios[m]), int(idx[m])
        x = x + alpha * p
        if j >= 0:
            W.append(j)
    raise RegistrationError(f"active-set QP did not converge in {max_iter} steps")


def solve_onesided_qp(
    J: np.ndarray,
    s: np.ndarray,
    lift: np.ndarray,
    damping: float,
    K: np.ndarray | None = None,
    e: np.ndarray | None = None,
    box: float | None = None,
) -> tuple[np.ndarray, int, int]:
    """min ||s + J x||^2 + ||e + K x||^2 + damping ||x||^2 subject to s + J x >= 0, exactly.

    J (m, k) with k unknowns (6 here, 3 for a motion in a section plane).

    By constraint generation: the objective uses every row; the constraints start with the rows of smallest gap and grow by
    the violated ones until none is violated -- then the solution of the reduced problem is the
    solution of the full one (it is feasible for a relaxation's optimum). J (m, 6), s (m,).
    lift (6,): the parameter vector that adds exactly 1 mm to every gap (a pure lift along the
    deflection direction), which gives a feasible start. box: optional trust region, |x_i| <= box
    for every parameter (12 more linear constraints, always in the working problem). Returns ``(x, active-set steps, active constraints)``.
    """
    k = J.shape[1]  # 6 for a rigid motion in space, 3 for one in a section plane
    H = J.T @ J
    H[np.diag_indices(k)] += damping
    g = J.T @ s
    if K is not None and e is not None and len(e):
        H += K.T @ K
        g += K.T @ e
    m = len(s)
    x0 = max(0.0, -float(s.min())) * lift
    if box is not None:
        box = max(box, 1.5 * float(np.abs(x0).max()))  # the lift itself must stay allowed
        Abox = np.vstack([np.eye(k), -np.eye(k)])
        bbox = np.full(2 * k, -box)
    else:
        Abox, bbox = np.zeros((0, k)), np.zeros(0)
    k0 = min(m, 256)
    work = np.argpartition(s, k0 - 1)[:k0] if k0 < m else np.arange(m)
    steps = 0
    for _ in range(50):
        A = np.vstack([J[work], Abox])
        b = np.concatenate([-s[work], bbox])
        x, it, active = _active_set_qp(H, g, A, b, x0)
        steps += it
        viol = np.flatnonzero(s + J @ x < -1e-10 * (1.0 + np.abs(s).max()))
        if len(viol) == 0:
            return x, steps, int((active < len(work)).sum())
        # add the worst violators (not all: a bad linearisation could violate many at once)
        worst = viol[np.argsort((s + J @ x)[viol])[:256]]
        work = np.union1d(work, worst)
    raise RegistrationError("one-sided QP: constraint generation did not settle")


_solve_onesided_qp = solve_onesided_qp  # the name the fits below and the tests use


# relative Levenberg-Marquardt damping of the one-sided step: without boundary anchoring the slide of a
# nearly spherical plate along itself is almost free, and undamped steps along it overshoot and cycle
DAMPING = 1e-6


def nonpenetrating_fit(
    surface: HeightField,
    measured_points_mm: np.ndarray,
    T_init: np.ndarray,
    *,
    up: np.ndarray = np.array([0.0, 0.0, 1.0]),
    max_iterations: int = 30,
    tolerance_mm: float = 1e-4,
    max_distance_mm: float = 25.0,
    design_corners_mm: np.ndarray | None = None,
    measured_corners_mm: np.ndarray | None = None,
    boundary_weight: float = BOUNDARY_WEIGHT,
    subsample: int = 20_000,
    rel_tolerance: float = 1e-5,
) -> NonPenetratingResult:
    """Rest the design on the measured surface: least squares with no point penetrating.

    surface: design height field (design frame). measured_points_mm: (n, 3) mm, measured frame,
    every surface point (no subsampling). T_init: (4, 4) design -> measured start (after ICP).
    up: (3,) deflection direction in the measured frame.

    Minimises sum_i gap_i^2 subject to gap_i >= 0, gap_i = distance from measured point i up to the
    design surface. Outer loop: correspondences along ``up``, then the gaps are linearised in the
    six motion parameters (rotation vector about the centroid, translation) with the exact
    Jacobian -[(q_i - c) x n_i, n_i] / (n_i . u) of the ray/tangent-plane intersection, and the
    resulting QP (6 unknowns, one linear constraint per point) is solved exactly by an active-set
    method; the rotation is applied through the exponential map. Finally any round-off penetration
    is removed by a pure lift along ``up`` (which raises every gap by exactly the same amount), so
    the result has zero penetrating points. Points off the footprint or more than
    ``max_distance_mm`` from the surface are not constrained (they are not on this plate).
    With matched corners the in-plane corner residuals are added to the objective, weighted as in
    :func:`icp_point_to_plane` by the two terms' information, with the RMS gap as the surface's
    scale (the QP stays exact; ``objective_mm2`` reports the gaps alone). Resting the unformed
    design on a formed plate is one-sided: whatever in-plane motion lowers the gaps pays for
    forming error with it, and on a nearly flat plate the surface hardly sees the yaw; large gaps
    hand the in-plane pose to the corners. (With a constant share of 1e-3 the e2e cell's plate
    turned 1.7 degrees off the true plate, 5-6 mm at its corners.)
    The first iterations run on a seeded ``subsample`` of the points, the last ones on all.
    The outer loop stops when a step moves less than ``tolerance_mm`` or, with every point
    feasible, lowers the objective by less than ``rel_tolerance`` of itself.
    """
    corners = _matched_corners(design_corners_mm, measured_corners_mm)
    P = _check_points("measured_points_mm", measured_points_mm, 6)
    T = _check_transform("T_init", T_init).copy()
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    # one Newton step is within about 1e-6 mm here (the ray is nearly the design's z); the exact
    # two-step gaps decide the lift and the final count below
    s, _, _, valid = deflection_gaps(surface, P, T, up, newton_steps=1, geometry=False)
    use = valid & (np.abs(s) < max_distance_mm)
    if use.sum() < 6:
        raise RegistrationError(f"non-penetrating fit: only {int(use.sum())} points lie over the design")
    Pu, s_all = P[use], s[use]
    penetrating_before = int((s_all < 0).sum())
    # coarse to fine: a seeded subsample walks most of the way cheaply, then every point decides
    # the last steps (the solution and its zero penetration are those of the full problem)
    sub = None
    if len(Pu) > 2 * subsample:
        # a seeded random share carries the objective; the points standing highest above the design
        # now are the ones likely to carry it at the end, so they come along as well
        rand = np.random.default_rng(0).choice(len(Pu), size=subsample, replace=False)
        high = np.argpartition(s_all, subsample // 4)[: subsample // 4]
        sub = np.union1d(rand, high)
    qp_steps, active, it_total, converged = 0, 0, 0, False
    # the subsample walks all the way (cheap), the full set only polishes
    stages = [(Pu[sub], tolerance_mm, rel_tolerance * 1e-3)] if sub is not None else []
    stages.append((Pu, tolerance_mm, rel_tolerance))
    for stage_points, tol, rel_tol in stages:
        T, steps, its, active, converged, kept = _onesided_iterations(
            surface, stage_points, T, up, corners, boundary_weight, max_iterations, tol, rel_tol
        )
        qp_steps += steps
        it_total += its
    Pu = kept
    for refit in range(4):
        # the fit may have moved the design over points that were off its footprint at the start:
        # they are plate points now and must not penetrate either
        s, _, _, valid = deflection_gaps(surface, P, T, up, geometry=False)
        now = valid & (np.abs(s) < max_distance_mm)
        if refit == 3 or len(Pu) == int(now.sum()) or not (s[now] < 0).any():
            break
        Pu = P[now]
        T, steps, its, active, converged, Pu = _onesided_iterations(
            surface, Pu, T, up, corners, boundary_weight, max_iterations, tolerance_mm, rel_tolerance
        )
        qp_steps += steps
        it_total += its
    T, s = _settle(surface, P, np.flatnonzero(now), s[now], T, up)
    objective = float((s**2).sum())
    result = NonPenetratingResult(
        transform=T,
        objective_mm2=objective,
        rms_mm=float(np.sqrt(objective / len(s))),
        min_gap_mm=float(s.min()),
        iterations=it_total,
        qp_iterations=qp_steps,
        points=len(s),
        penetrating_before=penetrating_before,
        penetrating_after=int((s < 0).sum()),
        active_points=active,
        converged=converged,
    )
    log.debug(
        "nonpenetrating_fit",
        points=result.points,
        iterations=it_total,
        penetrating_before=penetrating_before,
        penetrating_after=result.penetrating_after,
        rms_mm=round(result.rms_mm, 5),
    )
    return result


# the lowest gap after the fit: far above the gaps' round-off (1e-13 mm), far below anything that
# costs (the whole cloud's objective rises by 2 * sum(gap) * margin, 1e-9 of itself)
CONTACT_MARGIN_MM = 1e-9
# gaps below this after the final shift are recomputed from scratch rather than shifted
_RECHECK_MM = 1e-3


def _settle(
    surface: HeightField, P: np.ndarray, idx: np.ndarray, s: np.ndarray, T: np.ndarray, up: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Shift the design along ``up`` until its lowest gap over ``P[idx]`` is CONTACT_MARGIN_MM.

    P: (N, 3) mm, measured frame; idx: (n,) the points that count; s: (n,) their exact gaps at ``T``. A shift along ``up`` changes every gap by exactly the
    shift (the ray meets the surface at the same point), so a lift removes the round-off
    penetration the linearised steps leave and a drop removes the float they leave; either way the
    design ends in contact and the objective is the lowest of all poses along ``up`` that penetrate
    nowhere. The shifted gaps are taken as computed, except the few near contact, which decide
    feasibility: those are evaluated afresh (and any shortfall lifted again). Returns ``(T, gaps)``.
    """
    s = s.copy()
    keep = np.ones(len(s), dtype=bool)
    for _ in range(4):
        shift = CONTACT_MARGIN_MM - float(s[keep].min())
        T = make_transform(np.eye(3), shift * up) @ T
        s += shift
        near = np.flatnonzero(keep & (s < _RECHECK_MM))
        g = _ray_gaps(surface, P[idx[near]], T, up, 2, False)
        s[near] = g.gap_mm
        keep[near] = g.valid  # a point exactly on the footprint's edge may round either way
        if s[keep].min() >= 0.0:
            break
    return T, s[keep]


def _onesided_iterations(
    surface: HeightField,
    P: np.ndarray,
    T: np.ndarray,
    up: np.ndarray,
    corners: tuple[np.ndarray, np.ndarray] | None,
    boundary_weight: float,
    max_iterations: int,
    tolerance_mm: float,
    rel_tolerance: float,
    trust_mm: float = 5.0,
) -> tuple[np.ndarray, int, int, int, bool, np.ndarray]:
    """Outer correspondence loop of the one-sided fit on the points ``P`` (measured frame).

    The corners weigh as in :func:`icp_point_to_plane`, with the RMS gap as the surface's scale.

    Each step is confined to a trust region of ``trust_mm`` per parameter (translation in mm,
    rotation in mm at the points' RMS radius): the correspondences are only valid near the current
    pose, and a weakly determined direction (sliding along a nearly spherical plate) would
    otherwise take steps of hundreds of millimetres on a linear model that is long wrong there.
    Returns ``(T, active-set steps, iterations, active constraints, converged, points kept)``.
    """
    qp_steps, active, converged, it = 0, 0, False, 0
    trust, x_prev = float(trust_mm), np.zeros(6)
    for it in range(1, max_iterations + 1):
        # the linearisation only needs one Newton step; the caller checks with two
        g = _ray_gaps(surface, P, T, up, 1, True)
        s, q, m = g.gap_mm, g.q_design_mm, g.tilt
        if not g.valid.all():
            # a point slid off the footprint edge during the fit: keep it out from now on
            P, s, q, m = P[g.valid], s[g.valid], q[:, g.valid], m[:, g.valid]
        T_inv = invert_transform(T)
        u = T_inv[:3, :3] @ up
        c = q.mean(axis=1)
        d = q - c[:, None]
        scale = float(np.sqrt(np.einsum("ij,ij->", d, d) / len(s))) or 1.0
        # J = -[(q - c) x n, n] / (n . u): the normal's length cancels, so the unnormalised tilt
        # (-dz/dx, -dz/dy, 1) serves; rows (6, n) so that J^T J is one BLAS call
        w = m[0] * u[0]
        w += m[1] * u[1]
        w += u[2]
        np.reciprocal(w, out=w)
        np.negative(w, out=w)
        J6 = np.empty((6, len(s)))
        dx, dy, dz = d
        np.multiply(dz, m[1], out=J6[0])
        np.subtract(dy, J6[0], out=J6[0])
        np.multiply(dz, m[0], out=J6[1])
        J6[1] -= dx
        np.multiply(dx, m[1], out=J6[2])
        J6[2] -= dy * m[0]
        J6[:3] *= w * (1.0 / scale)
        np.multiply(m, w, out=J6[3:])
        J = J6.T
        lift = np.concatenate([np.zeros(3), -u])  # moving the points down along u lifts every gap by 1
        damping = DAMPING * float(np.einsum("ij,ij->", J6, J6)) / 6.0
        share = boundary_weight * float(s @ s) / len(s) / CORNER_SIGMA_MM**2
        K, e = _corner_terms(T_inv, corners, c, scale, share * len(s) / 8.0)
        x, steps, active = _solve_onesided_qp(J, s, lift, damping, K, e, box=trust)
        qp_steps += steps
        # a step that turns back on the last one means the linear model is overreaching: shrink
        # (never grow again: after ICP the fit has millimetres to go, not metres)
        if x @ x_prev < 0.0:
            trust *= 0.5
        x_prev = x
        omega, t = x[:3] / scale, x[3:]
        R = rotation_from_vector(omega)
        # the motion acts on the measured points in the design frame; the design moves by its inverse
        T = invert_transform(make_transform(R, c - R @ c + t) @ T_inv)
        step_mm = float(np.linalg.norm(x[:3]) + np.linalg.norm(t))
        obj = float(s @ s) + float(e @ e)
        r = s + J @ x
        gain = (obj - float(r @ r) - float(np.sum((e + K @ x) ** 2))) / max(obj, 1e-300)
        log.debug("onesided_step", it=it, step_mm=step_mm, relative_gain=gain, points=len(s))
        # converged when the step is negligible, or when, already feasible, it no longer lowers the
        # objective measurably: without boundary anchoring a nearly spherical plate can slide along
        # itself for ever at no cost, and such sliding is not worth iterating for
        if step_mm < tolerance_mm or (s.min() >= -10.0 * tolerance_mm and gain < rel_tolerance):
            converged = True
            break
    return T, qp_steps, it, active, converged, P


def grid_average(points_mm: np.ndarray, cell_mm: float = 1.0) -> np.ndarray:
    """Mean point of every occupied ``cell_mm`` square of the XY plane: (m, 3) mm.

    An HD8 scan puts about 20 points in every square millimetre; their cell means keep the shape,
    cut sensor noise by the square root of the count (which a one-sided fit would otherwise turn
    into a lift of the design by the noise's largest excursion) and make the non-penetrating fit
    ten to twenty times cheaper. Vectorised: one sort, one pass of bincounts.
    """
    P = _check_points("points_mm", points_mm)
    if cell_mm <= 0:
        raise RegistrationError(f"cell_mm must be positive, got {cell_mm}")
    ij = np.floor(P[:, :2] / cell_mm).astype(np.int64)
    ij -= ij.min(axis=0)
    key = ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]
    _, inv, count = np.unique(key, return_inverse=True, return_counts=True)
    out = np.empty((len(count), 3))
    for k in range(3):
        out[:, k] = np.bincount(inv, weights=P[:, k]) / count
    return out
