"""Sharding the coordinate computation of a large point set across the ranks of a
``torch.distributed`` process group: each rank computes the coordinates of its slice of the
points, and every rank receives all of them.

Example (inside an initialised process group; see docs/learning.md)::

    w = torchcage.distributed.shard_coordinates(F.mean_value_coordinates, points, cage)
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from typing import Any

import torch

from torchcage.cage import Cage

__all__ = ["shard_coordinates", "shard_slice"]

#: Seconds ``shard_coordinates`` waits at most, per gather, for gloo's worker to let go of the
#: tensors (see ``_all_gather_released``); it warns when the wait runs out.
RELEASE_WAIT_S = 10.0


def shard_slice(n: int, rank: int, world: int) -> slice:
    """Rank ``rank``'s contiguous slice of ``n`` items split as evenly as possible over ``world``
    ranks (the first ``n % world`` ranks take one more).

    Examples:
        >>> tuple(shard_slice(10, r, 3).start for r in range(3)), shard_slice(10, 2, 3).stop
        ((0, 4, 7), 10)
    """
    base, extra = divmod(n, world)
    start = rank * base + min(rank, extra)
    return slice(start, start + base + (1 if rank < extra else 0))


def shard_coordinates(
    fn: Callable[..., Any], points: torch.Tensor, cage: Cage, *, group: Any = None, **kwargs: Any
) -> Any:
    """``fn(points, cage, **kwargs)`` computed in slices across the ranks of ``group`` and gathered:
    every rank returns the full result, equal to the unsharded call (each row of the coordinates
    depends on its point only).

    Args:
        fn: a functional of torchcage (``F.mean_value_coordinates``, ``F.green_coordinates``, ...)
            returning a tensor or a tuple of tensors with the points on the first axis.
        points: ``(N, D)``, the same on every rank.
        cage: one cage (not batched), the same on every rank.
        group: the process group (default: the world).
        **kwargs: passed to ``fn``.

    Returns:
        What ``fn`` returns for all ``N`` points, on every rank, equal to the unsharded call (to the
        rounding of the torch kernels' chunked reductions; bitwise with the native kernels). No
        autograd graph: the gathered results are constants, as the modules store them.

    Raises:
        RuntimeError: no initialised process group.
    """
    import torch.distributed as dist

    if not dist.is_available() or not dist.is_initialized():
        raise RuntimeError("shard_coordinates needs an initialised torch.distributed process group")
    rank, world = dist.get_rank(group), dist.get_world_size(group)
    n = points.shape[0]
    size = -(-n // world)  # every rank sends the same number of rows (the last ones padded)
    mine = shard_slice(n, rank, world)
    with torch.no_grad():
        local = fn(points[mine], cage, **kwargs)
    parts = local if isinstance(local, tuple) else (local,)
    gathered = []
    for part in parts:
        pad = part.new_zeros((size - part.shape[0], *part.shape[1:]))
        buf = [part.new_empty((size, *part.shape[1:])) for _ in range(world)]
        send = torch.cat([part, pad]).contiguous()
        _all_gather_released(buf, send, group)
        counts = [shard_slice(n, r, world) for r in range(world)]
        gathered.append(torch.cat([b[: s.stop - s.start] for b, s in zip(buf, counts, strict=True)]))
    return tuple(gathered) if isinstance(local, tuple) else gathered[0]


def _all_gather_released(out: list[torch.Tensor], send: torch.Tensor, group: Any) -> None:
    """``dist.all_gather(out, send)``; where gloo carries it, returning once gloo's worker thread has
    let go of the tensors (within ``RELEASE_WAIT_S``, else with a warning; ``out`` is filled either way).

    The collective's result is ready before gloo's worker thread drops its references to the
    tensors. Were their Python objects freed first, the worker would free the tensors and need the
    GIL for it. With torch 2.5 (not 2.13), ``dist.destroy_process_group()`` joins that thread while
    holding the GIL: the process hangs for good (5 of about 50 calls right after this function
    hung here). Holding our references until the worker's are gone avoids it. Other backends
    (NCCL, which may hold CUDA tensors until the device is done) are not waited for.
    """
    import torch.distributed as dist

    backend = str(dist.get_backend(group))
    wait = backend == "gloo" or f"{send.device.type}:gloo" in backend  # (or "cpu:gloo,cuda:nccl")
    tensors = [*out, send]
    before = [t._use_count() for t in tensors]
    dist.all_gather(out, send, group=group)
    deadline = time.monotonic() + RELEASE_WAIT_S
    while wait and any(t._use_count() > b for t, b in zip(tensors, before, strict=True)):
        if time.monotonic() > deadline:
            warnings.warn(
                f"shard_coordinates: gloo still holds the gathered tensors after {RELEASE_WAIT_S:g} s; under "
                "torch 2.5 a destroy_process_group() now may hang",
                RuntimeWarning,
                stacklevel=3,
            )
            break
        time.sleep(1e-4)  # (releases the GIL, which the worker may need meanwhile)
