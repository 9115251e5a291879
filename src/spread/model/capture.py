"""One denoising network call captured as a CUDA graph and replayed at every step (``sampling.cuda_graph``).

A sampling step of the paper-size geometry model is a few hundred kernels; on a GPU, launching them one by one
from Python costs more than running them. :class:`GraphedStep` wraps an ε-function ``fn(x_t, t) → ε̂``: on its first
call (and whenever the shapes change) it runs ``fn`` a few times on a side stream (warm-up: kernels compiled,
allocator settled), then records one call into a CUDA graph over static input buffers; every later call copies
``x_t`` and ``t`` into those buffers and replays the whole call as one launch. The result is the graph's output
buffer, overwritten by the next replay: callers use it before calling again (the sampling loop multiplies it by the
mask at once, which makes a new tensor).

``fn`` must read no tensor on the host and allocate nothing whose size depends on tensor values — SPREAD's network
after :meth:`~spread.model.network.SceneDenoiser.condition` does neither. On any device but CUDA the wrapper calls
``fn`` directly.
"""

from __future__ import annotations

from typing import Callable

import torch


class GraphedStep:
    """``fn(x (B, N, C), t (B,)) → ε̂`` replayed from a CUDA graph (module docstring); ``warmup`` eager calls first."""

    def __init__(self, fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], warmup: int = 2):
        self.fn, self.warmup = fn, int(warmup)
        self.graph = None
        self.key = None
        self.captures = 0  # how many graphs were recorded (a new shape records a new one)

    def __call__(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        if x.device.type != "cuda":
            return self.fn(x, t)
        key = (tuple(x.shape), x.dtype, tuple(t.shape), t.dtype, x.device)
        if key != self.key:
            self._capture(x, t)
            self.key = key
        self.static_x.copy_(x)
        self.static_t.copy_(t)
        self.graph.replay()
        return self.static_out

    def _capture(self, x: torch.Tensor, t: torch.Tensor) -> None:
        self.static_x, self.static_t = x.clone(), t.clone()
        stream = torch.cuda.Stream(device=x.device)
        stream.wait_stream(torch.cuda.current_stream(x.device))
        with torch.cuda.stream(stream), torch.no_grad():
            for _ in range(self.warmup):
                self.fn(self.static_x, self.static_t)
        torch.cuda.current_stream(x.device).wait_stream(stream)
        # the warm-up's freed blocks stay cached for the side stream, where the graph's own memory pool cannot reuse
        # them: given back to the device, the pool can take that memory instead of adding to it (large batches)
        torch.cuda.empty_cache()
        self.graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.graph), torch.no_grad():
            self.static_out = self.fn(self.static_x, self.static_t)
        self.captures += 1
