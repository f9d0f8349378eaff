"""4x4 homogeneous transforms in numpy (float64) and the pinhole projection we use.

Camera convention (Mitsuba's ``look_at``): the camera-to-world matrix has columns
``(left, up, forward, origin)``; the camera looks along its local +z. Image pixel x grows to
the camera's right (local -x) and pixel y grows downward (local -y). Pixel centres sit at
``(i + 0.5, j + 0.5)``. The field of view ``fov`` is horizontal (Mitsuba ``fov_axis="x"``).
"""

from __future__ import annotations

import numpy as np


def translate(v) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = np.asarray(v, dtype=np.float64)
    return m


def scale(s) -> np.ndarray:
    s = np.broadcast_to(np.asarray(s, dtype=np.float64), (3,))
    return np.diag([s[0], s[1], s[2], 1.0])


def rotate(axis, degrees: float) -> np.ndarray:
    """Rotation about ``axis`` (through the origin) by ``degrees`` (right-handed)."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    t = np.radians(degrees)
    c, s = np.cos(t), np.sin(t)
    x, y, z = a
    r = np.array([
        [c + x * x * (1 - c), x * y * (1 - c) - z * s, x * z * (1 - c) + y * s],
        [y * x * (1 - c) + z * s, c + y * y * (1 - c), y * z * (1 - c) - x * s],
        [z * x * (1 - c) - y * s, z * y * (1 - c) + x * s, c + z * z * (1 - c)],
    ])
    m = np.eye(4)
    m[:3, :3] = r
    return m


def euler(degrees_xyz) -> np.ndarray:
    """Rotation by Euler angles in degrees, applied x first, then y, then z."""
    rx, ry, rz = np.broadcast_to(np.asarray(degrees_xyz, dtype=np.float64), (3,))
    return rotate([0, 0, 1], rz) @ rotate([0, 1, 0], ry) @ rotate([1, 0, 0], rx)


def look_at(origin, target, up) -> np.ndarray:
    """Camera-to-world matrix with columns (left, up, forward, origin), as Mitsuba builds it."""
    o = np.asarray(origin, dtype=np.float64)
    d = np.asarray(target, dtype=np.float64) - o
    d /= np.linalg.norm(d)
    left = np.cross(np.asarray(up, dtype=np.float64), d)
    n = np.linalg.norm(left)
    if n < 1e-9:
        raise ValueError("camera up vector is parallel to the viewing direction")
    left /= n
    new_up = np.cross(d, left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, new_up, d, o
    return m


def apply(m: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Transform points ``[..., 3]`` by the 4x4 matrix ``m`` (affine)."""
    return points @ m[:3, :3].T + m[:3, 3]


def apply_vector(m: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Transform directions ``[..., 3]`` by the linear part of ``m``."""
    return vectors @ m[:3, :3].T


def tan_half_fov(fov: float, width: int, height: int) -> tuple[float, float]:
    """(tan of half the horizontal fov, tan of half the vertical fov) for square pixels."""
    tx = float(np.tan(np.radians(fov) / 2))
    return tx, tx * height / width


def camera_space(cam_to_world: np.ndarray, world_points: np.ndarray) -> np.ndarray:
    """World points ``[..., 3]`` -> our camera space (x right, y up, z forward), ``[..., 3]``."""
    local = apply(np.linalg.inv(cam_to_world), world_points)
    return local * np.array([-1.0, 1.0, 1.0])


def project(cam_to_world: np.ndarray, fov: float, width: int, height: int, world_points: np.ndarray,
            directions: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates ``[..., 2]`` (x right, y down, continuous; centres at +0.5) and
    planar depth ``[...]`` of world points (or of directions at infinity when ``directions``).
    """
    if directions:
        c = apply_vector(np.linalg.inv(cam_to_world), world_points) * np.array([-1.0, 1.0, 1.0])
    else:
        c = camera_space(cam_to_world, world_points)
    tx, ty = tan_half_fov(fov, width, height)
    z = c[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = width * 0.5 * (1.0 + c[..., 0] / (z * tx))
        v = height * 0.5 * (1.0 - c[..., 1] / (z * ty))
    return np.stack([u, v], axis=-1), z


def pixel_rays(cam_to_world: np.ndarray, fov: float, width: int, height: int) -> np.ndarray:
    """World-space unit directions ``[H, W, 3]`` of the rays through the pixel centres."""
    tx, ty = tan_half_fov(fov, width, height)
    u = (np.arange(width) + 0.5) / width * 2.0 - 1.0
    v = 1.0 - (np.arange(height) + 0.5) / height * 2.0
    xr = u[None, :] * tx
    yu = v[:, None] * ty
    local = np.stack(np.broadcast_arrays(-xr, yu, np.ones_like(xr * yu)), axis=-1)  # Mitsuba local axes
    d = apply_vector(cam_to_world, local)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)
