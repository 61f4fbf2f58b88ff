"""The one place that decides how numerical kernels are compiled.

Every kernel in mavest is plain Python on NumPy arrays and scalars, compiled by
numba. Setting ``NUMBA_DISABLE_JIT=1`` runs those on arrays and scalars (so3,
sphere, the MAVLink scan) as Python, as coverage and debuggers see them; not
those on the filter's and the comparisons' records, which read fields as
attributes, as NumPy's plain records do not allow.

Compiled code is cached on disk so that only the first run on a machine pays
the compile time. numba keys each function's cache on its own source file
only, so a kernel would keep a stale copy of a callee edited in another file;
the cache directory is therefore named after a hash of every source file that
defines kernels (editing the command line does not force a recompile).

Loading a kernel from that cache skips numba's set-up for compiling
(:mod:`mavest._numba_cache`), which was the largest part of every command's start.
That, and compiling without numba's runtime, take numba's internals: they are used
only with the numba minor version they were tested with (:data:`TESTED_NUMBA`,
which pyproject.toml bounds numba to). With any other, or with
``MAVEST_NUMBA_PUBLIC=1``, kernels are numba's plain ``njit(cache=True)`` and its
public options only: slower to start and to run, the same results.
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
    return (
        re.search(rb"_jit import [^\n]*\b(inplace_)?(inlined_|exact_|callback_)?kernel\b", source)
        is not None
    )


TESTED_NUMBA = "0.68"


def _numba_internals_wanted() -> bool:
    """Whether to use numba's internals: with the tested numba, unless
    ``MAVEST_NUMBA_PUBLIC`` (set, not "0") asks for its public interface only."""
    if os.environ.get("MAVEST_NUMBA_PUBLIC", "0") != "0":
        return False
    return numba.__version__.split(".")[:2] == TESTED_NUMBA.split(".")


_NUMBA_INTERNALS = _numba_internals_wanted()


def _sources_digest() -> str:
    package = Path(__file__).parent
    # (the two ways of compiling write entries that the other cannot read)
    digest = hashlib.sha256(f"{numba.__version__} {_NUMBA_INTERNALS}".encode())
    for path in sorted(package.rglob("*.py")):
        source = path.read_bytes()
        # (how kernels are compiled and cached is part of every entry)
        if path.name in ("_jit.py", "_numba_cache.py") or compiles_kernels(source):
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


# The disk cache that loads kernels without numba's set-up for compiling (numba's
# internals: mavest._numba_cache); None: numba's public interface only.
_KernelCache = None
if _NUMBA_INTERNALS:
    from mavest import _numba_cache

    _KernelCache = _numba_cache.lean_cache_class()


def _compiled(**options: Any) -> Callable[[Callable[..., Any]], Any]:
    """A decorator compiling with ``options``, cached on disk."""
    options = {**_KERNEL_OPTIONS, **options}
    if _KernelCache is None:
        options.pop("_nrt", None)  # (a private option)
        return njit(cache=True, **options)
    return _numba_cache.cache_kernels(njit(**options), _KernelCache)


# nogil lets the pipeline run the filter in a worker thread without holding the
# interpreter; error_model="numpy" makes x/0 give inf/nan as NumPy does, which
# the kernels check for, instead of raising.
# No fastmath, not even its "contract" (a product and the sum it enters fused into one
# multiply-add), so that results do not depend on how the code was built: numba links a
# copy of every kernel a kernel calls into the caller's machine code, LLVM optimises each
# copy in its caller's context and fuses differently, and a call runs whichever copy the
# process loaded first: the callee's own when compiled in the process, a caller's when
# loaded from the disk cache (a replay's estimates differed in their last bits, and its
# output from mid-log on). Unfused, every copy rounds as the source says
# (tests/test_determinism.py); fusing had saved 5 % of an online sample at 200 Hz.
_KERNEL_OPTIONS = {"nogil": True, "error_model": "numpy", "fastmath": False}
kernel = _compiled()
# The same, inlined into its callers at numba's IR level: for the small kernels that
# pass over P several times a sample, where a call per block costs as much as the block
# (the reset's block products took half as long again as separate functions).
inlined_kernel = _compiled(inline="always")
# The filter's kernels allocate nothing: they work in the arrays they are given (the
# state record's fields and scratch). Compiled without numba's runtime (NRT), they
# also drop its reference counting, a call or two for every array that crosses a
# kernel's boundary, atomic where the array came from Python (tools/speed.py at
# 200 Hz: the batch loop 1.06 → 0.82 µs a sample, the online call 1.28 → 1.18). An
# allocation in one of them (or in anything it calls) fails to compile, saying so.
# (numba passes the setting down to callees that do not set it themselves.)
inplace_kernel = _compiled(_nrt=False)
inplace_inlined_kernel = _compiled(inline="always", _nrt=False)
# (every kernel is exact now: the MAVLink kernels' name for the same)
inplace_exact_kernel = inplace_kernel


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
            self._compiled = self._compile()
        return int(self._compiled.address)

    def _compile(self) -> Any:
        """numba's ``cfunc(signature, cache=True)``, loading from the cache as the
        kernels do (:func:`_lean_cache_class`) where numba's internals are used."""
        if _KernelCache is None:
            return numba.cfunc(self.signature, cache=True, **_KERNEL_OPTIONS)(self.function)
        return _numba_cache.compile_callback(
            self.function, self.signature, _KERNEL_OPTIONS, _KernelCache
        )


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
    it once here. Where numba's internals are not used (the overloads' entry points
    are not a documented interface), numba's eager form instead: compiled for these
    types only, so that others raise TypeError as the entry point's unboxing does.
    """
    if _KernelCache is not None:
        return _numba_cache.entry_point(function, *example)
    if numba.config.DISABLE_JIT:  # (plain Python: nothing to dispatch)
        function(*example)
        return function
    types = tuple(typeof(a) for a in example)
    return numba.jit(types, cache=True, **function.targetoptions)(function.py_func)
