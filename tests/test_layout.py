"""The state record's scratch buffers are owned per module: a ``w_<module>_…`` field is
read and written by mavest.estimator.<module> alone (layout.py's scratch block), so that
what a kernel's callee may overwrite can be seen: its own module's scratch."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

import mavest
from mavest.estimator.layout import SCRATCH_OWNERS, STATE_DTYPE

PACKAGE = Path(mavest.__file__).parent
ESTIMATOR = PACKAGE / "estimator"
LAYOUT = ESTIMATOR / "layout.py"

SCRATCH_FIELDS = frozenset(name for name in STATE_DTYPE.names if name.startswith("w_"))


def _owners(field: str) -> list[str]:
    return [owner for owner in SCRATCH_OWNERS if field.startswith(f"w_{owner}_")]


def scratch_owner(field: str) -> str | None:
    """The module a scratch field belongs to (its ``w_<owner>_`` prefix), None if none."""
    owners = _owners(field)
    return owners[0] if len(owners) == 1 else None


def scratch_named(source: str, is_python: bool) -> set[str]:
    """The scratch fields a module's code names: as an attribute (``s.w_x``) or a
    string (``s["w_x"]``); in a Cython source, anywhere."""
    if not is_python:
        return set(re.findall(r"\bw_\w+\b", source)) & SCRATCH_FIELDS
    named = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Attribute):
            named.add(node.attr)
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            named.add(node.value)
    return named & SCRATCH_FIELDS


def foreign_scratch(source: str, module: str, is_python: bool = True) -> list[str]:
    """The scratch fields ``module``'s source names that another module owns."""
    return sorted(
        field for field in scratch_named(source, is_python) if scratch_owner(field) != module
    )


def _sources() -> list[Path]:
    return sorted(
        path
        for pattern in ("*.py", "*.pyx")
        for path in PACKAGE.rglob(pattern)
        if path != LAYOUT and "__pycache__" not in path.parts
    )


def _module_of(path: Path) -> str | None:
    """A scratch owner's name for its own file, None for any other file."""
    if path.parent == ESTIMATOR and path.suffix == ".py" and path.stem in SCRATCH_OWNERS:
        return path.stem
    return None


def test_every_scratch_field_is_named_for_a_module_that_exists() -> None:
    assert SCRATCH_FIELDS
    for field in sorted(SCRATCH_FIELDS):
        assert len(_owners(field)) == 1, f"{field}: not one w_<module>_ prefix"
    for owner in SCRATCH_OWNERS:
        assert (ESTIMATOR / f"{owner}.py").exists(), owner


def test_no_module_touches_another_modules_scratch() -> None:
    foreign = {}
    for path in _sources():
        found = foreign_scratch(path.read_text(), _module_of(path), path.suffix == ".py")
        if found:
            foreign[str(path.relative_to(PACKAGE.parent))] = found
    assert not foreign, f"scratch of another module: {foreign}"


def test_every_scratch_field_is_used_by_its_owner() -> None:
    """No buffer left behind: each costs every state record (and its copies) its size."""
    used = set()
    for owner in SCRATCH_OWNERS:
        used |= scratch_named((ESTIMATOR / f"{owner}.py").read_text(), True)
    assert sorted(SCRATCH_FIELDS - used) == []


@pytest.mark.parametrize(
    ("source", "module", "found"),
    [
        ("def f(s):\n    s.w_heading_dx[0] = 1.0\n", "heading", []),
        ("def f(s):\n    s.w_frames_R[0, 0] = 1.0\n", "heading", ["w_frames_R"]),
        ("def f(s):\n    return s['w_gravity_update_K']\n", "rest", ["w_gravity_update_K"]),
        ("def f(s):\n    return s.w_gravity_update_K\n", None, ["w_gravity_update_K"]),
        ("cdef double x = s.w_rest_dx[0]\n", "online", ["w_rest_dx"]),
    ],
)
def test_the_scan_sees_a_foreign_buffer(source: str, module: str | None, found: list) -> None:
    assert foreign_scratch(source, module, not source.startswith("cdef")) == found
