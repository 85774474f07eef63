"""The elementwise pieces of the closed-form PA-MPJPE that core.geometry.procrustes runs on
(S,) stacks and core.geometry.procrustes_kernel compiles for scalars (one home of the
arithmetic for both): Horn's key matrix, the quaternion's rotation and the 4x4 adjugate's
term table."""

from __future__ import annotations

import numpy as np


def adjugate_table() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each 4x4 adjugate entry as three signed products (matrix entry) x (2x2 minor of rows
    (0,1): 0-5, or of rows (2,3): 6-11; columns 01 02 03 12 13 23): (entries (16,3), minors
    (16,3), signs (16,3))."""
    s0, s1, s2, s3, s4, s5, c0, c1, c2, c3, c4, c5 = range(12)
    terms = [  # adj[r][c] = sum sign * a[i][j] * minor, row-major over (r, c)
        [(+1, 1, 1, c5), (-1, 1, 2, c4), (+1, 1, 3, c3)],
        [(-1, 0, 1, c5), (+1, 0, 2, c4), (-1, 0, 3, c3)],
        [(+1, 3, 1, s5), (-1, 3, 2, s4), (+1, 3, 3, s3)],
        [(-1, 2, 1, s5), (+1, 2, 2, s4), (-1, 2, 3, s3)],
        [(-1, 1, 0, c5), (+1, 1, 2, c2), (-1, 1, 3, c1)],
        [(+1, 0, 0, c5), (-1, 0, 2, c2), (+1, 0, 3, c1)],
        [(-1, 3, 0, s5), (+1, 3, 2, s2), (-1, 3, 3, s1)],
        [(+1, 2, 0, s5), (-1, 2, 2, s2), (+1, 2, 3, s1)],
        [(+1, 1, 0, c4), (-1, 1, 1, c2), (+1, 1, 3, c0)],
        [(-1, 0, 0, c4), (+1, 0, 1, c2), (-1, 0, 3, c0)],
        [(+1, 3, 0, s4), (-1, 3, 1, s2), (+1, 3, 3, s0)],
        [(-1, 2, 0, s4), (+1, 2, 1, s2), (-1, 2, 3, s0)],
        [(-1, 1, 0, c3), (+1, 1, 1, c1), (-1, 1, 2, c0)],
        [(+1, 0, 0, c3), (-1, 0, 1, c1), (+1, 0, 2, c0)],
        [(-1, 3, 0, s3), (+1, 3, 1, s1), (-1, 3, 2, s0)],
        [(+1, 2, 0, s3), (-1, 2, 1, s1), (+1, 2, 2, s0)],
    ]
    t = np.array(terms)
    return t[..., 1] * 4 + t[..., 2], t[..., 3], t[..., 0].astype(np.float64)


#: each 4x4 adjugate entry as three signed products: entry (16,3), minor (16,3), sign (16,3)
ADJ_ENTRY, ADJ_MINOR, ADJ_SIGN = adjugate_table()


def fill_key_matrix(K, xx, xy, xz, yx, yy, yz, zx, zy, zz) -> None:
    """K[:4, :4] = Horn's key matrix of H = [[xx xy xz] [yx yy yz] [zx zy zz]], elementwise:
    entries of (S,) stacks here, scalars in the numba kernel that compiles this function."""
    K[0, 0] = xx + yy + zz
    K[1, 1] = xx - yy - zz
    K[2, 2] = yy - xx - zz
    K[3, 3] = zz - xx - yy
    K[0, 1] = K[1, 0] = yz - zy
    K[0, 2] = K[2, 0] = zx - xz
    K[0, 3] = K[3, 0] = xy - yx
    K[1, 2] = K[2, 1] = xy + yx
    K[1, 3] = K[3, 1] = zx + xz
    K[2, 3] = K[3, 2] = yz + zy


def fill_rotation(R, w, x, y, z) -> None:
    """R[:3, :3] = the rotation of the unit quaternion (w, x, y, z), elementwise (as
    :func:`fill_key_matrix`)."""
    R[0, 0] = w * w + x * x - y * y - z * z
    R[1, 1] = w * w - x * x + y * y - z * z
    R[2, 2] = w * w - x * x - y * y + z * z
    R[0, 1] = 2.0 * (x * y - w * z)
    R[1, 0] = 2.0 * (x * y + w * z)
    R[0, 2] = 2.0 * (x * z + w * y)
    R[2, 0] = 2.0 * (x * z - w * y)
    R[1, 2] = 2.0 * (y * z - w * x)
    R[2, 1] = 2.0 * (y * z + w * x)
