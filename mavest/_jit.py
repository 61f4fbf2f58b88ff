"""The one place that decides how numerical kernels are compiled.

Every kernel in mavest is plain Python on NumPy arrays and scalars, compiled by
numba. Setting ``NUMBA_DISABLE_JIT=1`` runs the very same code as Python, which
is how coverage and debuggers see it.

Compiled code is cached on disk so that only the first run on a machine pays
the compile time. numba keys each function's cache on its own source file
only, so a kernel would keep a stale copy of a callee edited in another file;
the cache directory is therefore named after a hash of every source file that
defines kernels (editing the command line does not force a recompile).
"""

from __future__ import annotations

import hashlib
import os
import re
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numba
from numba import njit, typeof


def compiles_kernels(source: bytes) -> bool:
    """Whether a module's source takes this module's decorators (so its kernels' code
    is part of the cache's key)."""
    return re.search(rb"_jit import [^\n]*\b(inlined_|callback_)?kernel\b", source) is not None


def _sources_digest() -> str:
    package = Path(__file__).parent
    digest = hashlib.sha256(numba.__version__.encode())
    for path in sorted(package.rglob("*.py")):
        source = path.read_bytes()
        if path.name == "_jit.py" or compiles_kernels(source):
            digest.update(path.relative_to(package).as_posix().encode())
            digest.update(source)
    return digest.hexdigest()[:16]


def _cache_directory() -> Path:
    base = os.environ.get("MAVEST_CACHE_DIR") or os.environ.get("NUMBA_CACHE_DIR")
    root = Path(base) if base else Path.home() / ".cache" / "mavest"
    directory = root / f"numba-{_sources_digest()}"
    try:
        directory.mkdir(parents=True, exist_ok=True)
        probe = directory / ".writable"
        probe.touch()
    except OSError:  # read-only home: a per-user temporary cache still saves the next run
        directory = Path(tempfile.gettempdir()) / f"mavest-numba-{os.getuid()}-{directory.name}"
        directory.mkdir(parents=True, exist_ok=True)
    return directory


CACHE_DIRECTORY = _cache_directory()
numba.config.CACHE_DIR = str(CACHE_DIRECTORY)


def cache_is_warm() -> bool:
    """Whether compiled kernels are already cached (else the first call compiles)."""
    return any(CACHE_DIRECTORY.rglob("*.nbi"))


# nogil lets the pipeline run the filter in a worker thread without holding the
# interpreter; error_model="numpy" makes x/0 give inf/nan as NumPy does, which
# the kernels check for, instead of raising.
_KERNEL_OPTIONS = {"nogil": True, "error_model": "numpy"}
kernel = njit(cache=True, **_KERNEL_OPTIONS)
# The same, inlined into its callers at numba's IR level: for the small kernels that
# pass over P several times a sample, where a call per block costs as much as the block
# (the reset's block products took half as long again as separate functions).
inlined_kernel = njit(cache=True, inline="always", **_KERNEL_OPTIONS)


class CallbackKernel:
    """A kernel compiled as a C function (numba's ``cfunc``) for compiled code to call
    through its address, with no Python objects crossing: compiled, or loaded from the
    cache, on first use rather than at import (``numba.cfunc`` compiles when applied,
    and importing mavest must not compile).

    Under ``NUMBA_DISABLE_JIT`` there is no compiled code to call back; callers check
    :attr:`available` and take their dispatched path instead.
    """

    def __init__(self, function: Callable[..., Any], signature: Any) -> None:
        self.function = function
        self.signature = signature
        self._compiled: Any = None

    @property
    def available(self) -> bool:
        return not numba.config.DISABLE_JIT

    @property
    def address(self) -> int:
        """The C function's address (compiles or loads it the first time)."""
        if self._compiled is None:
            if not self.available:
                raise RuntimeError("no C callbacks with NUMBA_DISABLE_JIT set")
            self._compiled = numba.cfunc(self.signature, cache=True, **_KERNEL_OPTIONS)(
                self.function
            )
        return int(self._compiled.address)


def callback_kernel(signature: Any) -> Callable[[Callable[..., Any]], CallbackKernel]:
    """``function`` as a :class:`CallbackKernel` of this numba signature."""

    def decorate(function: Callable[..., Any]) -> CallbackKernel:
        return CallbackKernel(function, signature)

    return decorate


def without_dispatch(function: Any, *example: Any) -> Callable[..., Any]:
    """``function`` compiled for the types of ``example`` (called once with it, so the
    example must be safe to change), as a callable that skips numba's type dispatch.

    Resolving a structured array's numba type on every call costs more than a
    small kernel does; a caller whose records keep their dtypes for life resolves
    it once here. Falls back to the dispatcher if numba's internals differ (the
    overloads' entry points are not a documented interface).
    """
    function(*example)
    overload = getattr(function, "overloads", {}).get(tuple(typeof(a) for a in example))
    return overload.entry_point if overload is not None else function
