"""A whole filtering run captured into one CUDA graph.

On a GPU a batched filter step is a few dozen small kernels; for batches up to ~10^5 sequences
their launch overhead, not the arithmetic, sets the speed. :class:`GraphedFilter` records the
complete ``T``-step scan of a :class:`~torchfilt.filters.GaussianFilter` (eager or
``compile=True``) once, on fixed-shape input buffers, and afterwards replays it with a single
``cudaGraphLaunch`` per run: the host does no work per step.

Constraints of a captured run (checked where possible):

* batch shape, ``T``, dtype and device are fixed at capture; so are ``x0``, ``P0`` and the model
  (parameters updated in place are seen by later replays; replaced tensors are not);
* no host synchronisation inside a step, so a covariance that fails its Cholesky factorisation
  turns its sequence to NaN instead of being jittered (as under ``torch.compile``), and a
  :class:`~torchfilt.exceptions.DivergenceWarning` is emitted after the replay;
* CUDA only. On the CPU use ``CKF(..., compile=True)``.
"""

from __future__ import annotations

import warnings
from typing import Any, Protocol

import torch
from torch import Tensor

from torchfilt.exceptions import ExecutionError, InputError, InputTypeError, ShapeError
from torchfilt.filters.engine import Engine
from torchfilt.filters.inputs import FilterInputs, observed
from torchfilt.filters.plan import ExecutionPlan
from torchfilt.filters.results import FilterResult, stack_records, warn_nonfinite
from torchfilt.settings import sync_free


class Scannable(Protocol):
    """What :class:`GraphedFilter` needs of a filter
    (:class:`~torchfilt.filters.GaussianFilter` provides it): the prepared inputs of a
    recording, its graphed :class:`~torchfilt.filters.plan.ExecutionPlan` (the plan refuses a
    step that decides on the host) and the :class:`~torchfilt.filters.engine.Engine` that runs
    the step."""

    def _capture(
        self, y: Tensor, u: Tensor | None, *, x0: Tensor, P0: Tensor
    ) -> tuple[FilterInputs, ExecutionPlan, Engine]: ...


__all__ = ["GraphedFilter", "Scannable"]


class GraphedFilter:
    """A filtering run of fixed shape captured into a CUDA graph and replayed.

    Build it with :meth:`GaussianFilter.graphed <torchfilt.filters.GaussianFilter.graphed>`.

    Args:
        filt: the filter to capture.
        y: example measurements ``(..., T, m)`` on a CUDA device; fixes the batch shape, ``T``,
            dtype and device of later runs.
        u: example inputs ``(..., T, nu)`` or ``None`` (then later runs take no inputs).
        x0: prior mean ``(..., n)``, fixed for every replay.
        P0: prior covariance ``(..., n, n)``, fixed for every replay.
        warmup: eager runs before the capture (they compile a ``compile=True`` step and let the
            CUDA caching allocator settle).

    Raises:
        ModelError: the filter's step cannot be captured (its plan says why).
        InputError: ``y`` is not on a CUDA device.
        ExecutionError: the filter's step needed a host synchronisation during capture (e.g. a
            model that reads values on the host); the message names the cause.
    """

    def __init__(
        self,
        filt: Scannable,
        y: Tensor,
        u: Tensor | None = None,
        *,
        x0: Tensor,
        P0: Tensor,
        warmup: int = 2,
    ) -> None:
        # the plan refuses a step that cannot be captured, and data off CUDA
        inp, plan, engine = filt._capture(y, u, x0=x0, P0=P0)
        if warmup < 1:
            raise InputError(f"warmup must be at least 1, got {warmup}")
        self.filter_ = filt
        # Static buffers: later runs copy their data into these before each replay.
        shape = (*inp.batch, *y.shape[-2:])
        self._y = inp.y.expand(shape).contiguous()
        self._obs = inp.obs.expand(shape).contiguous()
        self._u = None if inp.u is None else inp.u.expand(*inp.batch, *inp.u.shape[-2:]).clone()
        self._inp = type(inp)(
            self._y, self._obs, self._u, inp.x0.contiguous(), inp.P0.contiguous(), inp.batch
        )
        self.shape = shape
        self.dtype = inp.y.dtype
        self.device = inp.y.device
        self.plan = plan
        step_fn = engine.step_function(plan, self.device)

        side = torch.cuda.Stream(device=self.device)
        side.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(side), warnings.catch_warnings(), sync_free():
            warnings.simplefilter("ignore")
            for _ in range(warmup):
                engine.scan(plan, self._inp, step_fn)
        torch.cuda.current_stream(self.device).wait_stream(side)

        self.graph = torch.cuda.CUDAGraph()
        try:
            with torch.cuda.graph(self.graph), sync_free():
                records, _ = engine.scan(plan, self._inp, step_fn)
                observed_all = self._obs.expand(*inp.batch, *self._obs.shape[-2:])
                self._out = stack_records(records, observed_all, plan.numerics)
        except RuntimeError as e:
            raise ExecutionError(
                "GraphedFilter: capturing the filter into a CUDA graph failed; a step must not "
                f"synchronise with the host (no .item(), bool(tensor) or CPU copies): {e}"
            ) from e

    def filter(
        self,
        y: Tensor,
        u: Tensor | None = None,
        *,
        mask: Tensor | None = None,
        clone: bool = True,
    ) -> FilterResult:
        """Filter ``y`` by replaying the captured graph.

        Args:
            y: measurements of the captured shape ``(..., T, m)`` (dtype and device as captured).
                NaN entries are missing.
            u: inputs of the captured shape ``(..., T, nu)``, if the capture had inputs.
            mask: optional bool ``(..., T, m)``; ``False`` marks a component as missing.
            clone: return copies of the output buffers (default). ``False`` returns the buffers
                themselves, overwritten by the next replay.

        Returns:
            A :class:`~torchfilt.filters.FilterResult`, as :meth:`GaussianFilter.filter` gives.

        Raises:
            InputTypeError: ``y`` (or ``u``) is not a tensor, or of the wrong dtype.
            ShapeError: ``y``, ``u`` or ``mask`` is not of the captured shape.
            InputError: ``y`` or ``u`` not of the captured dtype and device, or inputs given
                to (or missing from) a capture without (or with) them.
        """
        if not isinstance(y, Tensor):
            raise InputTypeError(f"y must be a torch.Tensor, got {type(y).__name__}")
        if tuple(y.shape) != tuple(self.shape):
            raise ShapeError(
                f"y: the graph was captured for shape {tuple(self.shape)}, got {tuple(y.shape)}"
            )
        if y.dtype != self.dtype or y.device != self.device:
            raise InputError(
                f"y: the graph was captured for {self.dtype} on {self.device}, got {y.dtype} on "
                f"{y.device}"
            )
        if (u is None) != (self._u is None):
            raise InputError(
                "u: the graph was captured "
                + ("without" if self._u is None else "with")
                + " inputs"
            )
        obs = observed(y, mask)
        if obs.shape != self._obs.shape:
            raise ShapeError(
                f"mask: shape {tuple(obs.shape)} after broadcasting, the graph was captured for "
                f"{tuple(self._obs.shape)}"
            )
        self._obs.copy_(obs)
        self._y.copy_(torch.where(obs, y, torch.zeros((), dtype=y.dtype, device=y.device)))
        if u is not None:
            assert self._u is not None
            if tuple(u.shape) != tuple(self._u.shape):
                raise ShapeError(
                    f"u: the graph was captured for shape {tuple(self._u.shape)}, got "
                    f"{tuple(u.shape)}"
                )
            if not bool(torch.isfinite(u).all()):
                raise InputError("u contains non-finite entries; inputs cannot be missing")
            self._u.copy_(u)
        self.graph.replay()
        out = self._out
        if clone:
            clones: dict[str, Any] = {
                k: v.clone() for k, v in out._asdict().items() if isinstance(v, Tensor)
            }
            out = out._replace(**clones)
        warn_nonfinite(out, stacklevel=2)
        return out
