"""How kernels load from the disk cache: without numba's set-up for compiling, unless
a kernel needs a symbol that only that set-up defines; numba's own cache and public
interface where asked, with a numba other than the one tested, or where its internals
are not what mavest expects."""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
from pathlib import Path

import pytest

from mavest import _jit

# (what the rest of this module tests is how numba's internals are used)
lean = pytest.mark.skipif(_jit._KernelCache is None, reason="numba's public interface only")

KERNELS = """
import math

import numpy as np

from mavest._jit import kernel


@kernel
def roots(n):
    out = np.empty(n)  # allocated by numba's runtime (NRT)
    for i in range(n):
        out[i] = math.sqrt(i)
    return out
"""

PROBE = """
import sys

import tiny_kernels

print(tiny_kernels.roots(5).sum(), "numba.np.arraymath" in sys.modules)
"""


def _probe(directory: Path) -> tuple[str, bool]:
    """The kernel's result in a fresh process, and whether numba's compiler was set up."""
    env = dict(os.environ, MAVEST_CACHE_DIR=str(directory / "cache"), PYTHONPATH=str(directory))
    out = subprocess.run(
        [sys.executable, "-c", PROBE], env=env, capture_output=True, text=True, check=True
    ).stdout.split()
    return out[0], out[1] == "True"


@lean
def test_a_cached_kernel_loads_without_numbas_set_up_unless_a_symbol_is_missing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "tiny_kernels.py").write_text(KERNELS)
    compiled, set_up = _probe(tmp_path)  # compiles, and caches
    assert set_up and float(compiled) == pytest.approx(sum(i**0.5 for i in range(5)))
    assert _probe(tmp_path) == (compiled, False)

    (entry_file,) = (tmp_path / "cache").rglob("*.nbc")
    monkeypatch.syspath_prepend(str(tmp_path))  # (the entry names the kernel's module)
    payload, (external, defined) = pickle.loads(entry_file.read_bytes())
    assert any(name.startswith("NRT_") for name in external), external
    assert any("roots" in name for name in defined), defined
    # a symbol the kernel would need and nothing has defined yet: set up first
    doctored = (payload, ((*external, "mavest_no_such_symbol"), defined))
    entry_file.write_bytes(pickle.dumps(doctored))
    assert _probe(tmp_path) == (compiled, True)
    # an entry without the symbols (numba's own), or with the external ones only (an
    # earlier mavest's): set up first, as numba does
    for entry in (payload, (payload, external), (payload, ())):
        entry_file.write_bytes(pickle.dumps(entry))
        assert _probe(tmp_path) == (compiled, True)


LINKED_KERNELS = """
import numpy as np

from mavest._jit import inplace_kernel


@inplace_kernel
def halve_into(v, out):
    for i in range(v.shape[0]):
        out[i] = 0.5 * v[i]
"""

LINKED_PROBE = """
import numpy as np
from numba import njit
from numba.core.runtime import rtsys

import linked_kernels

out = np.empty(3)
linked_kernels.halve_into(np.arange(3.0), out)
runtime_before = rtsys._init


@njit  # (not cached: compiled here, calling the kernel loaded from the cache)
def halves(n):
    out = np.empty(n)
    linked_kernels.halve_into(np.arange(n) * 1.0, out)
    return out


print(out.sum(), runtime_before, halves(4).sum())
"""


@lean
def test_a_kernel_loaded_from_the_cache_links_into_code_compiled_later(tmp_path: Path) -> None:
    """Its module's bitcode, not parsed when it loads, is when a new kernel calls it; a
    kernel without numba's runtime loads without initialising it."""
    (tmp_path / "linked_kernels.py").write_text(LINKED_KERNELS)
    env = dict(os.environ, MAVEST_CACHE_DIR=str(tmp_path / "cache"), PYTHONPATH=str(tmp_path))
    command = [sys.executable, "-c", LINKED_PROBE]
    for _ in range(2):  # compiled and cached, then loaded from the cache
        out = subprocess.run(command, env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["1.5", "False", "3.0"]


@lean
def test_a_kernels_cache_is_set_up_when_first_used() -> None:
    assert _jit._KernelCache is not None

    def double(x: float) -> float:
        return 2 * x

    cache = _jit._KernelCache(double)
    assert "_impl" not in vars(cache)
    assert Path(cache.cache_path).is_relative_to(_jit.CACHE_DIRECTORY)
    assert "_impl" in vars(cache)


def test_numbas_own_cache_where_its_internals_are_not_as_expected(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from numba.core.caching import Cache, FunctionCache

    from mavest import _numba_cache

    monkeypatch.delattr(Cache, "_load_overload")
    assert _numba_cache.lean_cache_class() is None
    monkeypatch.setattr(_jit, "_KernelCache", None)

    def double(x: float) -> float:
        return 2 * x

    assert type(_jit._compiled()(double)._cache) is FunctionCache


REPLAY = """
import sys

from mavest.cli import main

main(["replay", sys.argv[1], "--out-tlog", sys.argv[2], "-q"])
from numba.core.runtime import rtsys

print(*(name in sys.modules for name in ("numba.np.arraymath", "scipy.linalg")), rtsys._init)
"""


@lean
def test_a_replay_starts_without_numbas_compiler_or_scipy(tmp_path: Path) -> None:
    """Nor numba's runtime: the kernels a replay loads are all compiled without it."""
    from mavest.sim.vehicle import AUTOPILOTS, write_flight_tlog

    flight = tmp_path / "flight.tlog"
    write_flight_tlog(flight, 1.0, 1000.0, AUTOPILOTS["ardupilot"], seed=1)
    command = [sys.executable, "-c", REPLAY, str(flight), str(tmp_path / "ours.tlog")]
    subprocess.run(command, capture_output=True, check=True)  # (compiles if not cached yet)
    out = subprocess.run(command, capture_output=True, text=True, check=True).stdout
    assert out.splitlines()[-1] == "False False False", out


PUBLIC_PROBE = """
import tiny_kernels
from mavest import _jit

roots = tiny_kernels.roots
total = roots(5).sum()
hits = sum(roots.stats.cache_hits.values())
print(total, hits, type(roots._cache).__name__, _jit._KernelCache)
"""


def test_numbas_public_interface_when_asked(tmp_path: Path) -> None:
    """``MAVEST_NUMBA_PUBLIC=1``: numba's own cache, which the next process loads from."""
    (tmp_path / "tiny_kernels.py").write_text(KERNELS)
    env = dict(
        os.environ,
        MAVEST_NUMBA_PUBLIC="1",
        MAVEST_CACHE_DIR=str(tmp_path / "cache"),
        PYTHONPATH=str(tmp_path),
    )
    command = [sys.executable, "-c", PUBLIC_PROBE]
    runs = [
        subprocess.run(command, env=env, capture_output=True, text=True, check=True).stdout.split()
        for _ in range(2)
    ]
    assert runs[0][2:] == runs[1][2:] == ["FunctionCache", "None"]
    assert [run[1] for run in runs] == ["0", "1"]  # compiled, then loaded
    assert runs[0][0] == runs[1][0]


@pytest.mark.parametrize(
    ("version", "public", "internals"),
    [
        (f"{_jit.TESTED_NUMBA}.0", None, True),
        (f"{_jit.TESTED_NUMBA}.5", "0", True),
        (f"{_jit.TESTED_NUMBA}.0", "1", False),
        ("0.99.0", None, False),
        ("0.6", None, False),
    ],
)
def test_numbas_internals_only_with_the_tested_numba_unless_told_not_to(
    monkeypatch: pytest.MonkeyPatch, version: str, public: str | None, internals: bool
) -> None:
    import numba

    monkeypatch.setattr(numba, "__version__", version)
    if public is None:
        monkeypatch.delenv("MAVEST_NUMBA_PUBLIC", raising=False)
    else:
        monkeypatch.setenv("MAVEST_NUMBA_PUBLIC", public)
    assert _jit._numba_internals_wanted() is internals


def test_numba_is_bounded_to_the_version_tested() -> None:
    """pyproject.toml's bound and the version whose internals mavest uses agree, and the
    numba the tests run on is that one (else the tests would run on its public interface
    only, whatever they were meant to check)."""
    import numba

    try:
        import tomllib
    except ImportError:  # Python 3.10
        import tomli as tomllib

    pyproject = Path(__file__).parents[1] / "pyproject.toml"
    requirements = tomllib.loads(pyproject.read_text())["project"]["dependencies"]
    (bound,) = [r for r in requirements if r.startswith("numba")]
    major, minor = map(int, _jit.TESTED_NUMBA.split("."))
    assert f"<{major}.{minor + 1}" in bound.split(","), bound
    assert numba.__version__.startswith(_jit.TESTED_NUMBA + ".")
