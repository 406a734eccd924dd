"""Frame rotations: NED (earth) velocities into the body frame with the attitude Euler angles.

Conventions: aerospace 3-2-1 Euler angles (yaw psi, pitch theta, roll phi), body-to-NED rotation
``R = Rz(psi) Ry(theta) Rx(phi)``; body velocity ``v_b = R^T v_ned``. Arrays are (n_samples,) per
angle and (n_samples, 3) for vectors; radians and m/s. Where the velocity comes from (local or
global position) is :mod:`groundstation.dsp.prepare`'s choice.
"""

from __future__ import annotations

import numpy as np


def body_to_ned_matrix(roll_rad: np.ndarray, pitch_rad: np.ndarray, yaw_rad: np.ndarray) -> np.ndarray:
    """Rotation matrices body -> NED, shape (n, 3, 3) (or (3, 3) for scalars)."""
    phi = np.asarray(roll_rad, dtype=float)
    th = np.asarray(pitch_rad, dtype=float)
    psi = np.asarray(yaw_rad, dtype=float)
    cf, sf = np.cos(phi), np.sin(phi)
    ct, st = np.cos(th), np.sin(th)
    cp, sp = np.cos(psi), np.sin(psi)
    R = np.empty(np.broadcast(phi, th, psi).shape + (3, 3))
    R[..., 0, 0] = ct * cp
    R[..., 0, 1] = sf * st * cp - cf * sp
    R[..., 0, 2] = cf * st * cp + sf * sp
    R[..., 1, 0] = ct * sp
    R[..., 1, 1] = sf * st * sp + cf * cp
    R[..., 1, 2] = cf * st * sp - sf * cp
    R[..., 2, 0] = -st
    R[..., 2, 1] = sf * ct
    R[..., 2, 2] = cf * ct
    return R


def ned_to_body(
    v_ned_m_s: np.ndarray, roll_rad: np.ndarray, pitch_rad: np.ndarray, yaw_rad: np.ndarray
) -> np.ndarray:
    """Rotate NED velocities (n, 3) into body axes (n, 3): u forward, v right, w down."""
    R = body_to_ned_matrix(roll_rad, pitch_rad, yaw_rad)
    v = np.asarray(v_ned_m_s, dtype=float)
    return np.einsum("...ji,...j->...i", R, v)
