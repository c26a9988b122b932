"""Multi-process training (DistributedDataParallel, gloo, CPU) with torchcage modules, and the
sharded coordinate computation: two processes, checked against a single-process computation."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import textwrap
import warnings

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

import torchcage
from torchcage import functional as F
from torchcage.testing import icosphere

pytestmark = pytest.mark.skipif(not dist.is_available() or not dist.is_gloo_available(), reason="needs gloo")

STEPS, LR = 3, 0.5


def _problem(rank: int):
    ico = icosphere()
    g = torch.Generator().manual_seed(100 + rank)  # each rank its own data
    x = torch.randn(200, 3, generator=g, dtype=torch.float64)
    x = 0.8 * x / x.norm(dim=1, keepdim=True) * torch.rand(200, 1, generator=g, dtype=torch.float64)
    target = x * torch.tensor([1.2, 0.9, 1.0], dtype=torch.float64) + 0.1 * rank
    return ico, x, target


class CageModel(torch.nn.Module):
    """A learnable deformed cage driving a mean value coordinates module and a Green one."""

    def __init__(self, ico: torchcage.Cage, x: torch.Tensor) -> None:
        super().__init__()
        self.mvc = torchcage.MeanValueCoordinates(ico, x)
        self.gc = torchcage.GreenCoordinates(ico, x)
        self.offset = torch.nn.Parameter(torch.zeros(42, 3, dtype=torch.float64))
        self.register_buffer("rest", ico.vertices.clone())

    def forward(self) -> torch.Tensor:
        v = self.rest + self.offset
        return 0.5 * (self.mvc(v) + self.gc(v))


def _loss(model, target):
    return (model() - target).square().mean()


def _worker(rank: int, world: int, port: int, out: str) -> None:
    os.environ["MASTER_ADDR"], os.environ["MASTER_PORT"] = "127.0.0.1", str(port)
    dist.init_process_group("gloo", rank=rank, world_size=world)
    torch.set_num_threads(1)
    try:
        ico, x, target = _problem(rank)
        # each rank embeds its own points: the modules' buffers differ by rank and must not be
        # overwritten by rank 0's (DDP's default broadcast_buffers=True would do that)
        model = torch.nn.parallel.DistributedDataParallel(CageModel(ico, x), broadcast_buffers=False)
        opt = torch.optim.SGD(model.parameters(), lr=LR)
        for _ in range(STEPS):
            opt.zero_grad()
            _loss(model, target).backward()
            opt.step()
        # the sharded coordinates of one shared point set
        shared = _problem(7)[1]
        w = torchcage.distributed.shard_coordinates(F.mean_value_coordinates, shared, ico)
        phi, psi = torchcage.distributed.shard_coordinates(F.green_coordinates, shared[:101], ico)
        torch.save({"offset": model.module.offset.detach(), "w": w, "phi": phi, "psi": psi}, f"{out}/rank{rank}.pt")
    finally:
        dist.destroy_process_group()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_ddp_training_and_sharded_coordinates(tmp_path):
    world = 2
    mp.spawn(_worker, args=(world, _free_port(), str(tmp_path)), nprocs=world, join=True)
    res = [torch.load(tmp_path / f"rank{r}.pt") for r in range(world)]
    # reference: one process, the gradient averaged over the ranks' losses (what DDP computes)
    models = [CageModel(*_problem(r)[:2]) for r in range(world)]
    targets = [_problem(r)[2] for r in range(world)]
    offset = torch.zeros(42, 3, dtype=torch.float64)
    for _ in range(STEPS):
        grads = []
        for m, t in zip(models, targets, strict=True):
            m.offset.data.copy_(offset)
            m.zero_grad()
            _loss(m, t).backward()
            grads.append(m.offset.grad.clone())
        offset = offset - LR * torch.stack(grads).mean(0)
    assert offset.abs().max() > 1e-3  # training moved the cage
    for r in res:
        assert (r["offset"] - offset).abs().max() < 1e-12
    ico, shared = icosphere(), _problem(7)[1]
    w = F.mean_value_coordinates(shared, ico)
    phi, psi = F.green_coordinates(shared[:101], ico)
    for r in res:  # to rounding: the torch kernels' reductions depend on chunk sizes and threads
        for got, want in ((r["w"], w), (r["phi"], phi), (r["psi"], psi)):
            assert (got - want).abs().max() < 1e-13


def test_shard_slice_covers_everything():
    from torchcage.distributed import shard_slice

    for n in (0, 1, 7, 100):
        for world in (1, 2, 3, 8):
            idx = [i for r in range(world) for i in range(n)[shard_slice(n, r, world)]]
            assert idx == list(range(n))


_TEARDOWN = textwrap.dedent("""
    import faulthandler
    faulthandler.dump_traceback_later(100, exit=True)  # (a hang: where, on stderr)
    import torch, torch.distributed as dist
    from torchcage import functional as F
    from torchcage.distributed import shard_coordinates
    from torchcage.testing import icosphere

    cage, points = icosphere(), 0.5 * torch.rand(200, 3, dtype=torch.float64)
    reference = F.mean_value_coordinates(points, cage)
    for _ in range(40):
        dist.init_process_group("gloo", store=dist.HashStore(), rank=0, world_size=1)
        w = shard_coordinates(F.mean_value_coordinates, points, cage)
        phi, psi = shard_coordinates(F.green_coordinates, points, cage)
        dist.destroy_process_group()
        assert torch.equal(w, reference)
    print("done")
""")


def test_destroying_the_group_right_after_sharding_does_not_hang():
    """Under torch 2.5, ``destroy_process_group`` right after a gloo collective deadlocked (5 of about
    50 calls) when the collective's tensors were freed before gloo's worker let go of them (the
    worker then needs the GIL the destroying thread holds): without the fix, the forty rounds hung
    here. In a child process, which a hang cannot take down with the test run."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    try:
        out = subprocess.run([sys.executable, "-c", _TEARDOWN], capture_output=True, text=True, timeout=120, env=env)
    except subprocess.TimeoutExpired as err:
        raise AssertionError(f"init, shard_coordinates and destroy hung (torch {torch.__version__})") from err
    assert out.returncode == 0 and out.stdout.strip() == "done", out.stderr[-3000:]
    assert "still holds the gathered tensors" not in out.stderr, out.stderr[-3000:]  # (no wait hit its cap)


def _fake_gather(monkeypatch, backend: str, keep: list | None) -> None:
    """``dist.all_gather`` copying ``send`` into every output; with ``keep``, like a backend still
    working, it keeps a view of each tensor (a view holds a reference to its base: ``_use_count``
    stays up)."""

    def all_gather(out, send, group=None):
        for o in out:
            o.copy_(send)
        if keep is not None:
            keep.extend(t.view(-1) for t in [*out, send])

    monkeypatch.setattr(dist, "all_gather", all_gather)
    monkeypatch.setattr(dist, "get_backend", lambda group=None: backend)


def test_the_wait_for_gloo_is_bounded_and_warns(monkeypatch):
    """A backend that never lets go: the gather returns its values after the wait, with a warning
    naming the risk; on other backends there is no wait, and a backend that lets go draws none."""
    from torchcage.distributed import _all_gather_released

    monkeypatch.setattr(torchcage.distributed, "RELEASE_WAIT_S", 0.05)
    send = torch.arange(6.0).reshape(3, 2)
    for backend, waits in [("gloo", True), ("cpu:gloo,cuda:nccl", True), ("nccl", False), ("mpi", False)]:
        for keep in ([], None):
            _fake_gather(monkeypatch, backend, keep)
            out = [torch.empty(3, 2) for _ in range(2)]
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                _all_gather_released(out, send, None)
            assert all(torch.equal(o, send) for o in out)
            warned = any("still holds the gathered tensors" in str(w.message) for w in caught)
            assert warned == (waits and keep is not None), (backend, keep)
