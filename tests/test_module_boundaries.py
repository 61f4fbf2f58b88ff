"""Each module keeps its underscore names to itself: no module of mavest reads, writes or
imports another's (an attribute of anything but ``self``/``cls``, a ``from … import _x``
of another module, a private module outside its package). What one module needs of
another is a public, documented name there, which the owner uses too, so that each rule
is written once. The few exceptions are listed below, each with its reason."""

from __future__ import annotations

import ast
from pathlib import Path

import mavest

PACKAGE = Path(mavest.__file__).parent

# pymavlink's message objects keep their header, type name, packet, payload, CRC and
# signature flag under these names (its own style: it has getters for them, no setters).
# mavest reads them on the hot path, where get_type()/get_header() would cost a call
# each, and sets them when it builds messages from a datagram itself
# (wire.decode_datagram), which pymavlink offers no other way to do.
PYMAVLINK_MESSAGE_FIELDS = frozenset(("_header", "_type", "_msgbuf", "_payload", "_crc", "_signed"))

# Modules exempt as a whole.
EXEMPT_MODULES = {
    # numba's cache and code-generation internals, which mavest uses to start faster,
    # kept to the numba version tested (mavest._jit.TESTED_NUMBA)
    "mavest/_numba_cache.py": "numba's internals",
}

# (module, name): a module touching an underscore name of an object it does not own.
ALLOWED: dict[tuple[str, str], str] = {
    ("mavest/launch.py", "_exit"): "os._exit, Python's documented exit without teardown",
    ("mavest/launch.py", "_run_exitfuncs"): (
        "atexit's runner of the exit handlers, which has no public name: run before "
        "os._exit so that Rerun's and logging's still flush; looked up, and where it is "
        "absent the interpreter's own exit"
    ),
}


def _is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def _module_name(relative: Path) -> str:
    parts = list(relative.with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _is_submodule(package: str, name: str) -> bool:
    """Whether ``package.name`` is a module of mavest (source, package or extension)."""
    folder = PACKAGE.parent.joinpath(*package.split("."))
    return (
        (folder / f"{name}.py").exists()
        or (folder / name / "__init__.py").exists()
        or any(folder.glob(f"{name}.*.so"))
        or (folder / f"{name}.pyx").exists()
    )


def _private_module_outside(module: str, importer: str) -> str | None:
    """The first underscore part of ``module`` (a dotted mavest module) whose package
    does not hold ``importer``: a private module imported from outside its package."""
    parts = module.split(".")
    for k, part in enumerate(parts):
        if _is_private(part):
            package = ".".join(parts[:k])
            if not (importer == package or importer.startswith(package + ".")):
                return ".".join(parts[: k + 1])
    return None


def trespasses(source: str, relative: Path) -> list[str]:
    """Where a module's source touches another's underscore names: "line: what"."""
    importer = _module_name(relative)
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Attribute) and _is_private(node.attr):
            receiver = node.value
            if isinstance(receiver, ast.Name) and receiver.id in ("self", "cls"):
                continue
            if node.attr in PYMAVLINK_MESSAGE_FIELDS:
                continue
            found.append(f"{node.lineno}: {ast.unparse(node)}")
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
            # getattr(x, "_y"), setattr, hasattr: the same reach, spelled as a string
            arguments = node.args
            if (
                node.func.id in ("getattr", "setattr", "hasattr", "delattr")
                and len(arguments) > 1
                and isinstance(arguments[1], ast.Constant)
                and isinstance(arguments[1].value, str)
                and _is_private(arguments[1].value)
                and not (isinstance(arguments[0], ast.Name) and arguments[0].id in ("self", "cls"))
            ):
                found.append(f"{node.lineno}: {ast.unparse(node)}")
        elif isinstance(node, ast.ImportFrom):
            module = node.module or ""
            if node.level:  # relative: resolved against the importer's package
                base = importer.split(".")
                if relative.name != "__init__.py":
                    base = base[:-1]
                base = base[: len(base) - (node.level - 1)]
                module = ".".join([*base, module] if module else base)
            if module.split(".")[0] != "mavest":
                continue
            outside = _private_module_outside(module, importer)
            if outside is not None:
                found.append(f"{node.lineno}: from {module} import … ({outside} is private)")
            for alias in node.names:
                if not _is_private(alias.name):
                    continue
                if _is_submodule(module, alias.name) and (
                    importer == module or importer.startswith(module + ".")
                ):
                    continue  # a private module of the importer's own package
                found.append(f"{node.lineno}: from {module} import {alias.name}")
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] != "mavest":
                    continue
                outside = _private_module_outside(alias.name, importer)
                if outside is not None:
                    found.append(f"{node.lineno}: import {alias.name} ({outside} is private)")
    return sorted(found, key=lambda finding: int(finding.split(":")[0]))


def _names(finding: str, name: str) -> bool:
    """Whether a finding is a reach for ``name`` (as an attribute, an import, a string)."""
    return f".{name}" in finding or f"import {name}" in finding or f"'{name}'" in finding


def _allowed(relative: str, finding: str) -> bool:
    return any(module == relative and _names(finding, name) for module, name in ALLOWED)


def test_no_module_touches_another_modules_underscore_names() -> None:
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        relative = path.relative_to(PACKAGE.parent)
        if relative.as_posix() in EXEMPT_MODULES:
            continue
        for finding in trespasses(path.read_text(), relative):
            if not _allowed(relative.as_posix(), finding):
                found.append(f"{relative.as_posix()}:{finding}")
    assert not found, "underscore names of other modules:\n" + "\n".join(found)


def test_every_exception_is_still_needed() -> None:
    """An allowance nothing uses any more goes: the list stays as short as the code lets."""
    for module in EXEMPT_MODULES:
        assert (PACKAGE.parent / module).exists(), module
    for module, name in ALLOWED:
        findings = trespasses((PACKAGE.parent / module).read_text(), Path(module))
        assert any(_names(f, name) for f in findings), (module, name)


def test_the_scan_sees_each_kind_of_reach() -> None:
    """The scan itself, on the ways one module can reach into another."""
    here = Path("mavest/service/example.py")
    reaches = {
        "pipeline._record_us = 1": 1,  # a write
        "x = self.pipeline._encoder(1)": 1,  # through an attribute of self
        "x = estimator._state.copy()": 1,
        "x = getattr(encoder, '_mav')": 1,
        "from mavest.service.pipeline import _reject, MAX_GYRO": 1,
        "from .pipeline import _reject": 1,  # relative
        "from mavest.estimator import _online": 1,  # a private module, another package
        "import mavest.estimator._online": 1,
        "from mavest.estimator._online import Estimate": 1,
        # the module's own, pymavlink's message fields, a private module of mavest's
        # top package, dunder names
        "self._x = cls._y = 1": 0,
        "h = message._header; t = message._type": 0,
        "from mavest._jit import exact_kernel": 0,
        "from mavest import __version__": 0,
        "x = getattr(self, '_cache', None)": 0,
    }
    for source, count in reaches.items():
        assert len(trespasses(source, here)) == count, source
    # a package's private module, imported within that package
    own = Path("mavest/estimator/online.py")
    assert trespasses("from mavest.estimator._online import Estimate", own) == []
