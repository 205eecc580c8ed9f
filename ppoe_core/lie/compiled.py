"""How :mod:`ppoe_core.lie` calls its compiled implementation (:mod:`ppoe_core.lie.kernels`): numba is imported on
the first call, not by ``import ppoe_core`` (``ppoe record`` starts fast), and a function of ``(..., *in)`` arrays is
the kernel's loop over the flattened leading axes."""

from __future__ import annotations

import importlib
from types import ModuleType
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["Array", "as_float", "lie_kernels", "compiled", "batched"]

Array = NDArray[np.float64]

_LIE: list[ModuleType] = []
_MODULES: dict[str, ModuleType] = {}


def as_float(x: ArrayLike) -> Array:
    """``x`` as a float64 array (no copy when it is one)."""
    return np.asarray(x, dtype=np.float64)


def lie_kernels() -> Any:
    """:mod:`ppoe_core.lie.kernels`, imported on the first call and kept (an import statement per message costs more
    than the kernel call)."""
    if not _LIE:
        _LIE.append(importlib.import_module("ppoe_core.lie.kernels"))
    return _LIE[0]


def compiled(name: str) -> Any:
    """The compiled module ``name`` (e.g. ``"ppoe_core.estimation.correction_kernels"``), imported on first use."""
    mod = _MODULES.get(name)
    if mod is None:
        mod = _MODULES[name] = importlib.import_module(name)
    return mod


def batched(kernel: str, x: ArrayLike, tail_in: tuple[int, ...], tail_out: tuple[int, ...]) -> Array:
    """``lie_kernels().<kernel>(flat, out)`` of ``x`` with shape ``(..., *tail_in)``, reshaped to
    ``(..., *tail_out)``.

    Raises
    ------
    ValueError
        ``x`` does not end in ``tail_in``.
    """
    a = as_float(x)
    k = len(tail_in)
    if a.shape[a.ndim - k:] != tail_in or a.ndim < k:
        raise ValueError(f"{kernel}: expected an array of shape (..., {', '.join(map(str, tail_in))}), "
                         f"got {a.shape}")
    lead = a.shape[:a.ndim - k]
    flat = np.ascontiguousarray(a.reshape((-1,) + tail_in))
    out = np.empty((flat.shape[0],) + tail_out)
    getattr(lie_kernels(), kernel)(flat, out)
    return out.reshape(lead + tail_out)
