"""Running a program on a batch of frames: the backend choice and the eager chunking.

The estimator, the forward model and the dynamics functions all run their programs through
:func:`run_program`: a generated kernel (``"cpu"``/``"cuda"``, built now; or ``"auto"``, once the
background build is ready) takes the whole batch in one call; eager torch runs it in
cache-sized chunks. This module holds only that dispatch; the kernels and their cache are in
:mod:`torchcontact.kernels`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import torch
from torch import Tensor

from torchcontact import kernels
from torchcontact._internal import in_tracing

__all__ = ["run_chunked", "run_program"]


def run_chunked(
    fn: Callable[[dict[str, Tensor]], dict[str, Tensor]],
    tensors: Mapping[str, Tensor],
    chunk_size: int | None,
) -> dict[str, Tensor]:
    """``fn`` on row chunks of ``(N, k)`` tensors, outputs concatenated (one go while tracing).

    Args:
        fn: input name -> ``(n, k)`` to output name -> ``(n, k')``.
        tensors: input name -> ``(N, k)``.
        chunk_size: rows per call; None for one call.
    """
    n = next(iter(tensors.values())).shape[0]
    if chunk_size is None or n <= chunk_size or in_tracing():
        return fn(dict(tensors))
    parts = [fn({k: x[s : s + chunk_size] for k, x in tensors.items()})
             for s in range(0, n, chunk_size)]  # fmt: skip
    return {k: torch.cat([p[k] for p in parts]) for k in parts[0]}


def run_program(
    program: kernels.Program,
    tensors: Mapping[str, Tensor],
    backend: str = "auto",
    chunk_size: int | None = 16384,
) -> dict[str, Tensor]:
    """Run ``program`` on ``(N, k)`` tensors: a kernel in one call, eager torch in chunks.

    Args:
        program: the program.
        tensors: input name -> ``(N, k)`` tensor (one dtype and device).
        backend: ``"auto"`` (the compiled kernel once built, started in the background for
            batches of at least :data:`~torchcontact.kernels.AUTO_BUILD_MIN_FRAMES` frames;
            eager meanwhile, for gradients and while tracing), ``"eager"``, ``"cpu"`` or
            ``"cuda"`` (built now; :class:`~torchcontact.errors.KernelBuildError` on failure),
            ``"cached"`` (the kernel if built already, else eager; never a build).
        chunk_size: frames per eager call (bounds memory); None for one call.

    Returns:
        Output name -> ``(N, k)`` tensor.
    """
    first = next(iter(tensors.values()))
    if backend in ("cpu", "cuda"):
        return kernels.run(program, tensors, backend)
    if backend in ("auto", "cached"):
        k = kernels._usable_kernel(program, first, backend)
        if k is not None:
            return k(dict(tensors))
    return run_chunked(lambda t: kernels.run_eager(program, t), tensors, chunk_size)
