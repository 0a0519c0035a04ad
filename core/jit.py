"""The one place that configures numba for core.

Why numba in a pure core: the paper's simulation must run at >= 2000x real
time at 100 Hz, i.e. <= 5 us per closed-loop step, which per-step Python
cannot reach. The controller and dynamics are therefore written once as
compiled kernels; the per-tick API that the live loop calls and the whole-run
simulator both call these same kernels. Compiled code is cached on disk.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar, cast

import numba
import numpy as np

F = TypeVar("F", bound=Callable[..., Any])


def kernel(fn: F) -> F:
    """Compile a numeric kernel (no Python objects inside), cached between runs."""
    return cast(F, numba.njit(cache=True, nogil=True)(fn))


def ufunc(signature: str) -> Callable[[Callable[..., float]], np.ufunc]:
    """Compile a scalar function to a NumPy ufunc, callable from Python (on scalars and
    arrays alike, so it is typed as a ufunc) and from kernels."""

    def wrap(fn: Callable[..., float]) -> np.ufunc:
        return cast(np.ufunc, numba.vectorize([signature], cache=True)(fn))  # type: ignore[no-untyped-call]  # numba ships no type hints

    return wrap
