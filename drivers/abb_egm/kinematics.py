"""Kinematics of the ABB IRB 4600-40/2.55: forward kinematics, Jacobian, damped least-squares IK.

The model is built in code with pinocchio from the joint origins and axes of the public
ros-industrial description (docs/reference/abb-egm-rws.md section 4), no URDF file, and the joint
ranges and rated speeds of :mod:`drivers.abb_egm.limits` (which also holds :class:`LinearTrack`).

Units: the public API speaks the controller's units, degrees and millimetres; pinocchio speaks
radians and metres. The conversion happens only in :func:`_q_rad`, :func:`_T_mm` and :func:`_T_m`.
Frames: ``base`` (robot base), ``flange`` (ABB tool0), and named tool frames given as
``T_flange_tool`` (4, 4) homogeneous transforms in mm.

The track: a robot on a linear track (:class:`LinearTrack`) is a seven-axis machine whose first
joint is prismatic. Its configuration is one vector, ``axes_mm_deg`` (7,): the track position in mm
first, then the six arm joints in degrees (the order of the kinematic chain and of EGM's feedback:
``externalJoints`` then ``joints``). With a track, every pose is in the cell's world frame; the
robot base keeps the world's orientation and moves along the track's direction. Without one, the
world frame is the base frame and a configuration is the six-vector ``q_deg``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from drivers.abb_egm.limits import (
    JOINT_NAMES,
    N_ARM_JOINTS,
    Q_MAX_DEG,
    Q_MIN_DEG,
    QD_MAX_DEG_S,
    KinematicsError,
    LinearTrack,
)

__all__ = [
    "IkResult",
    "KinematicsError",
    "Pose",
    "RobotKinematics",
    "fk_batch",
    "ik_branches",
    "matrix_from_quat_wxyz",
    "nearest_branch",
    "quat_wxyz_from_matrix",
]

#: joint origin in the parent link frame (m); all origin rotations are identity
_JOINT_XYZ_M = np.array(
    [
        [0.0, 0.0, 0.495],
        [0.175, 0.0, 0.0],
        [0.0, 0.0, 1.095],
        [0.0, 0.0, 0.175],
        [1.270, 0.0, 0.0],
        [0.135, 0.0, 0.0],
    ]
)
_JOINT_AXES = "zyyxyx"
#: link_6 -> tool0 (the ABB flange): rpy (0, pi/2, 0), no offset
_R_LINK6_FLANGE = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])


@dataclass(frozen=True, slots=True)
class Pose:
    """A frame pose in the robot base frame: ``pos_mm`` (3,) mm, ``quat_wxyz`` (4,) scalar first,
    ``T_base_frame`` (4, 4) homogeneous transform with translation in mm."""

    pos_mm: np.ndarray
    quat_wxyz: np.ndarray
    T_base_frame: np.ndarray


@dataclass(frozen=True, slots=True)
class IkResult:
    """Outcome of :meth:`RobotKinematics.ik`.

    ``q_deg`` (6,) is the best configuration found (always within the joint limits), ``converged``
    tells whether both tolerances were met, ``pos_err_mm`` / ``rot_err_deg`` are the remaining
    errors, ``iterations`` the iterations used.
    """

    q_deg: np.ndarray
    converged: bool
    iterations: int
    pos_err_mm: float
    rot_err_deg: float


# ---------------------------------------------------------------------------------------------
# unit boundary


def _q_rad(q_deg: np.ndarray) -> np.ndarray:
    """Controller units -> pinocchio units: (6,) deg -> rad, or (7,) [mm, deg...] -> [m, rad...]."""
    if q_deg.shape[-1] == N_ARM_JOINTS + 1:
        out = np.deg2rad(q_deg)
        out[..., 0] = q_deg[..., 0] / 1000.0
        return out
    return np.deg2rad(q_deg)


def _q_ctrl(q_pin: np.ndarray) -> np.ndarray:
    """Pinocchio units -> controller units (inverse of :func:`_q_rad`)."""
    if q_pin.shape[-1] == N_ARM_JOINTS + 1:
        out = np.rad2deg(q_pin)
        out[..., 0] = q_pin[..., 0] * 1000.0
        return out
    return np.rad2deg(q_pin)


def _T_mm(M: pin.SE3) -> np.ndarray:
    T = np.array(M.homogeneous)
    T[:3, 3] *= 1000.0
    return T


def _T_m(T_mm: np.ndarray) -> pin.SE3:
    return pin.SE3(np.array(T_mm[:3, :3]), np.array(T_mm[:3, 3]) / 1000.0)


def _as_q(q_deg, n_joints: int = 6) -> np.ndarray:
    q = np.asarray(q_deg, dtype=np.float64)
    name = "axes_mm_deg" if n_joints == N_ARM_JOINTS + 1 else "q_deg"
    if q.shape != (n_joints,):
        raise KinematicsError(f"{name} must have shape ({n_joints},), got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise KinematicsError(f"{name} has non-finite values: {q}")
    return q


def _as_T(T, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise KinematicsError(f"{name} must be a finite (4, 4) transform, got shape {T.shape}")
    R = T[:3, :3]
    # np.allclose(R @ R.T, I, atol=1e-6) (rtol 1e-5) and det(R) >= 0, without their per-call
    # overhead: the planner's inverse kinematics checks every one of its tens of thousands of targets
    if not np.all(np.abs(R @ R.T - _EYE3) <= _ORTHONORMAL_TOL):
        raise KinematicsError(f"{name} rotation part is not a rotation matrix")
    (a, b, c), (d, e, f), (g, h, i) = R.tolist()
    if a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) < 0:
        raise KinematicsError(f"{name} rotation part is not a rotation matrix")
    return T


_EYE3 = np.eye(3)
_ORTHONORMAL_TOL = 1e-6 + 1e-5 * _EYE3


# ---------------------------------------------------------------------------------------------
# rotations


def quat_wxyz_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (4,) scalar first, with w >= 0, of a rotation matrix (3, 3)."""
    q = pin.Quaternion(np.asarray(R, dtype=np.float64))
    out = np.array([q.w, q.x, q.y, q.z])
    out /= np.linalg.norm(out)
    return -out if out[0] < 0 else out


def matrix_from_quat_wxyz(quat_wxyz: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of a quaternion (4,) scalar first (normalised here)."""
    w, x, y, z = np.asarray(quat_wxyz, dtype=np.float64) / np.linalg.norm(quat_wxyz)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


# ---------------------------------------------------------------------------------------------
# model


def _build_model(track: LinearTrack | None = None) -> tuple[pin.Model, int]:
    model = pin.Model()
    model.name = "irb4600_40_255" if track is None else "irb4600_40_255_on_track"
    joint_models = {"x": pin.JointModelRX, "y": pin.JointModelRY, "z": pin.JointModelRZ}
    parent = 0
    prev_frame = model.getFrameId("universe")
    vmax_rad_s = np.deg2rad(QD_MAX_DEG_S)
    lower, upper = np.deg2rad(Q_MIN_DEG), np.deg2rad(Q_MAX_DEG)
    # The description has no inertias; a small nominal body keeps pinocchio's algorithms well defined.
    inertia = pin.Inertia.FromSphere(1.0, 0.05)
    if track is not None:
        # the carriage: a prismatic joint along the track's direction at the base's position at 0,
        # in metres (the unit boundary converts); the arm's chain hangs from it
        jid = model.addJoint(
            0,
            pin.JointModelPrismaticUnaligned(np.array(track.direction)),
            pin.SE3(np.eye(3), np.array(track.origin_mm) / 1000.0),
            "track",
            np.zeros(1),
            np.array([track.speed_max_mm_s / 1000.0]),
            np.array([track.travel_min_mm / 1000.0]),
            np.array([track.travel_max_mm / 1000.0]),
        )
        model.appendBodyToJoint(jid, inertia, pin.SE3.Identity())
        jf = model.addJointFrame(jid, prev_frame)
        prev_frame = model.addBodyFrame("carriage", jid, pin.SE3.Identity(), jf)
        parent = jid
    for i, name in enumerate(JOINT_NAMES):
        placement = pin.SE3(np.eye(3), _JOINT_XYZ_M[i])
        jid = model.addJoint(
            parent,
            joint_models[_JOINT_AXES[i]](),
            placement,
            name,
            np.zeros(1),
            np.array([vmax_rad_s[i]]),
            np.array([lower[i]]),
            np.array([upper[i]]),
        )
        model.appendBodyToJoint(jid, inertia, pin.SE3.Identity())
        jf = model.addJointFrame(jid, prev_frame)
        prev_frame = model.addBodyFrame(f"link_{i + 1}", jid, pin.SE3.Identity(), jf)
        parent = jid
    flange = model.addFrame(
        pin.Frame("flange", parent, prev_frame, pin.SE3(_R_LINK6_FLANGE, np.zeros(3)), pin.FrameType.OP_FRAME)
    )
    return model, flange


class RobotKinematics:
    """IRB 4600-40/2.55 kinematics with the flange and optional named tool frames, on an optional track.

    Args:
        tools: name -> ``T_flange_tool`` (4, 4), translation in mm (e.g. the laser sensor frame).
        track: the linear track the base rides on, or None. With a track every configuration is
            ``axes_mm_deg`` (7,) (track mm, then the six joints in deg) and poses are in the world
            frame; without one a configuration is ``q_deg`` (6,) and poses are in the base frame.

    Not thread-safe: one pinocchio ``Data`` is reused by every call (create one instance per thread).
    """

    def __init__(
        self, tools: Mapping[str, np.ndarray] | None = None, track: LinearTrack | None = None
    ) -> None:
        self.track = track
        #: axes in a configuration: 6 (arm) or 7 (track, then arm)
        self.n_axes = N_ARM_JOINTS + (track is not None)
        self.model, self._flange_id = _build_model(track)
        self._frames: dict[str, int] = {"flange": self._flange_id}
        self._T_flange_tool_mm: dict[str, np.ndarray] = {"flange": np.eye(4)}
        for name, T in (tools or {}).items():
            self.add_tool(name, T)
        self.data = self.model.createData()
        # limits per axis in controller units (with a track: mm and mm/s first, then deg and deg/s)
        if track is None:
            self.q_min_deg = Q_MIN_DEG.copy()
            self.q_max_deg = Q_MAX_DEG.copy()
            self.qd_max_deg_s = QD_MAX_DEG_S.copy()
        else:
            self.q_min_deg = np.concatenate([[track.travel_min_mm], Q_MIN_DEG])
            self.q_max_deg = np.concatenate([[track.travel_max_mm], Q_MAX_DEG])
            self.qd_max_deg_s = np.concatenate([[track.speed_max_mm_s], QD_MAX_DEG_S])

    def add_tool(self, name: str, T_flange_tool: np.ndarray) -> None:
        """Add (or replace) a tool frame ``name`` fixed to the flange; ``T_flange_tool`` in mm."""
        T = _as_T(T_flange_tool, "T_flange_tool")
        placement = pin.SE3(_R_LINK6_FLANGE, np.zeros(3)) * _T_m(T)
        flange = self.model.frames[self._flange_id]
        if name in self._frames:
            if name == "flange":
                raise KinematicsError("the flange frame cannot be replaced")
            self.model.frames[self._frames[name]].placement = placement
        else:
            self._frames[name] = self.model.addFrame(
                pin.Frame(name, flange.parentJoint, self._flange_id, placement, pin.FrameType.OP_FRAME)
            )
        self._T_flange_tool_mm[name] = T.copy()
        self.data = self.model.createData()

    @property
    def frames(self) -> tuple[str, ...]:
        """Names of the frames FK can report (``flange`` and the tools)."""
        return tuple(self._frames)

    def _fid(self, frame: str) -> int:
        try:
            return self._frames[frame]
        except KeyError:
            raise KinematicsError(f"unknown frame {frame!r}; known: {sorted(self._frames)}") from None

    def fk(self, q_deg: np.ndarray, frame: str = "flange") -> Pose:
        """Pose of ``frame`` at ``q_deg`` (6,) deg, in the base frame; with a track at ``axes_mm_deg``
        (7,), in the world frame (the returned ``T_base_frame`` is then ``T_world_frame``)."""
        fid = self._fid(frame)
        q = _as_q(q_deg, self.n_axes)
        pin.framesForwardKinematics(self.model, self.data, _q_rad(q))
        T = _T_mm(self.data.oMf[fid])
        return Pose(pos_mm=T[:3, 3].copy(), quat_wxyz=quat_wxyz_from_matrix(T[:3, :3]), T_base_frame=T)

    def jacobian(self, q_deg: np.ndarray, frame: str = "flange") -> np.ndarray:
        """Geometric Jacobian (6, n_axes) of ``frame`` at ``q_deg`` (6,) or ``axes_mm_deg`` (7,),
        base- (world-) aligned axes at the frame origin.

        Rows 0..2 map joint rates in deg/s to linear velocity in mm/s (mm/deg); rows 3..5 map them
        to angular velocity in deg/s (deg/deg). A track's column maps mm/s to mm/s (and no rotation).
        """
        fid = self._fid(frame)
        q = _q_rad(_as_q(q_deg, self.n_axes))
        pin.computeJointJacobians(self.model, self.data, q)
        pin.updateFramePlacements(self.model, self.data)
        J = pin.getFrameJacobian(self.model, self.data, fid, pin.LOCAL_WORLD_ALIGNED).copy()
        arm = slice(self.n_axes - N_ARM_JOINTS, None)
        J[:3, arm] *= 1000.0 * np.pi / 180.0  # m/rad -> mm/deg (a track's m/m column is already mm/mm)
        return J

    def within_limits(self, q_deg: np.ndarray, margin_deg: float = 0.0) -> bool:
        """True if every axis is inside its limits shrunk by ``margin_deg`` (a track: by that many mm)."""
        q = _as_q(q_deg, self.n_axes)
        return bool(np.all(q >= self.q_min_deg + margin_deg) and np.all(q <= self.q_max_deg - margin_deg))

    def ik(
        self,
        T_base_target: np.ndarray,
        q_seed_deg: np.ndarray,
        frame: str = "flange",
        *,
        tol_mm: float = 1e-3,
        tol_deg: float = 1e-4,
        max_iterations: int = 200,
        damping: float = 1e-6,
        max_step_deg: float = 5.0,
        move_track: bool = False,
    ) -> IkResult:
        """Damped least-squares inverse kinematics near a seed, within the joint limits.

        Args:
            T_base_target: target pose of ``frame`` (4, 4), translation in mm (world frame with a track).
            q_seed_deg: (6,) deg, or ``axes_mm_deg`` (7,) with a track: the start; the solution is the
                branch nearest to it.
            move_track: with a track, let the solver move it too; by default the track stays at the
                seed's position (the planner chooses track positions, the arm reaches from there).
            tol_mm, tol_deg: convergence tolerances on position and rotation error.
            damping: lambda of the damped pseudo-inverse; keeps steps bounded near singularities.
            max_step_deg: largest joint change per iteration, so the solver does not jump branches.
        """
        fid = self._fid(frame)
        target = _T_m(_as_T(T_base_target, "T_base_target"))
        q = _q_rad(np.clip(_as_q(q_seed_deg, self.n_axes), self.q_min_deg, self.q_max_deg))
        lo, hi = _q_rad(self.q_min_deg), _q_rad(self.q_max_deg)
        max_step = np.deg2rad(max_step_deg)
        tol_m, tol_rad = tol_mm / 1000.0, np.deg2rad(tol_deg)
        best = (np.inf, q.copy(), np.inf, np.inf)
        iterations = 0
        for iterations in range(1, max_iterations + 1):  # noqa: B007 - used after the loop
            pin.framesForwardKinematics(self.model, self.data, q)
            current_to_target = self.data.oMf[fid].actInv(target)
            err = pin.log6(current_to_target).vector  # (v, w) in the frame: m, rad
            pos_err, rot_err = float(np.linalg.norm(err[:3])), float(np.linalg.norm(err[3:]))
            # Rank by a scale-free error (1 mm ~ 1 mrad) so the best-so-far is meaningful.
            score = pos_err + rot_err
            if score < best[0]:
                best = (score, q.copy(), pos_err, rot_err)
            if pos_err < tol_m and rot_err < tol_rad:
                break
            J = pin.computeFrameJacobian(self.model, self.data, q, fid, pin.LOCAL)
            J = pin.Jlog6(current_to_target.inverse()) @ J
            if self.track is not None and not move_track:
                J[:, 0] = 0.0  # a zero column: the damped step leaves the track where it is
            dq = J.T @ np.linalg.solve(J @ J.T + damping * np.eye(6), err)
            step = np.max(np.abs(dq))
            if step > max_step:
                dq *= max_step / step
            q = np.clip(q + dq, lo, hi)
        _, q_best, pos_err, rot_err = best
        return IkResult(
            q_deg=_q_ctrl(q_best),
            converged=bool(pos_err < tol_m and rot_err < tol_rad),
            iterations=iterations,
            pos_err_mm=pos_err * 1000.0,
            rot_err_deg=float(np.rad2deg(rot_err)),
        )

    def ik_branches(self, T_base_target: np.ndarray, frame: str = "flange") -> np.ndarray:
        """Every closed-form IK solution of ``frame`` at many poses: ``T_base_target`` (n, 4, 4), mm
        -> (n, 8, 6) deg, NaN where a branch has none (:func:`ik_branches`). The arm alone: with a
        track, solve in the base frame at the carriage's position (the planner does)."""
        if self.track is not None:
            raise KinematicsError(
                "ik_branches solves the arm alone: give base-frame poses to a model without a track"
            )
        T = np.asarray(T_base_target, dtype=np.float64)
        if T.ndim != 3 or T.shape[1:] != (4, 4):
            raise KinematicsError(f"T_base_target must have shape (n, 4, 4), got {T.shape}")
        T_tool_flange = _inverse_rigid(self._T_flange_tool_mm[self._fid_name(frame)])
        return ik_branches(T @ T_tool_flange)

    def fk_batch(self, q_deg: np.ndarray, frame: str = "flange") -> np.ndarray:
        """Poses of ``frame`` for many configurations: ``q_deg`` (n, 6) deg (or ``axes_mm_deg``
        (n, 7) with a track) -> (n, 4, 4), mm."""
        return fk_batch(q_deg, self._T_flange_tool_mm[self._fid_name(frame)], track=self.track)

    def _fid_name(self, frame: str) -> str:
        self._fid(frame)
        return frame


#: for a rotation about axis a, the two columns of R it mixes: R @ Rot(a, q) changes only these
#: (x: columns 1, 2; y: columns 2, 0; z: columns 0, 1), as ``(u, v) -> (c u + s v, c v - s u)``
_MIXED_COLUMNS = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}
#: per joint, the (column, length in mm) of its origin offset: the chain's offsets lie on one axis each
_JOINT_OFFSETS_MM = tuple(
    tuple((int(j), float(v) * 1000.0) for j, v in enumerate(row) if v != 0.0) for row in _JOINT_XYZ_M
)


_G_CACHE: dict[bytes, np.ndarray] = {}


def _link6_to_tool(T_flange_tool: np.ndarray | None) -> np.ndarray:
    """(3, 4) ``[R | p]`` of link_6 -> tool. Cached per tool: the rotation check runs once per tool,
    not once per batch of feedback samples."""
    key = b"" if T_flange_tool is None else T_flange_tool.tobytes() + str(T_flange_tool.shape).encode()
    G = _G_CACHE.get(key)
    if G is None:
        G = np.zeros((3, 4))
        G[:, :3] = _R_LINK6_FLANGE
        if T_flange_tool is not None:
            T_ft = _as_T(T_flange_tool, "T_flange_tool")
            G[:, :3] = _R_LINK6_FLANGE @ T_ft[:3, :3]
            G[:, 3] = _R_LINK6_FLANGE @ T_ft[:3, 3]
        G.flags.writeable = False
        if len(_G_CACHE) >= 64:  # a handful of tools in practice; never grow without bound
            _G_CACHE.clear()
        _G_CACHE[key] = G
    return G


def fk_batch(
    q_deg: np.ndarray, T_flange_tool: np.ndarray | None = None, track: LinearTrack | None = None
) -> np.ndarray:
    """Vectorised forward kinematics for many configurations (numpy only, no per-sample loop).

    Args:
        q_deg: (n, 6) joint angles, deg; with ``track``, ``axes_mm_deg`` (n, 7): track mm, then joints.
        T_flange_tool: optional (4, 4) tool transform, mm; identity gives the flange.
        track: the linear track the base rides on; the poses are then in the world frame.

    Returns:
        (n, 4, 4) ``T_base_tool`` (``T_world_tool`` with a track), translations in mm. Agrees with
        :meth:`RobotKinematics.fk`.
    """
    q = np.asarray(q_deg, dtype=np.float64)
    if track is not None:
        if q.ndim != 2 or q.shape[1] != N_ARM_JOINTS + 1:
            raise KinematicsError(f"axes_mm_deg must have shape (n, 7), got {q.shape}")
        T = fk_batch(q[:, 1:], T_flange_tool)
        # the base keeps the world's orientation: the carriage only adds its translation
        T[:, :3, 3] += track.base_pos_mm(q[:, 0])
        return T
    if q.ndim != 2 or q.shape[1] != 6:
        raise KinematicsError(f"q_deg must have shape (n, 6), got {q.shape}")
    q_rad = _q_rad(q)
    n = q.shape[0]
    cos, sin = np.cos(q_rad.T), np.sin(q_rad.T)  # (6, n): one contiguous row per joint
    # R kept as its three columns, each (3, n) with the samples contiguous: an elementary rotation
    # mixes two columns, so a joint costs a few element-wise operations instead of a stacked 3x3
    # matrix product (ingestion runs this for every 250 Hz feedback sample)
    cols = [np.zeros((3, n)) for _ in range(3)]
    for j in range(3):
        cols[j][j] = 1.0
    p = np.zeros((3, n))
    for i in range(6):  # six joints: a loop over the chain, vectorised over the samples
        for j, length_mm in _JOINT_OFFSETS_MM[i]:
            p += cols[j] * length_mm
        a, b = _MIXED_COLUMNS[_JOINT_AXES[i]]
        c, s = cos[i], sin[i]
        u, v = cols[a], cols[b]
        cols[a] = u * c + v * s
        cols[b] = v * c - u * s
    # flange (R @ _R_LINK6_FLANGE) and tool in one small product: [R p] @ G with G (3, 4) constant
    G = _link6_to_tool(None if T_flange_tool is None else np.asarray(T_flange_tool, dtype=np.float64))
    rows = np.stack(cols, axis=-1)  # (3, n, 3): R[row, sample, column]
    top = (rows.reshape(3 * n, 3) @ G).reshape(3, n, 4)
    top[:, :, 3] += p
    T = np.empty((n, 4, 4))
    T[:, :3, :] = top.transpose(1, 0, 2)
    T[:, 3, :3] = 0.0
    T[:, 3, 3] = 1.0
    return T


# ---------------------------------------------------------------------------------------------
# closed-form inverse kinematics
#
# The IRB 4600 has an ortho-parallel base (joint 1 vertical, joints 2 and 3 parallel to each other
# and perpendicular to it) and a spherical wrist (joints 4, 5 and 6 meet in one point, the wrist
# centre, 135 mm behind the flange). The wrist centre fixes joints 1-3 (a shoulder turned toward or
# away from it, an elbow up or down); the orientation left over fixes joints 4-6 as x-y-x Euler
# angles (two wrists, joint 5 positive or negative): eight branches. The lengths are the model's
# (``_JOINT_XYZ_M``).

_SHOULDER_R_MM = 1000.0 * _JOINT_XYZ_M[1, 0]  # joint 2 ahead of joint 1's axis
_SHOULDER_Z_MM = 1000.0 * _JOINT_XYZ_M[0, 2]  # joint 2 above the base
_UPPER_ARM_MM = 1000.0 * _JOINT_XYZ_M[2, 2]  # joint 2 -> joint 3
#: joint 3 -> wrist centre: along the forearm (joint 4's axis) and across it
_FOREARM_ALONG_MM = 1000.0 * _JOINT_XYZ_M[4, 0]
_FOREARM_ACROSS_MM = 1000.0 * _JOINT_XYZ_M[3, 2]
_FOREARM_MM = float(np.hypot(_FOREARM_ALONG_MM, _FOREARM_ACROSS_MM))
_FOREARM_TILT_RAD = float(np.arctan2(_FOREARM_ACROSS_MM, _FOREARM_ALONG_MM))
_WRIST_FLANGE_MM = 1000.0 * _JOINT_XYZ_M[5, 0]  # wrist centre -> flange along link 6's x axis


def _inverse_rigid(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def _wrap_pi(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def ik_branches(T_base_flange: np.ndarray) -> np.ndarray:
    """The eight closed-form IK solutions of the flange at many poses, vectorised.

    Args:
        T_base_flange: (n, 4, 4) flange poses in the base frame, mm (rotation parts must be rotations).

    Returns:
        (n, 8, 6) joint angles in deg, each in (-180, 180]; branch ``4 s + 2 e + w``: shoulder ``s``
        (0: facing the wrist centre, 1: turned away), elbow ``e`` (0 and 1: the two solutions of the
        planar arm), wrist ``w`` (0: joint 5 positive, 1: negative). NaN where a branch has no
        solution (the wrist centre out of the arm's reach). Joint limits are not applied (nor the
        other turns of joints 4 and 6 up to +-400 deg: :func:`nearest_branch` chooses among them).
        At a wrist singularity (joint 5 at 0) joints 4 and 6 are one rotation: it goes to joint 6.
    """
    T = np.asarray(T_base_flange, dtype=np.float64)
    n = T.shape[0]
    R = T[:, :3, :3] @ _R_LINK6_FLANGE.T  # link_6 in the base frame
    c = T[:, :3, 3] - _WRIST_FLANGE_MM * R[:, :, 0]  # the wrist centre
    out = np.full((n, 8, 6), np.nan)
    a, b = _UPPER_ARM_MM, _FOREARM_MM
    for s in (0, 1):
        q1 = np.arctan2(c[:, 1], c[:, 0]) + s * np.pi
        r = np.hypot(c[:, 0], c[:, 1]) * (1.0 - 2.0 * s)
        dx, dz = r - _SHOULDER_R_MM, c[:, 2] - _SHOULDER_Z_MM
        # in the arm's plane (along r, down z), the upper arm points along q2 - pi/2 and the
        # forearm's wrist offset along q2 + q3 - tilt; their difference is q3 + pi/2 - tilt
        cos_d = (dx * dx + dz * dz - a * a - b * b) / (2.0 * a * b)
        reach = np.abs(cos_d) <= 1.0 + 1e-12
        d0 = np.arccos(np.clip(cos_d, -1.0, 1.0))
        for e in (0, 1):
            d = d0 if e == 0 else -d0
            q2 = np.arctan2(-dz, dx) - np.arctan2(b * np.sin(d), a + b * np.cos(d)) + 0.5 * np.pi
            q3 = d - 0.5 * np.pi + _FOREARM_TILT_RAD
            phi = q2 + q3
            c1, s1, c23, s23 = np.cos(q1), np.sin(q1), np.cos(phi), np.sin(phi)
            # R_3 = Rz(q1) Ry(q2 + q3); M = R_3^T R = Rx(q4) Ry(q5) Rx(q6)
            R3 = np.empty((n, 3, 3))
            R3[:, 0, 0], R3[:, 0, 1], R3[:, 0, 2] = c1 * c23, -s1, c1 * s23
            R3[:, 1, 0], R3[:, 1, 1], R3[:, 1, 2] = s1 * c23, c1, s1 * s23
            R3[:, 2, 0], R3[:, 2, 1], R3[:, 2, 2] = -s23, 0.0, c23
            M = np.einsum("nji,njk->nik", R3, R)
            sin5 = np.hypot(M[:, 1, 0], M[:, 2, 0])
            for w in (0, 1):
                sign = 1.0 - 2.0 * w
                q5 = np.arctan2(sign * sin5, M[:, 0, 0])
                q4 = np.arctan2(sign * M[:, 1, 0], -sign * M[:, 2, 0])
                q6 = np.arctan2(sign * M[:, 0, 1], sign * M[:, 0, 2])
                singular = sin5 < 1e-9
                if singular.any():  # Rx(q4 + q6): all of it on joint 6
                    q4 = np.where(singular, 0.0, q4)
                    q6 = np.where(singular, np.arctan2(M[:, 2, 1], M[:, 1, 1]) * np.sign(M[:, 0, 0]), q6)
                q = np.stack([q1, q2, q3, q4, q5, q6], axis=-1)
                q = np.rad2deg(_wrap_pi(q))
                q[~reach] = np.nan
                out[:, 4 * s + 2 * e + w] = q
    return out


def nearest_branch(
    candidates_deg: np.ndarray, seed_deg: np.ndarray, q_min_deg: np.ndarray, q_max_deg: np.ndarray
) -> np.ndarray | None:
    """The solution nearest ``seed_deg`` (6,) (Euclidean, deg) among ``candidates_deg`` (m, 6) of
    :func:`ik_branches`, each joint first turned by whole turns to lie nearest the seed's, and inside
    ``[q_min_deg, q_max_deg]``; None when no candidate lies inside."""
    q = candidates_deg + 360.0 * np.round((seed_deg - candidates_deg) / 360.0)
    # a configuration exactly at a limit comes back a rounding error beyond it: inside, clipped
    ok = np.all((q >= q_min_deg - _LIMIT_ROUNDING_DEG) & (q <= q_max_deg + _LIMIT_ROUNDING_DEG), axis=1)
    if not ok.any():  # NaN rows fail the test above
        return None
    d = np.where(ok, np.sum((q - seed_deg) ** 2, axis=1), np.inf)
    return np.clip(q[int(np.argmin(d))], q_min_deg, q_max_deg)


_LIMIT_ROUNDING_DEG = 1e-9
