"""The native kernels' calling interface, written once: each C entry point's arguments (names as in
its C prototype, types, and the shapes of its arrays), the :mod:`ctypes` argument types derived
from it, and :func:`check_arguments`, which validates a keyword call before any pointer is taken.

An argument is written ``name:type`` with ``type`` one of

* ``i64`` (C ``long``), ``i32`` (``int``), ``f64`` (``double``): scalars;
* ``f64*``, ``i32*``, ``u8*``: ``const`` arrays (inputs); a trailing ``!`` marks an output
  (non-``const``) array, a trailing ``?`` an array that may be ``None`` (``NULL``);

followed for arrays by ``[shape]``, comma-separated expressions in the scalar arguments (``T``,
``2*Q``, ``V+1``); ``...`` in a shape skips the check of that dimension. ``tests/test_native_abi.py``
parses the C prototypes and fails on any drift from these tables.
"""

from __future__ import annotations

import ctypes
import functools
import re
from dataclasses import dataclass

import torch

__all__ = ["SIGNATURES", "Arg", "argtypes", "check_arguments"]

_DTYPES = {"f64": torch.float64, "i32": torch.int32, "u8": torch.uint8}
_SCALARS = {"i64": ctypes.c_long, "i32": ctypes.c_int, "f64": ctypes.c_double}
_ARG = re.compile(
    r"^(?P<name>\w+):(?P<kind>i64|i32|f64|u8)(?P<ptr>\*)?(?P<out>!)?(?P<opt>\?)?(?:\[(?P<shape>[^\]]*)\])?$"
)


@dataclass(frozen=True)
class Arg:
    """One argument of a native entry point."""

    name: str
    kind: str  # "i64" | "i32" | "f64" | "u8"
    pointer: bool
    output: bool = False
    optional: bool = False
    shape: tuple[str, ...] | None = None

    @property
    def c_type(self) -> str:
        """The argument's C type, normalised as ``tests/test_native_abi.py`` reads prototypes."""
        base = {"i64": "long", "i32": "int", "f64": "double", "u8": "unsigned char"}[self.kind]
        if not self.pointer:
            return base
        return f"{base} *" if self.output else f"const {base} *"


def _parse(spec: str) -> tuple[Arg, ...]:
    args = []
    for token in spec.split():
        m = _ARG.match(token)
        if m is None:
            raise ValueError(f"bad native argument spec {token!r}")
        shape = tuple(s.strip() for s in m["shape"].split(",")) if m["shape"] is not None else None
        args.append(Arg(m["name"], m["kind"], bool(m["ptr"]), bool(m["out"]), bool(m["opt"]), shape))
    return tuple(args)


# Layouts (see each C file's comment): structure-of-arrays ``(3, T)`` where a pass vectorises over
# faces, array-of-structures ``(T, 3)`` elsewhere. ``tol`` is the absolute on-cage tolerance.
SIGNATURES: dict[str, tuple[Arg, ...]] = {
    "tc_mvc3d": _parse(
        "B:i64 P:f64*[B,3,V] V:i64 tri:i32*[3,T] T:i64 edges:i32*[2,E] E:i64 fe:i32*[3,T] inc_ptr:i32*[V+1] "
        "inc_idx:i32*[3*T] fs:f64*[3,T] nrm:f64*[B,3,T] two_area:f64*[B,T] ell:f64*[B,T,3] gram:f64*[B,T,3,3] "
        "far_bary:f64*[Q,3] far_qw:f64*[Q] longest:f64*[B,T] Q:i64 far_c:f64 cancel_c:f64 "
        "X:f64*[XB,n,3] XB:i64 n:i64 tol:f64*[B] near_c:f64 nthreads:i32 W:f64*![B,n,V] on:u8*![B,n] normalize:i32"
    ),
    "tc_mvc2d": _parse(
        "B:i64 P:f64*[B,V,2] V:i64 edges:i32*[E,2] E:i64 X:f64*[XB,n,2] XB:i64 n:i64 tol:f64*[B] nthreads:i32 "
        "W:f64*![B,n,V] on:u8*![B,n]"
    ),
    "tc_gc3d": _parse(
        "Pv:f64*[3,V] V:i64 tri:i32*[3,T] T:i64 edges:i32*[2,E] E:i64 eu:f64*[3,E] fe:i32*[3,T] nrm:f64*[T,3] "
        "two_area:f64*[T] ell:f64*[T,3] edir:f64*[T,3,3] eout:f64*[T,3,3] gbary:f64*[T,3,3] longest:f64*[T] "
        "far_nodes:f64*[T,Q,3] far_w:f64*[T,Q] far_bary:f64*[Q,3] Q:i64 far_c:f64 X:f64*[n,3] n:i64 "
        "tol:f64 nthreads:i32 PHI:f64*![n,V] PSI:f64*![n,T] ONF:i32*!?[n] AL:f64*!?[n,3]"
    ),
    "tc_gc3d_batch": _parse(
        "B:i64 Pv:f64*[B,3,V] V:i64 tri:i32*[3,T] T:i64 edges:i32*[2,E] E:i64 eu:f64*[B,3,E] fe:i32*[3,T] "
        "nrm:f64*[B,T,3] two_area:f64*[B,T] ell:f64*[B,T,3] edir:f64*[B,T,3,3] eout:f64*[B,T,3,3] "
        "gbary:f64*[B,T,3,3] longest:f64*[B,T] far_nodes:f64*[B,T,Q,3] far_w:f64*[B,T,Q] far_bary:f64*[Q,3] Q:i64 "
        "far_c:f64 X:f64*[B,n,3] n:i64 tol:f64*[B] nthreads:i32 PHI:f64*![B,n,V] PSI:f64*![B,n,T] "
        "ONF:i32*!?[B,n] AL:f64*!?[B,n,3]"
    ),
    "tc_gc3d_vjp_batch": _parse(
        "B:i64 P:f64*[B,V,3] V:i64 tri:i32*[T,3] T:i64 nrm:f64*[B,T,3] edir:f64*[B,T,3,3] eout:f64*[B,T,3,3] "
        "gbary:f64*[B,T,3,3] gnorm:f64*[B,T,3] two_area:f64*[B,T] longest:f64*[B,T] thin:u8*[B,T] "
        "far_nodes:f64*[B,T,Q,3] far_w:f64*[B,T,Q] far_bary:f64*[Q,3] Q:i64 far_c:f64 near_c:f64 vertex_c:f64 "
        "tol:f64*[B] X:f64*[B,n,3] n:i64 GPHI:f64*[B,n,V] GPSI:f64*[B,n,T] nthreads:i32 GX:f64*![B,n,3] "
        "GA:f64*![B,V,3] GF:f64*![B,T,33] GN:f64*![B,T,Q,3] GW:f64*![B,T,Q] reg:u8*![B,n]"
    ),
    "tc_gcd3d": _parse(
        "Pv:f64*[3,V] V:i64 tri:i32*[3,T] T:i64 edges:i32*[2,E] E:i64 eu:f64*[3,E] fe:i32*[3,T] nrm:f64*[T,3] "
        "two_area:f64*[T] ell:f64*[T,3] edir:f64*[T,3,3] eout:f64*[T,3,3] gbary:f64*[T,3,3] longest:f64*[T] "
        "far_nodes:f64*[T,Q,3] far_w:f64*[T,Q] far_bary:f64*[Q,3] Q:i64 far_c:f64 X:f64*[n,3] n:i64 "
        "tol:f64 order:i32 nthreads:i32 GPHI:f64*![n,V,3] GPSI:f64*![n,T,3] HPHI:f64*!?[n,V,3,3] "
        "HPSI:f64*!?[n,T,3,3] OK:i32*![n]"
    ),
    "tc_qmvc3d": _parse(
        "B:i64 P:f64*[B,V,3] V:i64 quads:i32*[Q,4] Q:i64 size:f64*[B,Q] X:f64*[XB,npts,3] XB:i64 npts:i64 "
        "tol:f64*[B] n:i32 qtol:f64 gl:f64*[17,2,16] nthreads:i32 W:f64*![B,npts,V] on:u8*![B,npts]"
    ),
    "tc_qgc3d": _parse(
        "B:i64 P:f64*[B,V,3] V:i64 quads:i32*[Q,4] Q:i64 size:f64*[B,Q] pinv:f64*[B,Q,8,4] null:f64*[B,Q,8,4] "
        "origin:f64*[B,3] pattern:i32*[Pn,3,2] Pn:i64 K:i32 X:f64*[XB,n,3] XB:i64 n:i64 tol:f64*[B] qtol:f64 "
        "gl:f64*[17,2,16] nthreads:i32 PHI:f64*![B,n,V] PSIQ:f64*![B,n,4*Q] ONQ:i32*![B,n] UV:f64*![B,n,2] "
        "s_Pv:f64*[B,3,V] s_tri:i32*[3,2*Q] s_edges:i32*[2,s_E] s_E:i64 s_eu:f64*[B,3,s_E] s_fe:i32*[3,2*Q] "
        "s_nrm:f64*[B,2*Q,3] s_two_area:f64*[B,2*Q] s_ell:f64*[B,2*Q,3] s_edir:f64*[B,2*Q,3,3] "
        "s_eout:f64*[B,2*Q,3,3] s_gbary:f64*[B,2*Q,3,3]"
    ),
    "tc_mvcd3d": _parse(
        "B:i64 P:f64*[B,V,3] V:i64 tri:i32*[T,3] T:i64 fe:i32*[T,3] NE:i64 E:f64*[B,T,3,3] nrm:f64*[B,T,3] "
        "two_area:f64*[B,T] ell:f64*[B,T,3] gram:f64*[B,T,3,3] longest:f64*[B,T] far_nodes:f64*[B,T,Q,3] "
        "far_coef:f64*[B,T,Q,3] Q:i64 far_c:f64 near_c:f64 gl_y:f64*[ng] gl_w:f64*[ng] ng:i32 X:f64*[XB,n,3] "
        "XB:i64 n:i64 tol:f64*[B] order:i32 nthreads:i32 L:f64*![B,n,V] G:f64*![B,n,V,3] H:f64*!?[B,n,V,3,3] "
        "on:u8*![B,n]"
    ),
    "tc_mvcd2d": _parse(
        "B:i64 P:f64*[B,V,2] V:i64 edges:i32*[NE,2] NE:i64 X:f64*[XB,n,2] XB:i64 n:i64 tol:f64*[B] order:i32 "
        "nthreads:i32 L:f64*![B,n,V] G:f64*![B,n,V,2] H:f64*!?[B,n,V,2,2] on:u8*![B,n]"
    ),
    "tc_mvc3d_vjp": _parse(
        "P:f64*[V,3] V:i64 tri:i32*[T,3] T:i64 X:f64*[n,3] n:i64 G:f64*[n,V] tol:f64 near_c:f64 cancel_c:f64 "
        "far_always:f64 nthreads:i32 GX:f64*![n,3] GP:f64*![V,3] reg:u8*![n]"
    ),
    "tc_mvc3d_vjp_batch": _parse(
        "B:i64 P:f64*[B,V,3] V:i64 tri:i32*[T,3] T:i64 X:f64*[B,n,3] n:i64 G:f64*[B,n,V] tol:f64*[B] near_c:f64 "
        "cancel_c:f64 far_always:f64 nthreads:i32 GX:f64*![B,n,3] GP:f64*![B,V,3] reg:u8*![B,n]"
    ),
    "tc_mvc3d_vjp_near": _parse(
        "P:f64*[V,3] V:i64 tri:i32*[T,3] T:i64 X:f64*[n,3] n:i64 G:f64*[n,V] tol:f64 near_c:f64 cancel_c:f64 "
        "far_always:f64 band:f64 near_d:f64 far_d:f64 split_pairs:i32 nthreads:i32 GX:f64*![n,3] "
        "GP:f64*![V,3] status:u8*![n] PAIR:u8*![n,T] WB:f64*![n,V] SN:f64*![n] HS:f64*![n]"
    ),
    "tc_winding3d": _parse("P:f64*[T,3,3] T:i64 X:f64*[n,3] n:i64 nthreads:i32 W:f64*![n]"),
    "tc_nearest3d": _parse("P:f64*[T,3,3] T:i64 S:f64*?[T] X:f64*[n,3] n:i64 nthreads:i32 D:f64*![n] I:i32*![n]"),
    "tc_lbc_admm": _parse(
        "D:i64 C:i64 m:i64 V:i64 g_ptr:i32*[D*C+1] g_idx:i32*[g_nnz] g_val:f64*[g_nnz] g_nnz:i64 gt_ptr:i32*[m+1] "
        "gt_idx:i32*[gt_nnz] gt_val:f64*[gt_nnz] gt_nnz:i64 l_ptr:i32*[m+1] l_idx:i32*[l_nnz] l_val:f64*[l_nnz] "
        "l_nnz:i64 u_ptr:i32*[m+1] u_idx:i32*[u_nnz] u_val:f64*[u_nnz] u_nnz:i64 u_diag:f64*[m] pr:i32*[m] "
        "pc:i32*[m] nb:i64 GtJ:f64*[m,V] H:f64*[m,V] phiA:f64*[C,V] Q:f64*[D+1,V] mu:f64 alpha:f64 ws:f64 "
        "iters:i64 nthreads:i32 P1:f64*![D*C,V] P2:f64*![m+nb,V] u1:f64*![D*C,V] u2:f64*![m,V] "
        "work:f64*![2*D*C*V+2*m*V+2*nthreads*D*V+2*nthreads*V] res:f64*![2]"
    ),
    "tc_raster2d": _parse(
        "P:f64*[B,Nv,2] B:i64 Nv:i64 tri:i32*[T,3] T:i64 H:i64 W:i64 S:f64*[Nv,C] C:i64 nthreads:i32 "
        "out:i32*![B,H,W] val:f64*![B,H,W,C]"
    ),
}


def argtypes(name: str) -> list[type]:
    """The :mod:`ctypes` argument types of entry point ``name`` (pointers as ``c_void_p``)."""
    return [ctypes.c_void_p if a.pointer else _SCALARS[a.kind] for a in SIGNATURES[name]]


@functools.cache
def _terms(expr: str) -> tuple[tuple[int | str, ...], ...]:
    """A shape expression (``"3*T+1"``) parsed once: its terms, each a tuple of factors (numbers
    or scalar names)."""
    return tuple(
        tuple(int(f) if f.isdigit() else f for f in (factor.strip() for factor in term.split("*")))
        for term in expr.split("+")
    )


def _dim(expr: str, scalars: dict[str, int]) -> int | None:
    if expr == "...":
        return None
    total = 0
    for term in _terms(expr):
        prod = 1
        for factor in term:
            prod *= factor if isinstance(factor, int) else int(scalars[factor])
        total += prod
    return total


def check_arguments(name: str, kwargs: dict[str, object]) -> list[object]:
    """Validate a keyword call of entry point ``name`` and return its positional C arguments.

    Arrays must be CPU tensors of the declared dtype, contiguous, of the declared shape (outputs
    are written in place, so they must not be temporary copies); scalars are converted to ``int``
    or ``float``.

    Raises:
        TypeError: a missing or unknown argument, a tensor where a scalar is expected or the reverse.
        ValueError: a wrong dtype, device, layout or shape (the message names the argument).
    """
    sig = SIGNATURES[name]
    names = {a.name for a in sig}
    missing = [a.name for a in sig if a.name not in kwargs]
    extra = sorted(set(kwargs) - names)
    if missing or extra:
        raise TypeError(f"{name}: missing arguments {missing}, unknown arguments {extra}")
    scalars: dict[str, int] = {}
    for a in sig:
        if not a.pointer:
            value = kwargs[a.name]
            if isinstance(value, torch.Tensor):
                raise TypeError(f"{name}: argument {a.name!r} is a scalar ({a.kind}), got a tensor")
            scalars[a.name] = float(value) if a.kind == "f64" else int(value)  # type: ignore[arg-type]
    out: list[object] = []
    for a in sig:
        value = kwargs[a.name]
        if not a.pointer:
            out.append(scalars[a.name])
            continue
        if value is None and a.optional:
            out.append(None)
            continue
        if not isinstance(value, torch.Tensor):
            raise TypeError(f"{name}: argument {a.name!r} must be a tensor, got {type(value).__name__}")
        want = _DTYPES[a.kind]
        if value.dtype != want or value.device.type != "cpu" or not value.is_contiguous():
            raise ValueError(
                f"{name}: argument {a.name!r} must be a contiguous CPU {want} tensor, got {value.dtype} on "
                f"{value.device} (contiguous: {value.is_contiguous()})"
            )
        if a.shape is not None:
            expect = [_dim(d, scalars) for d in a.shape]
            ok = value.dim() == len(expect) and all(
                e is None or e == s for e, s in zip(expect, value.shape, strict=False)
            )
            if not ok:
                raise ValueError(
                    f"{name}: argument {a.name!r} must have shape {list(a.shape)} = {expect}, got {list(value.shape)}"
                )
        out.append(value.data_ptr())
    return out
