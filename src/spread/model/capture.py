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
    """``fn(x (B, N, C), t (B,)) → ε̂`` replayed from a CUDA graph (module docstring); ``warmup`` eager calls first.

    ``fallback`` (the default setting's use, ``sampling.cuda_graph=null``): ``check()`` is asked after the warm-up —
    which builds the kernels, so a Triton kernel that failed here has fallen back by then — and when it says no, or
    recording raises, the step runs eagerly from then on, with one warning. Without it a failure is raised."""

    def __init__(self, fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], warmup: int = 2,
                 check: Callable[[], bool] | None = None, fallback: bool = False):
        self.fn, self.warmup = fn, int(warmup)
        self.check, self.fallback = check, bool(fallback)
        self.graph = None
        self.key = None
        self.eager = False  # True once the fallback gave up recording
        self.captures = 0  # how many graphs were recorded (a new shape records a new one)

    def __call__(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        if x.device.type != "cuda" or self.eager:
            return self.fn(x, t)
        key = (tuple(x.shape), x.dtype, tuple(t.shape), t.dtype, x.device)
        if key != self.key:
            if not self._capture(x, t):
                return self.fn(x, t)
            self.key = key
        self.static_x.copy_(x)
        self.static_t.copy_(t)
        self.graph.replay()
        return self.static_out

    def _give_up(self, why: str) -> bool:
        import warnings

        self.eager, self.graph = True, None
        warnings.warn(f"sampling.cuda_graph: the step is not recorded ({why}); it runs eagerly", stacklevel=3)
        return False

    def _capture(self, x: torch.Tensor, t: torch.Tensor) -> bool:
        """Record a graph for these shapes; False when the fallback runs the step eagerly instead."""
        if not self.fallback:
            self._record(x, t)
            return True
        try:
            self._record(x, t, self.check)
        except _NotCapturable as reason:
            return self._give_up(str(reason))
        except RuntimeError as error:  # e.g. "operation not permitted when stream is capturing": a host read
            return self._give_up(f"{type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}")
        return True

    def _record(self, x: torch.Tensor, t: torch.Tensor, check: Callable[[], bool] | None = None) -> None:
        self.static_x, self.static_t = x.clone(), t.clone()
        stream = torch.cuda.Stream(device=x.device)
        stream.wait_stream(torch.cuda.current_stream(x.device))
        with torch.cuda.stream(stream), torch.no_grad():
            for _ in range(self.warmup):
                self.fn(self.static_x, self.static_t)
        torch.cuda.current_stream(x.device).wait_stream(stream)
        if check is not None and not check():
            raise _NotCapturable("the model's step reads the host on this device")
        # the warm-up's freed blocks stay cached for the side stream, where the graph's own memory pool cannot reuse
        # them: given back to the device, the pool can take that memory instead of adding to it (large batches)
        torch.cuda.empty_cache()
        self.graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.graph), torch.no_grad():
            self.static_out = self.fn(self.static_x, self.static_t)
        self.captures += 1


class _NotCapturable(Exception):
    """The model says, after the warm-up, that its step cannot be recorded here."""
