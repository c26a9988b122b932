"""Elementary functions for the Triton kernels, from arithmetic and ``sqrt`` alone: the same code
on a GPU and in Triton's interpreter (which runs no libdevice function), in float32 and float64."""

from __future__ import annotations

import triton
import triton.language as tl

PI = 3.141592653589793
HALF_PI = 1.5707963267948966


@triton.jit
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
    p = -1.0 / 23.0
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


@triton.jit
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
