"""CUDA graphs: a call recorded once on static input buffers, then replayed as one launch.

A small network's forward on a GPU is a few dozen tiny kernels, each costing a launch on the
host (microseconds) that is longer than the kernel itself; replaying a recorded graph costs one.
Two users, each at a batch shape that stays fixed while they run:

- the served policy: a batch-1 call of a fixed-step sampler, encoder and sampler recorded
  together (`sefa_model/policy/artifact.py`);
- reflow's batched solves: the velocity field f(x, t, cond) at a block's B*K rows, replayed at
  every network evaluation of the solve (`FieldGraphs`). The solver itself stays on the host:
  RK45's step sizes are decided there from the error norm.

torch.cuda.graphs' own wrapper (`make_graphed_callables`) is made for training (it records
backward too and wants autograd-visible inputs); here nothing is trained, so the graph is
recorded directly with `torch.cuda.graph`, as its docs show for inference.
"""

from __future__ import annotations

import warnings
from typing import Callable, Hashable

import torch
from torch import Tensor

Args = Tensor | dict[str, Tensor]


def _clone(a: Args) -> Args:
    return {k: v.clone() for k, v in a.items()} if isinstance(a, dict) else a.clone()


def _copy_into(dst: Args, src: Args) -> None:
    if isinstance(dst, dict):
        for k, v in src.items():
            dst[k].copy_(v)
    else:
        dst.copy_(src)


def _device(a: Args) -> torch.device:
    return next(iter(a.values())).device if isinstance(a, dict) else a.device


class CapturedCall:
    """fn(*args) (each a tensor or a dict of tensors) recorded once as a CUDA graph on static
    copies of the example args, then replayed. Each call copies its inputs into the buffers and
    returns a copy of the output (the next replay overwrites it). Warm-up runs on a side stream
    first, as torch.cuda.graphs asks, so that lazy initialisation is not recorded."""

    def __init__(self, fn: Callable[..., Tensor], *args: Args, warmup: int = 3):
        self.args = tuple(_clone(a) for a in args)
        device = _device(args[0])
        side = torch.cuda.Stream(device=device)
        side.wait_stream(torch.cuda.current_stream(device))
        with torch.cuda.stream(side):
            for _ in range(warmup):
                fn(*self.args)
        torch.cuda.current_stream(device).wait_stream(side)
        self.graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.graph):
            self.out = fn(*self.args)

    def __call__(self, *args: Args) -> Tensor:
        for dst, src in zip(self.args, args):
            _copy_into(dst, src)
        self.graph.replay()
        return self.out.clone()


class GraphCache(dict):
    """Recorded calls by key (each user's key says which calls share a graph), None for a key
    whose capture failed: that key then runs eager, said in one warning."""

    def recorded(self, key, fn: Callable[..., Tensor], *args: Args, failing: Callable[[], str],
                 record: Callable[..., Callable[..., Tensor]] = CapturedCall):
        """The graph of `key`, recorded from fn(*args) at its first call; None: run eager.
        failing() begins the warning of a capture that fails (an op that cannot be recorded);
        a callable, so that the calls that replay build no message."""
        if key not in self:
            try:
                self[key] = record(fn, *args)
            except RuntimeError as e:
                warnings.warn(f"{failing()} ({str(e).splitlines()[0]})")
                self[key] = None
        return self[key]


Field = Callable[[Tensor, Tensor, Tensor], Tensor]
"""f(x (B, T, Da), t (B,), cond (B, D)) -> (B, T, Da)"""


class FieldGraphs:
    """A velocity field recorded as a CUDA graph per (tag, input shapes and dtypes), recorded at
    its first call and replayed at every later one. Made for CUDA tensors: its owner makes one
    only where the field runs on CUDA (elsewhere the capture fails, eager). The owner names what the
    field computes with `tag` (e.g. a student's step input): two fields of one tag and shapes
    must compute the same function, since the second replays the first's graph.

    A capture that fails (an op that cannot be recorded) leaves that key eager, with one
    warning. `record` is the recorder (CapturedCall; tests hand in their own). `replays` and
    `eager` count the calls of each kind."""

    def __init__(self, record: Callable[..., Callable[..., Tensor]] = CapturedCall):
        self.record = record
        self.graphs = GraphCache()
        self.replays = 0
        self.eager = 0

    def field(self, fn: Field, tag: Hashable = None) -> Field:
        def captured(x: Tensor, t: Tensor, cond: Tensor) -> Tensor:
            graph = self._graph(fn, tag, x, t, cond)
            if graph is None:
                self.eager += 1
                return fn(x, t, cond)
            self.replays += 1
            return graph(x, t, cond)

        return captured

    def _graph(self, fn: Field, tag: Hashable, x: Tensor, t: Tensor, cond: Tensor):
        key = (tag, *((a.shape, a.dtype, a.device) for a in (x, t, cond)))
        return self.graphs.recorded(
            key, fn, x, t, cond, record=self.record,
            failing=lambda: f"running the velocity field eager: its CUDA graph capture at "
                            f"{tuple(x.shape)} failed")
