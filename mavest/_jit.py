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

Loading a kernel from that cache skips numba's set-up for compiling (see
:func:`_lean_cache_class`), which was the largest part of every command's start.
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


def _module_symbols(bitcode: bytes) -> tuple[tuple[str, ...], frozenset[str]]:
    """The symbols a compiled module takes from outside itself (numba's runtime and
    helpers, libm, Python's C API; LLVM's own intrinsics need no one) and those it
    defines, by name."""
    import llvmlite.binding as ll

    module = ll.parse_bitcode(bitcode)
    external: list[str] = []
    defined: set[str] = set()
    for values in (module.functions, module.global_variables):
        for value in values:
            if not value.is_declaration:
                defined.add(value.name)
            elif not value.name.startswith("llvm."):
                external.append(value.name)
    return tuple(sorted(external)), frozenset(defined)


def _library_parsed_when_linked(codegen: Any, serialized: Any, defined: frozenset[str]) -> Any:
    """numba's ``CPUCodeLibrary._unserialize`` of a library cached as object code,
    except that the module's bitcode, which a load parses only to list the symbols
    it defines and to keep for linking into code compiled later, is parsed when such
    code first links it: the list is recorded in the entry. (Parsing was 45 of a
    replay's 210 ms after imports, the filter's 1 MB module most of it.)"""
    import llvmlite.binding as ll

    name, _, (object_code, bitcode) = serialized
    library = codegen.create_library(name)
    library.enable_object_caching()
    library._set_compiled_object(object_code)
    parsed: list[Any] = []

    def module_for_linking() -> Any:
        if not parsed:
            parsed.append(ll.parse_bitcode(bitcode))
        return parsed[0]

    library._get_module_for_linking = module_for_linking
    library._finalize_final_module()
    codegen._engine._defined_symbols |= defined
    return library


def _lean_cache_class() -> type | None:
    """numba's disk cache for mavest's kernels, loading them without numba's set-up
    for compiling; None if this numba's cache is not built as expected.

    Before each load from the cache, numba refreshes its compiler's target: it
    imports and registers every typing and lowering module it has, its linear
    algebra among them, whose BLAS check imports scipy.linalg. That was about half a
    second of every command's start, and a load uses none of it: a cached kernel is
    object code, which needs symbols numba registers when it starts (helpers, libm),
    those of its runtime (NRT) if it uses it, plus any that a module registers when
    imported. So that no kernel runs with a symbol missing (a crash, not an error),
    each entry records, when compiled, the external symbols it uses; a load that
    finds one not yet defined initialises the runtime (which defines its own), then
    if one is still missing refreshes, as numba would. A command whose kernels are
    all compiled without the runtime (``inplace_kernel``: ``mavest replay``) never
    initialises it, 20 ms. A compile (a cache miss) refreshes as always: numba's
    compiler does it itself.

    The entry also records the symbols its module defines, which numba's load gets
    by parsing the module's bitcode: that is parsed only when code compiled later
    links the kernel in (:func:`_library_parsed_when_linked`).
    """
    try:
        import llvmlite.binding as ll
        from numba.core.caching import CompileResultCacheImpl, FunctionCache
        from numba.core.ccallback import CFunc  # noqa: F401 (CallbackKernel compiles with it)
        from numba.core.codegen import CPUCodeLibrary, JITCPUCodegen, JitEngine
        from numba.core.compiler_lock import global_compiler_lock
        from numba.core.runtime import rtsys
    except ImportError:
        return None
    if not all(
        callable(getattr(owner, name, None))
        for owner, name in (
            (FunctionCache, "_load_overload"),
            (FunctionCache, "_guard_against_spurious_io_errors"),
            (CompileResultCacheImpl, "reduce"),
            (CompileResultCacheImpl, "rebuild"),
            (rtsys, "initialize"),
            (JITCPUCodegen, "unserialize_library"),
            (JITCPUCodegen, "create_library"),
            (CPUCodeLibrary, "enable_object_caching"),
            (CPUCodeLibrary, "_set_compiled_object"),
            (CPUCodeLibrary, "_finalize_final_module"),
            (CPUCodeLibrary, "_get_module_for_linking"),
            (JitEngine, "_load_defined_symbols"),  # (which fills _defined_symbols)
        )
    ):
        return None

    class _KernelCacheImpl(CompileResultCacheImpl):
        def reduce(self, cres: Any) -> Any:
            payload = super().reduce(cres)
            try:
                # numba's entry starts with its library: (name, "object", (object
                # code, the module's bitcode)) for the JIT's
                _, kind, data = payload[0]
                symbols = _module_symbols(data[1]) if kind == "object" else None
            except Exception:  # laid out otherwise: none recorded, so loads set up
                symbols = None
            return (payload, symbols)

        def rebuild(self, target_context: Any, entry: Any) -> Any:
            payload, symbols = entry if len(entry) == 2 else (entry, None)
            recorded = isinstance(symbols, tuple) and len(symbols) == 2
            if not (recorded and isinstance(symbols[1], frozenset)):
                # none recorded (or laid out otherwise): set up as numba does (the
                # refresh initialises the runtime first)
                target_context.refresh()
                return super().rebuild(target_context, payload)
            external, defined = symbols
            if not all(map(ll.address_of_symbol, external)):
                # numba's runtime defines its symbols when initialised (20 ms, which a
                # command whose kernels use none of it saves); anything still missing
                # is registered by the refresh numba does before every load
                rtsys.initialize(target_context)
                if not all(map(ll.address_of_symbol, external)):
                    target_context.refresh()
            codegen = target_context.codegen()
            with global_compiler_lock:  # (no other thread's load sees the lambda)
                codegen.unserialize_library = lambda serialized: _library_parsed_when_linked(
                    codegen, serialized, defined
                )
                try:
                    return super().rebuild(target_context, payload)
                finally:
                    del codegen.unserialize_library

    class _KernelCache(FunctionCache):
        _impl_class = _KernelCacheImpl

        def __init__(self, py_func: Any) -> None:
            # numba sets a function's cache up when it is defined (finds its file, checks
            # the directory is writable with a temporary file, hashes the source): for
            # the 150 kernels defined at import, of which a command loads a dozen. Here
            # that waits for the first use of what it sets (see __getattr__).
            self._py_func = py_func
            self._set_up = False

        def __getattr__(self, name: str) -> Any:
            # (called only for what is not set yet)
            if name.startswith("__") or vars(self).get("_set_up", True):
                raise AttributeError(name)
            self._set_up = True
            try:
                FunctionCache.__init__(self, self._py_func)
            except BaseException:
                self._set_up = False  # (raised again on the next use, as numba would)
                raise
            return getattr(self, name)

        def load_overload(self, sig: Any, target_context: Any) -> Any:
            with self._guard_against_spurious_io_errors():
                return self._load_overload(sig, target_context)

    return _KernelCache


# (None: numba's public interface only)
_KernelCache = _lean_cache_class() if _NUMBA_INTERNALS else None


def _compiled(**options: Any) -> Callable[[Callable[..., Any]], Any]:
    """A decorator compiling with ``options``, cached on disk."""
    options = {**_KERNEL_OPTIONS, **options}
    if _KernelCache is None:
        options.pop("_nrt", None)  # (a private option)
        return njit(cache=True, **options)
    compile_function = njit(**options)

    def decorate(function: Callable[..., Any]) -> Any:
        dispatcher = compile_function(function)
        if hasattr(dispatcher, "_cache"):  # (not with NUMBA_DISABLE_JIT: plain Python)
            dispatcher._cache = _KernelCache(dispatcher.py_func)
        return dispatcher

    return decorate


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
        from numba.core.ccallback import CFunc
        from numba.core.sigutils import normalize_signature

        options = dict(_KERNEL_OPTIONS)
        compiled = CFunc(self.function, normalize_signature(self.signature), {}, options)
        compiled._cache = _KernelCache(self.function)
        compiled.compile()
        return compiled


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
    if _KernelCache is None and not numba.config.DISABLE_JIT:
        types = tuple(typeof(a) for a in example)
        return numba.jit(types, cache=True, **function.targetoptions)(function.py_func)
    function(*example)
    overload = getattr(function, "overloads", {}).get(tuple(typeof(a) for a in example))
    return overload.entry_point if overload is not None else function
