"""The switch and the entry of the compiled (numba) CPU kernels of the relational max aggregation
(:mod:`sb3_graph.common.layers._max_kernel`): whether they run, and the empty arrays that stand for
an absent argument."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

# "segment_max": the kernels also serve SegmentMax (benchmarks switch that alone off to time the
# learner without it, benchmarks/bench_learner.py).
# "compact": compute only the relation rows that some edge reads (:class:`_CompactRelationalConv`).
_COMPILED = {"enabled": True, "kernels": None, "segment_max": True, "compact": True}


def use_compiled_kernels(enabled: bool) -> bool:
    """Switch the compiled (numba) CPU kernels of the relational max aggregation on or off.

    Off, every device runs the PyTorch formulation of :class:`_RelationalMax`: the reference that
    the kernels are tested against (same values, gradients equal to float rounding).

    :param enabled: use the kernels for CPU tensors of float32 / float64
    :return: the previous setting
    """
    previous = _COMPILED["enabled"]
    _COMPILED["enabled"] = bool(enabled)
    return bool(previous)


def use_compact_rows(enabled: bool) -> bool:
    """Switch the compact relation rows of the compiled max path on or off
    (:class:`_CompactRelationalConv`: only the relation rows that some edge reads are computed).

    Off, the path computes every vertex's relation and root rows in one fused matmul, as before;
    both give the same values and gradients to float rounding.

    :param enabled: compute only the relation rows that some edge reads (with autograd, for
        stacked convolutions, and for large batches without it)
    :return: the previous setting
    """
    previous = _COMPILED["compact"]
    _COMPILED["compact"] = bool(enabled)
    return bool(previous)


def _kernels(device: torch.device) -> Any:
    """The compiled kernels module (imported on first use) for tensors on ``device``, or ``None``:
    switched off, not a CPU device, or numba missing or broken (then switched off for good)."""
    if not _COMPILED["enabled"] or device.type != "cpu":
        return None
    if _COMPILED["kernels"] is None:
        try:
            from sb3_graph.common.layers import _max_kernel
        except ImportError:  # numba missing or broken: the PyTorch formulation
            _COMPILED["enabled"] = False
            return None
        _COMPILED["kernels"] = _max_kernel
    return _COMPILED["kernels"]


def _compiled_path(rows: Tensor) -> bool:
    return rows.dtype in (torch.float32, torch.float64) and _kernels(rows.device) is not None


_NO_TERMS = np.empty((0, 2), dtype=np.int64)


def _empty_arrays(like: Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Empty ``(0, 0)`` and ``(0, 0, 0)`` arrays of the dtype of ``like``: the kernels' arguments
    for no separate root rows, no edge features and no edge features' weights."""
    dtype = torch.empty(0, dtype=like.dtype).numpy().dtype
    return np.empty((0, 0), dtype), np.empty((0, 0, 0), dtype)
