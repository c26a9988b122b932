"""Elementary functions for the Triton kernels, from arithmetic and ``sqrt`` alone: the same code
on a GPU and in Triton's interpreter (which runs no libdevice function), in float32 and float64."""

from __future__ import annotations

import triton.language as tl

from torchcage.backends.triton import device_function

PI = tl.constexpr(3.141592653589793)
HALF_PI = tl.constexpr(1.5707963267948966)


@device_function
def atan(t):
    """``atan(t)``: ``|t| > 1`` reflected (``pi/2 - atan(1/t)``), two half-angle steps
    (``z / (1 + sqrt(1 + z^2))``, down to ``|z| <= tan(pi/16)``), then 12 terms of the series
    (``z^24 / 25 < 1e-18``): within a few ulps in float64."""
    a = tl.abs(t)
    inv = a > 1.0
    z = tl.where(inv, 1.0 / tl.where(inv, a, 1.0), a)
    z = z / (1.0 + tl.sqrt(1.0 + z * z))
    z = z / (1.0 + tl.sqrt(1.0 + z * z))
    s = z * z
    # (a float literal alone becomes an fp32 scalar on a GPU: -1/23 lost its fp64 digits)
    p = tl.zeros_like(s) - 1.0 / 23.0
    p = p * s + 1.0 / 21.0
    p = p * s - 1.0 / 19.0
    p = p * s + 1.0 / 17.0
    p = p * s - 1.0 / 15.0
    p = p * s + 1.0 / 13.0
    p = p * s - 1.0 / 11.0
    p = p * s + 1.0 / 9.0
    p = p * s - 1.0 / 7.0
    p = p * s + 1.0 / 5.0
    p = p * s - 1.0 / 3.0
    p = p * s + 1.0
    r = 4.0 * z * p
    r = tl.where(inv, HALF_PI - r, r)
    return tl.where(t < 0, -r, r)


@device_function
def atan2(y, x):
    """``atan2(y, x)`` in ``(-pi, pi]`` (0 at the origin)."""
    ax = tl.abs(x)
    ay = tl.abs(y)
    big = tl.maximum(ax, ay)
    small = tl.minimum(ax, ay)
    r = atan(small / tl.where(big > 0, big, 1.0))
    r = tl.where(ay > ax, HALF_PI - r, r)
    r = tl.where(x < 0, PI - r, r)
    return tl.where(y < 0, -r, r)


LN2 = tl.constexpr(0.6931471805599453)
SQRT2 = tl.constexpr(1.4142135623730951)


@device_function
def log(x):
    """``log(x)`` for ``x > 0`` (0 elsewhere): the exponent taken out by a binary search on powers
    of two (``2^512 .. 2^1``; the constants past float32's range never select), the mantissa
    ``m`` in ``[1/sqrt 2, sqrt 2)`` through ``2 atanh((m - 1) / (m + 1))`` (11 terms of its series,
    ``z^2 <= 0.0295``): within a few ulps in float64."""
    ok = x > 0
    m = tl.where(ok, x, 1.0)
    e = tl.zeros_like(m)
    for p in tl.static_range(9, -1, -1):
        big = 2.0 ** (2**p)
        up = m >= big
        m = tl.where(up, m / big, m)
        e = tl.where(up, e + 2**p, e)
        down = m < 1.0 / big
        m = tl.where(down, m * big, m)
        e = tl.where(down, e - 2**p, e)
    # now 2^-1 <= m < 2
    lo = m < 1.0
    m = tl.where(lo, m * 2.0, m)
    e = tl.where(lo, e - 1.0, e)
    hi = m > SQRT2
    m = tl.where(hi, m * 0.5, m)
    e = tl.where(hi, e + 1.0, e)
    z = (m - 1.0) / (m + 1.0)
    s = z * z
    q = tl.zeros_like(s) + 1.0 / 23.0
    q = q * s + 1.0 / 21.0
    q = q * s + 1.0 / 19.0
    q = q * s + 1.0 / 17.0
    q = q * s + 1.0 / 15.0
    q = q * s + 1.0 / 13.0
    q = q * s + 1.0 / 11.0
    q = q * s + 1.0 / 9.0
    q = q * s + 1.0 / 7.0
    q = q * s + 1.0 / 5.0
    q = q * s + 1.0 / 3.0
    q = q * s + 1.0
    return tl.where(ok, 2.0 * z * q + e * LN2, 0.0)
