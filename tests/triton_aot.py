"""Compile every Triton kernel of torchcage for a GPU without one (``python tests/triton_aot.py
[sm]``): Triton's ahead-of-time compiler, down to a cubin with the ptxas its wheel ships. Prints one
line per kernel (name, seconds, cubin bytes, registers and stack per thread) and exits 1 on the first
kernel that does not compile.

Each kernel is launched once through its Python wrapper with the launch intercepted: the arguments
are recorded (types as Triton's launcher gives them: a Python float is an ``fp32`` scalar, an int
``i32``) and compiled for ``cuda:sm`` (90, an H100/H200, by default). Run by
``tests/test_triton_compile.py`` in a process of its own, as Triton decides between its
interpreter and its compiler when a kernel is defined (``TRITON_INTERPRET``, set to 0 when run as a
script). Importing this module (pytest's doctest collection) imports neither triton nor torchcage's
kernels.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tempfile
import time

import torch

_TYPES = {torch.float64: "*fp64", torch.float32: "*fp32", torch.int32: "*i32", torch.int64: "*i64", torch.uint8: "*u8"}


def _type(v: object) -> str:
    if isinstance(v, torch.Tensor):
        return _TYPES[v.dtype]
    if isinstance(v, bool):
        return "i1"
    if isinstance(v, int):
        return "i32" if -(2**31) <= v < 2**31 else "i64"
    if isinstance(v, float):
        return "fp32"
    raise TypeError(f"no Triton type for {type(v).__name__}")


def _recorded(module: object, name: str, call) -> tuple[object, dict[str, object]]:
    """The kernel ``module.name`` and the arguments ``call()`` launches it with."""
    kernel = getattr(module, name)
    seen: dict[str, object] = {}

    class Recorder:
        def __getitem__(self, grid: object):
            def launch(*args: object, **kwargs: object) -> None:
                seen.update(zip(kernel.arg_names, args, strict=False))
                seen.update(kwargs)

            return launch

    setattr(module, name, Recorder())
    try:
        call()
    except Exception:
        pass
    finally:
        setattr(module, name, kernel)
    if not seen:
        raise RuntimeError(f"{name} was not launched")
    return kernel, seen


def _kernels() -> list[tuple[str, object, dict[str, object]]]:
    import torchcage as tc
    from torchcage.families.green.kernel3d import triangle_green_data
    from torchcage.families.green.triton import gc3d
    from torchcage.families.mean_value.kernel3d import triangle_cage_data
    from torchcage.families.mean_value.triton import mvc2d, mvc3d, mvcd2d, mvcd3d
    from torchcage.families.quad_mean_value.kernel import quad_data
    from torchcage.families.quad_mean_value.triton import qmvc3d

    D = torch.float64
    cube = tc.load_cage(tc.data.path("cube.obj")).to(D).triangulated()
    square = tc.Cage(torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]], dtype=D))
    x3, x2 = torch.zeros(4, 3, dtype=D), torch.full((4, 2), 0.5, dtype=D)
    out = []
    for dt in (torch.float64, torch.float32):
        c = cube.to(dt)
        k, a = _recorded(mvc3d, "_mvc3d_kernel", lambda c=c, dt=dt: mvc3d.mvc3d_triton(
            x3.to(dt), mvc3d.triton_tables(triangle_cage_data(c, dt))))  # fmt: skip
        out.append((f"mvc3d {dt}", k, a))
        k, a = _recorded(mvc2d, "_mvc2d_kernel", lambda dt=dt: mvc2d.mvc2d_triton(
            x2.to(dt), mvc2d.triton_tables(square, dt)))  # fmt: skip
        out.append((f"mvc2d {dt}", k, a))
        k, a = _recorded(gc3d, "_gc3d_kernel", lambda c=c, dt=dt: gc3d.gc3d_triton(
            x3.to(dt), gc3d.triton_tables(triangle_green_data(c, dt), c.vertices)))  # fmt: skip
        out.append((f"gc3d {dt}", k, a))
    two = torch.stack([cube.vertices, 1.5 * cube.vertices])  # (a batch of two cages: the BATCHED kernel)
    k, a = _recorded(gc3d, "_gc3d_kernel", lambda: gc3d.gc3d_triton(
        x3[None], gc3d.batch_tables(two, cube.triangles, torch.full((2,), 1e-13, dtype=D))))  # fmt: skip
    out.append(("gc3d batched", k, a))
    quads = tc.load_cage(tc.data.path("cube.obj")).to(D)
    k, a = _recorded(mvc3d, "_mvc3d_kernel", lambda: mvc3d.mvc3d_triton(
        x3, mvc3d.part_tables(triangle_cage_data(cube, D)), normalize=False))  # fmt: skip
    out.append(("mvc3d raw weights", k, a))
    k, a = _recorded(qmvc3d, "_qmvc3d_kernel", lambda: qmvc3d.qmvc3d_triton(
        x3, qmvc3d.triton_tables(quads.vertices, quad_data(quads.vertices, quads.quads, 1e-12), 4),
        torch.zeros(4, 8, dtype=D), torch.zeros(4, dtype=torch.int32)))  # fmt: skip
    out.append(("qmvc3d", k, a))
    twoq = torch.stack([quads.vertices, 1.5 * quads.vertices])  # (a batch of two cages: the BATCHED kernel)
    k, a = _recorded(qmvc3d, "_qmvc3d_kernel", lambda: qmvc3d.qmvc3d_triton(
        x3[None], qmvc3d.batch_tables(twoq, quads.quads, torch.full((2,), 1e-12, dtype=D), 4),
        torch.zeros(2, 4, 8, dtype=D), torch.zeros(2, 4, dtype=torch.int32)))  # fmt: skip
    out.append(("qmvc3d batched", k, a))
    k, a = _recorded(mvcd2d, "_mvcd2d_kernel", lambda: mvcd2d.mvcd2d_triton(x2, square, 2))
    out.append(("mvcd2d", k, a))
    k, a = _recorded(mvcd3d, "_mvcd3d_kernel", lambda: mvcd3d.mvcd3d_triton(x3, cube, 2))
    out.append(("mvcd3d", k, a))
    cages = [cube, cube.with_vertices(1.5 * cube.vertices)]
    k, a = _recorded(mvcd3d, "_mvcd3d_kernel", lambda: mvcd3d.mvcd3d_triton_batch(
        x3[None], mvcd3d.batch_tables(two, cube.triangles, torch.full((2,), 1e-13, dtype=D)), 2, cages))  # fmt: skip
    out.append(("mvcd3d batched", k, a))
    return out


def _usage(cubin: bytes) -> str:
    """Registers and stack (spills) per thread, by the ``cuobjdump`` of Triton's wheel."""
    import triton

    tool = os.path.join(os.path.dirname(triton.__file__), "backends", "nvidia", "bin", "cuobjdump")
    with tempfile.NamedTemporaryFile(suffix=".cubin") as f:
        f.write(cubin)
        f.flush()
        try:
            out = subprocess.run([tool, "-res-usage", f.name], capture_output=True, text=True, timeout=60).stdout
        except (OSError, subprocess.SubprocessError):
            return ""
    m = re.search(r"REG:(\d+) STACK:(\d+)", out)
    return f"registers {m.group(1)}, stack {m.group(2)} B" if m else ""


def main(sm: int = 90) -> int:
    import triton
    from triton.backends.compiler import GPUTarget

    target = GPUTarget("cuda", sm, 32)
    for label, kernel, args in _kernels():
        constexprs = {kernel.arg_names[i]: args[kernel.arg_names[i]] for i in kernel.constexprs}
        signature = {n: ("constexpr" if n in constexprs else _type(args[n])) for n in kernel.arg_names}
        t = time.perf_counter()
        try:
            options = {k: args[k] for k in ("num_warps", "num_stages") if k in args}
            source = triton.compiler.ASTSource(kernel, signature, constexprs)
            compiled = triton.compile(source, target=target, options=options)
        except Exception as e:
            print(f"FAILED {label}: {e}", flush=True)
            return 1
        seconds = time.perf_counter() - t
        print(f"{label:22s} {seconds:6.1f} s  cubin {len(compiled.asm['cubin']):7d} B  {_usage(compiled.asm['cubin'])}",
              flush=True)  # fmt: skip
    return 0


if __name__ == "__main__":
    os.environ["TRITON_INTERPRET"] = "0"
    sys.exit(main(int(sys.argv[1]) if len(sys.argv) > 1 else 90))
