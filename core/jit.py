"""The one place that configures numba for core.

Why numba in a pure core: the paper's simulation must run at >= 2000x real
time at 100 Hz, i.e. <= 5 us per closed-loop step, which per-step Python
cannot reach. The controller and dynamics are therefore written once as
compiled kernels; the per-tick API that the live loop calls and the whole-run
simulator both call these same kernels. Compiled code is cached on disk.
"""

from __future__ import annotations

from typing import Any, Callable, TypeVar

import numba

F = TypeVar("F", bound=Callable[..., Any])


def kernel(fn: F) -> F:
    """Compile a numeric kernel (no Python objects inside), cached between runs."""
    return numba.njit(cache=True, nogil=True)(fn)  # type: ignore[no-any-return]


def ufunc(signature: str) -> Callable[[F], F]:
    """Compile a scalar function to a NumPy ufunc, callable from Python and from kernels."""

    def wrap(fn: F) -> F:
        return numba.vectorize([signature], cache=True)(fn)  # type: ignore[no-any-return]

    return wrap
