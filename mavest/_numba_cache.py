"""Loading mavest's compiled kernels from numba's disk cache without numba's set-up
for compiling: numba's internals, used only with the numba version they were
tested with (``mavest._jit.TESTED_NUMBA``, to which pyproject.toml bounds numba).

Everything here is one optimisation of start-up, about half a second of every
command (:func:`lean_cache_class`). With any other numba, or
``MAVEST_NUMBA_PUBLIC=1``, :mod:`mavest._jit` does not import this module and
the kernels are numba's plain ``njit(cache=True)``: slower to start, the same
results (CI runs the kernels, the filter's two paths and the golden outputs that way).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from numba import typeof


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


def lean_cache_class() -> type | None:
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


def cache_kernels(compile_function: Callable[..., Any], cache_class: type) -> Callable[..., Any]:
    """A decorator compiling with ``compile_function`` (numba's ``njit`` with options,
    no cache) whose kernels keep their entries in ``cache_class``."""

    def decorate(function: Callable[..., Any]) -> Any:
        dispatcher = compile_function(function)
        if hasattr(dispatcher, "_cache"):  # (not with NUMBA_DISABLE_JIT: plain Python)
            dispatcher._cache = cache_class(dispatcher.py_func)
        return dispatcher

    return decorate


def compile_callback(
    function: Callable[..., Any], signature: Any, options: dict[str, Any], cache_class: type
) -> Any:
    """numba's ``cfunc(signature, cache=True)``, its entry in ``cache_class``."""
    from numba.core.ccallback import CFunc
    from numba.core.sigutils import normalize_signature

    compiled = CFunc(function, normalize_signature(signature), {}, dict(options))
    compiled._cache = cache_class(function)
    compiled.compile()
    return compiled


def entry_point(function: Any, *example: Any) -> Callable[..., Any]:
    """The compiled entry point of ``function``'s overload for the types of
    ``example`` (compiled or loaded by calling it once with them), which skips
    numba's type dispatch; ``function`` itself where there is none (NUMBA_DISABLE_JIT)."""
    function(*example)
    overload = getattr(function, "overloads", {}).get(tuple(typeof(a) for a in example))
    return overload.entry_point if overload is not None else function
