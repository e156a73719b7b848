"""Private helpers: input validation and batch flattening shared by the public functions."""

from __future__ import annotations

import math
import sys

import numpy as np
import torch
from torch import Tensor

from torchcontact.errors import InputError


def in_tracing() -> bool:
    """True while tracing for ONNX export, TorchScript or torch.compile (no value checks then).

    ``torch.onnx`` is asked only once something imported it: no export runs without it, and
    torch imports it lazily, at a cost of 0.1 s (the first frame of a log job paid it).
    """
    onnx = sys.modules.get("torch.onnx")
    return bool(
        torch.jit.is_tracing()
        or (onnx is not None and onnx.is_in_onnx_export())
        or torch.compiler.is_compiling()
    )


def counts(x: Tensor) -> Tensor:
    """A program's counts ``(*S)`` float as ``(*S)`` int64, rounded to the nearest.

    Counts are ranks, unknowns, status bits and iterations: small non-negative integers held as
    floats.

    ``(x + 0.5)`` truncated, not ``torch.round``: round's CPU kernel opens an OpenMP region from a
    few thousand elements on, and the region's idle threads then spin for milliseconds, taking a
    core from a log job's reader and writer threads (16-20 % of the CPU of a warm
    ``estimate_file`` run with torch's default threads, measured).
    """
    return (x + 0.5).to(torch.int64)


def check_input(
    name: str,
    x: object,
    trailing: tuple[int, ...],
    model,
    expected: str,
    batch: torch.Size | None = None,
    finite: bool = True,
) -> None:
    """Raise :class:`~torchcontact.errors.InputError` unless ``x`` is shaped ``(*B, *trailing)``.

    Also checks that dtype and device match the model's and, outside tracing, that all values are
    finite.
    """
    if not isinstance(x, Tensor):
        raise InputError(
            f"{name} must be a torch.Tensor of shape {expected}, got {type(x).__name__}"
        )
    if x.dim() < len(trailing) or tuple(x.shape[x.dim() - len(trailing) :]) != trailing:
        raise InputError(f"{name} must have shape {expected}, got {tuple(x.shape)}")
    if x.dtype != model.dtype:
        raise InputError(
            f"{name} has dtype {x.dtype} but the model is {model.dtype}; use model.to(dtype=...)"
            " or convert the input"
        )
    if x.device != model.device:
        raise InputError(
            f"{name} is on {x.device} but the model is on {model.device}; use model.to(device)"
        )
    # one reduction (no mask allocated): a NaN or inf makes the sum non-finite; only then (or
    # on an overflowing sum of finite values) look for the culprit
    if finite and not in_tracing() and x.numel() and not _finite_sum(x):
        bad = (~torch.isfinite(x)).nonzero()
        if len(bad):
            raise InputError(
                f"{name} contains NaN or inf (first at index {tuple(bad[0].tolist())})"
            )


def _finite_sum(x: Tensor) -> bool:
    """Whether the sum of ``x`` is finite; a CPU float array is summed by numpy, on this thread.

    torch's CPU sum of more than 32768 elements is an OpenMP region, whose idle threads then
    spin for milliseconds beside a log job's reader and writer threads.
    """
    if (
        x.device.type == "cpu"
        and x.dtype in (torch.float32, torch.float64)
        and x.layout == torch.strided
        and not x.is_neg()
    ):
        return bool(np.isfinite(x.detach().numpy().sum()))
    return bool(torch.isfinite(x.sum()))


def flatten_batch(x: Tensor, batch: torch.Size, n_feature_dims: int) -> Tensor:
    """Reshape ``(*batch, *features)`` to ``(N, *features)``."""
    # math.prod, not batch.numel(): a symbolic batch size stays symbolic under torch.export
    return x.reshape(math.prod(batch), *x.shape[x.dim() - n_feature_dims :])
