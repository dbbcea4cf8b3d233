"""Rotations: Hamilton quaternions (scalar first), rotation matrices, the SO(3) exponential map.

One convention everywhere (docs/configuration.md, "Frames and conventions"): a unit quaternion ``q = [w, x, y, z]``
rotates body vectors into the world, ``v_W = R(q) v_B``; composition is Hamilton's product,
so ``q_WC = q_WB ⊗ q_BC``. Every function accepts a single quaternion/vector or a stack of
them along the leading axes (``[..., 4]`` / ``[..., 3]``), which keeps evaluation code free of
Python loops.

The scalar primitives (:func:`quat_product`, :func:`rotvec_quat`, :func:`quat_exp_of`, :func:`rot_of`,
:func:`rotate`, :func:`right_jacobian_of`) are written once here and serve three callers: Python on plain
floats (the per-sample paths), numpy on whole arrays (the same expressions, element-wise), and the compiled
kernels, which call their numba forms ``compiled_<name>`` (made on first use, so that importing the
rotations, as the mapper's client does, loads no numba). Each is the same operations in the same order
in all three, so the results agree to the last bit. numba's cache of a kernel does not notice a change
made here: after editing a primitive, delete the ``*.nbi``/``*.nbc`` files under ``estimator/``.
"""

from __future__ import annotations

import math

import numpy as np

_SMALL_ANGLE = 1e-8


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix: ``skew(a) @ b == np.cross(a, b)``; a stack ``(..., 3)`` gives ``(..., 3, 3)``."""
    v = np.asarray(v, dtype=float)
    if v.ndim == 1:
        x, y, z = v
        return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def is_proper_rotation(r: np.ndarray, atol: float = 1e-6) -> bool:
    """Orthonormal with determinant +1 (not a reflection)."""
    r = np.asarray(r, dtype=float)
    return r.shape == (3, 3) and bool(np.allclose(r @ r.T, np.eye(3), atol=atol)) and np.linalg.det(r) > 0.0


def rotvec_quat(x: float, y: float, z: float) -> tuple[float, float, float, float]:
    """Unit quaternion of the rotation vector (x, y, z), on plain floats: the per-sample fast path
    (:func:`quat_exp` is the array version)."""
    angle = math.sqrt(x * x + y * y + z * z)
    s = math.sin(0.5 * angle) / angle if angle > 1e-9 else 0.5 - angle * angle / 48.0
    return math.cos(0.5 * angle), s * x, s * y, s * z


def quat_exp_of(x: float, y: float, z: float) -> tuple[float, float, float, float]:
    """:func:`quat_exp` of one rotation vector on plain floats, with its threshold and series (the smoother
    applies its corrections with this one, :func:`rotvec_quat` is the filter's)."""
    angle = math.sqrt(x * x + y * y + z * z)
    half = 0.5 * angle
    k = math.sin(half) / max(angle, _SMALL_ANGLE) if angle > _SMALL_ANGLE else 0.5 - angle**2 / 48.0
    return math.cos(half), k * x, k * y, k * z


def quat_product(aw: float, ax: float, ay: float, az: float,
                 bw: float, bx: float, by: float, bz: float) -> tuple[float, float, float, float]:
    """Hamilton product ``a ⊗ b`` of two quaternions given by their components (floats, or arrays
    element-wise): the one place the product is written out."""
    return (aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw)


def rotate(w: float, x: float, y: float, z: float, vx: float, vy: float, vz: float) -> tuple[float, float, float]:
    """``R(q) v`` for a unit quaternion without forming R: v + 2w (r × v) + 2 r × (r × v), r = (x, y, z)."""
    cx, cy, cz = y * vz - z * vy, z * vx - x * vz, x * vy - y * vx
    return (vx + 2.0 * (w * cx + y * cz - z * cy),
            vy + 2.0 * (w * cy + z * cx - x * cz),
            vz + 2.0 * (w * cz + x * cy - y * cx))


def right_jacobian_of(x: float, y: float, z: float) -> tuple[tuple[float, float, float], ...]:
    """Right Jacobian of SO(3) at φ = (x, y, z), as row tuples: ``Exp(φ + δ) ≈ Exp(φ) Exp(Jr(φ) δ)``.

    Jr = I − a [φ]× + b [φ]×², a = (1 − cos θ)/θ², b = (θ − sin θ)/θ³, with [φ]×² = φ φᵀ − θ² I; the
    series' first terms below θ² = 1e-10, where the closed forms lose their digits."""
    t2 = x * x + y * y + z * z
    if t2 < 1e-10:
        a, b = 0.5, 1.0 / 6.0
    else:
        t = math.sqrt(t2)
        a, b = (1.0 - math.cos(t)) / t2, (t - math.sin(t)) / (t2 * t)
    return (
        (1.0 + b * (x * x - t2), a * z + b * x * y, -a * y + b * x * z),
        (-a * z + b * x * y, 1.0 + b * (y * y - t2), a * x + b * y * z),
        (a * y + b * x * z, -a * x + b * y * z, 1.0 + b * (z * z - t2)),
    )


def right_jacobian(phi: np.ndarray) -> np.ndarray:
    """:func:`right_jacobian_of` of one rotation vector, as a 3 × 3 array."""
    return np.array(right_jacobian_of(*np.asarray(phi, dtype=float).tolist()))


def quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product ``p ⊗ q`` (scalar first), of single quaternions or stacks."""
    p = np.asarray(p, dtype=float)
    q = np.asarray(q, dtype=float)
    return np.stack(quat_product(p[..., 0], p[..., 1], p[..., 2], p[..., 3], q[..., 0], q[..., 1], q[..., 2], q[..., 3]),
                    axis=-1)


def quat_conj(q: np.ndarray) -> np.ndarray:
    """Conjugate, the inverse of a unit quaternion."""
    q = np.asarray(q, dtype=float)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_normalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternion with a non-negative scalar part (one representative of ±q)."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    sign = np.where(q[..., :1] < 0.0, -1.0, 1.0)
    return q * sign


def rot_of(w: float, x: float, y: float, z: float) -> tuple[tuple[float, float, float], ...]:
    """:func:`quat_to_rot` of one quaternion on plain floats, as row tuples: the per-sample fast path."""
    return (
        (1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)),
        (2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)),
        (2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)),
    )


def quat_to_rot(q: np.ndarray) -> np.ndarray:
    """Rotation matrix ``R(q)`` with ``v_W = R v_B`` (the transpose of thesis eq. 3.31)."""
    q = np.asarray(q, dtype=float)
    if q.shape == (4,):  # one quaternion: the same arithmetic on floats, a fraction of the numpy calls
        return np.array(rot_of(*q.tolist()))
    rows = rot_of(q[..., 0], q[..., 1], q[..., 2], q[..., 3])  # element-wise over the stack
    r = np.empty(q.shape[:-1] + (3, 3))
    for i in range(3):
        for j in range(3):
            r[..., i, j] = rows[i][j]
    return r


def rot_to_quat(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (w ≥ 0) of a rotation matrix; numerically safe for every angle."""
    r = np.asarray(r, dtype=float)
    flat = r.reshape(-1, 3, 3)
    out = np.empty((flat.shape[0], 4))
    for i, m in enumerate(flat):
        tr = m[0, 0] + m[1, 1] + m[2, 2]
        if tr > 0.0:
            s = 2.0 * np.sqrt(tr + 1.0)
            out[i] = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
        elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
            s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
            out[i] = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
        elif m[1, 1] > m[2, 2]:
            s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
            out[i] = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
        else:
            s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
            out[i] = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    return quat_normalize(out).reshape(r.shape[:-2] + (4,))


def quat_exp(rotvec: np.ndarray) -> np.ndarray:
    """Quaternion of a rotation vector (axis × angle): ``[cos(θ/2), sin(θ/2) axis]``."""
    rv = np.asarray(rotvec, dtype=float)
    angle = np.linalg.norm(rv, axis=-1, keepdims=True)
    half = 0.5 * angle
    # sin(θ/2)/θ, with its series near zero so tiny rotations keep full precision.
    k = np.where(angle > _SMALL_ANGLE, np.sin(half) / np.maximum(angle, _SMALL_ANGLE), 0.5 - angle**2 / 48.0)
    return np.concatenate([np.cos(half), k * rv], axis=-1)


def quat_log(q: np.ndarray) -> np.ndarray:
    """Rotation vector of a unit quaternion, angle in [0, π]."""
    q = quat_normalize(q)
    vec = q[..., 1:]
    s = np.linalg.norm(vec, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., :1])
    k = np.where(s > _SMALL_ANGLE, angle / np.maximum(s, _SMALL_ANGLE), 2.0 / np.maximum(q[..., :1], _SMALL_ANGLE))
    return k * vec


def so3_exp(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues)."""
    return quat_to_rot(quat_exp(rotvec))


def so3_log(r: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix."""
    return quat_log(rot_to_quat(r))


def quat_from_euler(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Body→world quaternion from aerospace Z-Y-X Euler angles: ``R = Rz(yaw) Ry(pitch) Rx(roll)``."""
    cr, sr = np.cos(0.5 * roll), np.sin(0.5 * roll)
    cp, sp = np.cos(0.5 * pitch), np.sin(0.5 * pitch)
    cy, sy = np.cos(0.5 * yaw), np.sin(0.5 * yaw)
    return np.array(
        [
            cy * cp * cr + sy * sp * sr,
            cy * cp * sr - sy * sp * cr,
            cy * sp * cr + sy * cp * sr,
            sy * cp * cr - cy * sp * sr,
        ]
    )


def euler_from_quat(q: np.ndarray) -> np.ndarray:
    """``[roll, pitch, yaw]`` (Z-Y-X) of body→world quaternions; inverse of :func:`quat_from_euler`."""
    r = quat_to_rot(q)
    roll = np.arctan2(r[..., 2, 1], r[..., 2, 2])
    pitch = -np.arcsin(np.clip(r[..., 2, 0], -1.0, 1.0))
    yaw = np.arctan2(r[..., 1, 0], r[..., 0, 0])
    return np.stack([roll, pitch, yaw], axis=-1)


def yaw_of(q: np.ndarray) -> np.ndarray:
    """Heading (rotation about world down) of body→NED quaternions, radians in (-π, π]: :func:`euler_from_quat`'s
    yaw from the two entries of ``R(q)`` it takes, written as :func:`rot_of` writes them (the same numbers)."""
    q = np.asarray(q, dtype=float)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.asarray(np.arctan2(2.0 * (x * y + w * z), 1.0 - 2.0 * (y * y + z * z)))


def quat_slerp(q0: np.ndarray, q1: np.ndarray, alpha: np.ndarray | float) -> np.ndarray:
    """Spherical interpolation from ``q0`` (alpha = 0) to ``q1`` (alpha = 1) along the short arc."""
    q0 = np.asarray(q0, dtype=float)
    q1 = np.asarray(q1, dtype=float)
    alpha = np.asarray(alpha, dtype=float)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0.0, -q1, q1)
    delta = quat_log(quat_mul(quat_conj(q0), q1))
    return quat_normalize(quat_mul(q0, quat_exp(alpha * delta)))


def rotation_angle(q_a: np.ndarray, q_b: np.ndarray) -> np.ndarray:
    """Angle in radians of the rotation between two attitudes (``R_a^T R_b``), in [0, π]."""
    dq = quat_mul(quat_conj(q_a), q_b)
    return 2.0 * np.arctan2(np.linalg.norm(dq[..., 1:], axis=-1), np.abs(dq[..., 0]))


_COMPILED = (quat_product, rotvec_quat, quat_exp_of, rot_of, rotate, right_jacobian_of)


def __getattr__(name: str):
    """``compiled_<primitive>``: the primitive compiled by numba, for the kernels to call. Made on first use
    (numba imports scipy's top package, which the mapper's client must not load)."""
    if name.startswith("compiled_") and name[len("compiled_"):] in {f.__name__ for f in _COMPILED}:
        import numba

        for primitive in _COMPILED:
            globals()["compiled_" + primitive.__name__] = numba.njit(cache=True, nogil=True)(primitive)
        return globals()[name]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
