"""Directions, local frames and angle parameterisations.

Conventions (see ARCHITECTURE.md): in the sample frame +z is the surface normal and +x
the sample's reference direction; ``theta`` is measured from +z, ``phi`` from +x
counter-clockwise seen from above.  Directions are unit vectors in arrays of shape
``(..., 3)``; angles are in radians.  All functions are vectorised, work in float64 and
propagate NaN instead of raising.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]

_Z = np.array([0.0, 0.0, 1.0])


def as_vectors(v: ArrayLike) -> Array:
    """Return ``v`` as a float64 array whose last axis has length 3.

    Raises
    ------
    ValueError
        If the last axis is not of length 3.
    """
    a = np.asarray(v, dtype=np.float64)
    if a.ndim == 0 or a.shape[-1] != 3:
        raise ValueError(f"expected direction vectors of shape (..., 3), got shape {a.shape}")
    return a


def flat_pairs(wi: ArrayLike, wo: ArrayLike) -> tuple[Array, Array, tuple[int, ...]]:
    """Direction pairs broadcast together and flattened: ``(wi (N, 3), wo (N, 3), shape)``,
    ``shape`` the broadcast batch shape to give results back.

    Raises
    ------
    ValueError
        If a last axis is not of length 3, or the shapes do not broadcast.
    """
    wi, wo = np.broadcast_arrays(as_vectors(wi), as_vectors(wo))
    return wi.reshape(-1, 3), wo.reshape(-1, 3), wi.shape[:-1]


def dot(a: ArrayLike, b: ArrayLike) -> Array:
    """Dot product over the last axis, broadcasting the leading ones."""
    return np.einsum("...i,...i->...", as_vectors(a), as_vectors(b))


def normalize(v: ArrayLike) -> Array:
    """Unit vectors along ``v`` (shape ``(..., 3)``).

    A zero vector gives NaN components rather than a division warning.
    """
    a = as_vectors(v)
    n = np.sqrt(np.einsum("...i,...i->...", a, a))[..., None]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, a / np.where(n > 0, n, 1.0), np.nan)


def spherical_to_direction(theta: ArrayLike, phi: ArrayLike) -> Array:
    """Unit vector from polar angle ``theta`` and azimuth ``phi`` (radians).

    Returns
    -------
    ndarray, shape ``broadcast(theta, phi).shape + (3,)``
    """
    theta = np.asarray(theta, dtype=np.float64)
    phi = np.asarray(phi, dtype=np.float64)
    st = np.sin(theta)
    return np.stack(np.broadcast_arrays(st * np.cos(phi), st * np.sin(phi), np.cos(theta)), axis=-1)


def direction_to_spherical(w: ArrayLike) -> tuple[Array, Array]:
    """Polar angle ``theta`` in [0, pi] and azimuth ``phi`` in (-pi, pi] of directions ``w``.

    ``w`` need not be normalised.  For ``w`` along the z axis, ``phi`` is 0.
    """
    w = as_vectors(w)
    rho = np.hypot(w[..., 0], w[..., 1])
    theta = np.arctan2(rho, w[..., 2])
    phi = np.arctan2(w[..., 1], w[..., 0])
    return theta, phi


def cos_theta(w: ArrayLike) -> Array:
    """Cosine of the polar angle of unit directions in the local frame (the z component)."""
    return as_vectors(w)[..., 2]


def reflect(w: ArrayLike, n: ArrayLike = _Z) -> Array:
    """Mirror direction of ``w`` about the normal ``n``: ``2 (w.n) n - w``."""
    w = as_vectors(w)
    n = as_vectors(n)
    return 2.0 * dot(w, n)[..., None] * n - w


def frame_from_normal(n: ArrayLike, tangent: ArrayLike | None = None) -> Array:
    """Orthonormal frames whose third axis is the normal ``n``.

    Parameters
    ----------
    n
        Normals, shape ``(..., 3)``; normalised here.
    tangent
        Optional reference direction for the first axis; its component along ``n`` is
        removed (Gram-Schmidt).  Without it, a continuous branchless basis is built
        (Duff et al. 2017, "Building an Orthonormal Basis, Revisited").

    Returns
    -------
    ndarray, shape ``(..., 3, 3)``
        Rows are the frame's x (tangent), y (bitangent) and z (normal) axes in world
        coordinates, so ``to_local(v, F) = F @ v``.
    """
    n = normalize(n)
    if tangent is None:
        sign = np.where(n[..., 2] >= 0.0, 1.0, -1.0)
        a = -1.0 / (sign + n[..., 2])
        b = n[..., 0] * n[..., 1] * a
        t = np.stack([1.0 + sign * n[..., 0] ** 2 * a, sign * b, -sign * n[..., 0]], axis=-1)
        s = np.stack([b, sign + n[..., 1] ** 2 * a, -n[..., 1]], axis=-1)
    else:
        tg = as_vectors(tangent)
        t = normalize(tg - dot(tg, n)[..., None] * n)
        s = np.cross(n, t)
    t, s, n = np.broadcast_arrays(t, s, n)
    return np.stack([t, s, n], axis=-2)


def to_local(v: ArrayLike, frame: ArrayLike) -> Array:
    """Express world vectors ``v`` in ``frame`` (rows = axes, from :func:`frame_from_normal`)."""
    return np.einsum("...ij,...j->...i", np.asarray(frame, dtype=np.float64), as_vectors(v))


def to_world(v: ArrayLike, frame: ArrayLike) -> Array:
    """Inverse of :func:`to_local`."""
    return np.einsum("...ji,...j->...i", np.asarray(frame, dtype=np.float64), as_vectors(v))


def angle_between(a: ArrayLike, b: ArrayLike) -> Array:
    """Angle between vectors (rad, in [0, pi]), accurate near 0 and near pi.

    ``atan2(|a x b|, a . b)``, so neither vector needs to be normalised.

    Parameters
    ----------
    a, b
        Vectors, shape ``(..., 3)``, broadcast together (any length, same unit).

    Returns
    -------
    ndarray, shape ``broadcast(a, b).shape[:-1]``
        NaN where a component is NaN; 0 when a vector is zero.
    """
    a = as_vectors(a)
    b = as_vectors(b)
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.einsum("...i,...i", a, b))


def rotation_about(axis: ArrayLike, angle: ArrayLike) -> Array:
    """Rotation matrices about unit ``axis`` by ``angle`` (Rodrigues' formula).

    ``R = I + sin(angle) K + (1 - cos(angle)) K^2`` with ``K`` the cross-product matrix
    of ``axis``: ``R @ v`` turns ``v`` counter-clockwise about ``axis`` seen from its tip.

    Parameters
    ----------
    axis
        Unit rotation axes, shape ``(..., 3)`` (not normalised here).
    angle
        Rotation angles (rad), shape ``(...)``; broadcast against ``axis[..., 0]``.

    Returns
    -------
    ndarray, shape ``broadcast(axis[..., 0], angle).shape + (3, 3)``
        NaN in -> NaN out.
    """
    a = as_vectors(axis)
    # Filled in place rather than stacked: the same numbers, a fifth of the time on the
    # small batches kinematics and the rig calibration's Jacobians pass (~10^4 calls).
    K = np.zeros(a.shape + (3,))
    K[..., 0, 1], K[..., 0, 2] = -a[..., 2], a[..., 1]
    K[..., 1, 0], K[..., 1, 2] = a[..., 2], -a[..., 0]
    K[..., 2, 0], K[..., 2, 1] = -a[..., 1], a[..., 0]
    angle = np.asarray(angle, dtype=np.float64)
    s = np.sin(angle)[..., None, None]
    c = np.cos(angle)[..., None, None]
    return np.eye(3) + s * K + (1.0 - c) * (K @ K)


def rotation_angle(rotation: ArrayLike) -> Array:
    """Angle (rad, in [0, pi]) of rotation matrices: ``arccos((trace R - 1) / 2)``.

    The angle between two orientations ``R1``, ``R2`` is ``rotation_angle(R1 @ R2.T)``.

    Parameters
    ----------
    rotation
        Rotation matrices, shape ``(..., 3, 3)``.

    Returns
    -------
    ndarray, shape ``(...)``
        NaN in -> NaN out.
    """
    R = np.asarray(rotation, dtype=np.float64)
    if R.shape[-2:] != (3, 3):
        raise ValueError(f"expected rotation matrices of shape (..., 3, 3), got shape {R.shape}")
    return np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1.0, 1.0))


def look_along_rotation(forward: ArrayLike, up: ArrayLike = (0.0, 0.0, 1.0)) -> Array:
    """World-to-camera rotation of a camera looking along the unit vector ``forward``.

    OpenCV camera axes: x right, y down (image rows), z forward.  The image's up is
    ``up`` made perpendicular to ``forward``; where ``up`` is (nearly) parallel to it,
    the world's +y, then +x, is used instead.

    Parameters
    ----------
    forward
        Unit viewing directions, shape ``(..., 3)`` (not normalised here).
    up
        Approximate up directions of the image, shape ``(..., 3)``; any length.

    Returns
    -------
    ndarray, shape ``broadcast(forward, up).shape[:-1] + (3, 3)``
        Rows are the camera's x, y, z axes in world coordinates (the camera-to-world
        rotation is the transpose).  NaN in -> NaN out.
    """
    f = as_vectors(forward)
    up = as_vectors(up)
    shape = np.broadcast_shapes(f.shape, up.shape)
    f = np.broadcast_to(f, shape)
    right = np.full(shape, np.nan)
    found = np.zeros(shape[:-1], dtype=bool)
    # Cross products rather than projecting up onto the image plane: no cancellation when
    # up is nearly parallel to the view.
    for cand in (up, (0.0, 1.0, 0.0), (1.0, 0.0, 0.0)):
        r = np.cross(f, normalize(cand))
        nr = np.linalg.norm(r, axis=-1, keepdims=True)
        ok = ~found & (nr[..., 0] > 1e-9)
        with np.errstate(invalid="ignore", divide="ignore"):
            right = np.where(ok[..., None], r / nr, right)
        found |= ok
        if found.all():
            break  # the other candidates would change nothing (ok is False everywhere)
    R = np.stack([right, np.cross(f, right), f], axis=-2)
    nan = np.isnan(f).any(axis=-1) | np.isnan(up).any(axis=-1)
    return np.where(nan[..., None, None], np.nan, R)


def look_at_rotation(
    position: ArrayLike, target: ArrayLike, up: ArrayLike = (0.0, 0.0, 1.0)
) -> Array:
    """World-to-camera rotation of a camera at ``position`` looking at ``target``.

    :func:`look_along_rotation` with ``forward = normalize(target - position)``.

    Parameters
    ----------
    position, target
        Camera centre and the point it looks at (metres), shape ``(..., 3)``.
    up
        Approximate up direction of the image, shape ``(..., 3)``; any length.

    Returns
    -------
    ndarray, shape ``(..., 3, 3)``
        Rows are the camera's x (right), y (down), z (forward) axes in world
        coordinates.  NaN where ``position == target`` or an input is NaN.
    """
    return look_along_rotation(normalize(as_vectors(target) - as_vectors(position)), up)


def _rotate_z(v: Array, angle: Array) -> Array:
    c, s = np.cos(angle), np.sin(angle)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return np.stack(np.broadcast_arrays(c * x - s * y, s * x + c * y, z), axis=-1)


def _rotate_y(v: Array, angle: Array) -> Array:
    c, s = np.cos(angle), np.sin(angle)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return np.stack(np.broadcast_arrays(c * x + s * z, y, -s * x + c * z), axis=-1)


def half_diff_from_directions(wi: ArrayLike, wo: ArrayLike) -> tuple[Array, Array, Array, Array]:
    """Rusinkiewicz half/difference angles of direction pairs.

    Parameters
    ----------
    wi, wo
        Unit directions towards the light and the camera, shape ``(..., 3)``.

    Returns
    -------
    theta_h, phi_h, theta_d, phi_d : ndarray
        Half vector ``h = normalize(wi + wo)`` in spherical angles, and ``wi`` expressed in
        the frame obtained by rotating ``h`` onto the normal (radians).  For ``wi == -wo``
        the half vector is undefined and NaN is returned.
    """
    wi = as_vectors(wi)
    wo = as_vectors(wo)
    h = normalize(wi + wo)
    theta_h, phi_h = direction_to_spherical(h)
    d = _rotate_y(_rotate_z(wi, -phi_h), -theta_h)
    theta_d, phi_d = direction_to_spherical(d)
    return theta_h, phi_h, theta_d, phi_d


def directions_from_half_diff(
    theta_h: ArrayLike, phi_h: ArrayLike, theta_d: ArrayLike, phi_d: ArrayLike
) -> tuple[Array, Array]:
    """Inverse of :func:`half_diff_from_directions`: ``(wi, wo)`` from half/difference angles."""
    theta_h = np.asarray(theta_h, dtype=np.float64)
    phi_h = np.asarray(phi_h, dtype=np.float64)
    d = spherical_to_direction(theta_d, phi_d)
    wi = _rotate_z(_rotate_y(d, theta_h), phi_h)
    h = spherical_to_direction(theta_h, phi_h)
    wo = reflect(wi, h)
    return wi, wo
