"""Second-order jets of scalar functions of a 3D point for the Triton kernels: the operations of
``torchcage/backends/native/jet.h`` on tuples ``(v, gx, gy, gz, hxx, hyy, hzz, hxy, hxz, hyz)`` of blocks
(the value, the gradient and the Hessian's upper triangle). A formula written with them carries its
own first and second derivatives, exact up to rounding.

Every function here is elementwise: masked-off lanes may hold inf or NaN, which the kernels drop
with ``tl.where`` (never by multiplying with a mask).
"""

from __future__ import annotations

import triton.language as tl

from torchcage.backends.triton import device_function
from torchcage.backends.triton.common import atan2


@device_function
def jconst(c, like):
    """The jet of a constant ``c`` (shaped as the block ``like``)."""
    z = tl.zeros_like(like)
    return c + z, z, z, z, z, z, z, z, z, z


@device_function
def jlinear(v, gx, gy, gz):
    """The jet of an affine function: value ``v``, gradient ``(gx, gy, gz)``, Hessian 0."""
    z = tl.zeros_like(v)
    return v, gx + z, gy + z, gz + z, z, z, z, z, z, z


@device_function
def jquad(v, gx, gy, gz, hxx, hyy, hzz, hxy, hxz, hyz):
    """A jet from its ten components (constants broadcast to the block of ``v``)."""
    z = tl.zeros_like(v)
    return v, gx + z, gy + z, gz + z, hxx + z, hyy + z, hzz + z, hxy + z, hxz + z, hyz + z


@device_function
def jadd(a, b):
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2], a[3] + b[3], a[4] + b[4],
            a[5] + b[5], a[6] + b[6], a[7] + b[7], a[8] + b[8], a[9] + b[9])  # fmt: skip


@device_function
def jsub(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2], a[3] - b[3], a[4] - b[4],
            a[5] - b[5], a[6] - b[6], a[7] - b[7], a[8] - b[8], a[9] - b[9])  # fmt: skip


@device_function
def jscale(a, c):
    return a[0] * c, a[1] * c, a[2] * c, a[3] * c, a[4] * c, a[5] * c, a[6] * c, a[7] * c, a[8] * c, a[9] * c


@device_function
def jwhere(m, a, b):
    """``a`` where ``m``, else ``b``, component by component."""
    return (tl.where(m, a[0], b[0]), tl.where(m, a[1], b[1]), tl.where(m, a[2], b[2]), tl.where(m, a[3], b[3]),
            tl.where(m, a[4], b[4]), tl.where(m, a[5], b[5]), tl.where(m, a[6], b[6]), tl.where(m, a[7], b[7]),
            tl.where(m, a[8], b[8]), tl.where(m, a[9], b[9]))  # fmt: skip


@device_function
def jmul(a, b):
    """The product rule."""
    av, ax, ay, az = a[0], a[1], a[2], a[3]
    bv, bx, by, bz = b[0], b[1], b[2], b[3]
    return (
        av * bv,
        av * bx + bv * ax,
        av * by + bv * ay,
        av * bz + bv * az,
        av * b[4] + bv * a[4] + 2.0 * ax * bx,
        av * b[5] + bv * a[5] + 2.0 * ay * by,
        av * b[6] + bv * a[6] + 2.0 * az * bz,
        av * b[7] + bv * a[7] + ax * by + ay * bx,
        av * b[8] + bv * a[8] + ax * bz + az * bx,
        av * b[9] + bv * a[9] + ay * bz + az * by,
    )


@device_function
def jf1(a, f0, f1, f2):
    """``f(a)`` from ``f(a.v) = f0``, ``f' = f1``, ``f'' = f2`` (the chain rule)."""
    ax, ay, az = a[1], a[2], a[3]
    return (
        f0,
        f1 * ax,
        f1 * ay,
        f1 * az,
        f1 * a[4] + f2 * ax * ax,
        f1 * a[5] + f2 * ay * ay,
        f1 * a[6] + f2 * az * az,
        f1 * a[7] + f2 * ax * ay,
        f1 * a[8] + f2 * ax * az,
        f1 * a[9] + f2 * ay * az,
    )


@device_function
def jf2(a, b, f, fa, fb, faa, fab, fbb):
    """``f(a, b)`` from its value and partial derivatives up to second order."""
    ax, ay, az = a[1], a[2], a[3]
    bx, by, bz = b[1], b[2], b[3]
    return (
        f,
        fa * ax + fb * bx,
        fa * ay + fb * by,
        fa * az + fb * bz,
        fa * a[4] + fb * b[4] + faa * ax * ax + 2.0 * fab * ax * bx + fbb * bx * bx,
        fa * a[5] + fb * b[5] + faa * ay * ay + 2.0 * fab * ay * by + fbb * by * by,
        fa * a[6] + fb * b[6] + faa * az * az + 2.0 * fab * az * bz + fbb * bz * bz,
        fa * a[7] + fb * b[7] + faa * ax * ay + fab * (ax * by + ay * bx) + fbb * bx * by,
        fa * a[8] + fb * b[8] + faa * ax * az + fab * (ax * bz + az * bx) + fbb * bx * bz,
        fa * a[9] + fb * b[9] + faa * ay * az + fab * (ay * bz + az * by) + fbb * by * bz,
    )


@device_function
def jrecip(a):
    r = 1.0 / a[0]
    return jf1(a, r, -r * r, 2.0 * r * r * r)


@device_function
def jdiv(a, b):
    return jmul(a, jrecip(b))


@device_function
def jsqrt(a):
    s = tl.sqrt(a[0])
    return jf1(a, s, 0.5 / s, -0.25 / (s * a[0]))


@device_function
def jatan2(y, x):
    xv = x[0]
    yv = y[0]
    r2 = xv * xv + yv * yv
    q = 1.0 / (r2 * r2)
    return jf2(y, x, atan2(yv, xv), xv / r2, -yv / r2, -2.0 * xv * yv * q, (yv * yv - xv * xv) * q, 2.0 * xv * yv * q)


@device_function
def atan_over(z):
    """``atan(z) / z`` and its first two derivatives: the series below ``|z| = 0.1`` (10 terms),
    else the closed form (``jet.h: atan_over``)."""
    small = tl.abs(z) < 0.1
    zs = tl.where(small, z, 0.0)
    z2 = zs * zs
    a0 = tl.zeros_like(z) + 1.0
    a1 = tl.zeros_like(z)
    a2 = tl.zeros_like(z)
    p = tl.zeros_like(z) + 1.0  # z^(2k - 2)
    k2 = tl.zeros_like(z) + 2.0  # 2k as a float
    sgn = tl.zeros_like(z) - 1.0  # (-1)^k
    for _k in range(1, 10):
        c = sgn / (k2 + 1.0)
        a2 += c * k2 * (k2 - 1.0) * p
        a1 += c * k2 * p * zs
        a0 += c * p * z2
        p *= z2
        k2 += 2.0
        sgn = -sgn
    zc = tl.where(small, 1.0, z)
    A = atan2(zc, tl.zeros_like(zc) + 1.0) / zc
    q = 1.0 / (1.0 + zc * zc)
    A1 = (q - A) / zc
    A2 = (-2.0 * zc * q * q - 2.0 * A1) / zc
    return tl.where(small, a0, A), tl.where(small, a1, A1), tl.where(small, a2, A2)
