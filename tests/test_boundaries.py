"""Architecture rules of DESIGN.md section 2, enforced on the source tree."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def imported_modules(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


def sources(package: str) -> list[Path]:
    return sorted((ROOT / package).rglob("*.py"))


def test_hal_never_imports_the_runtime() -> None:
    offenders = {
        str(p.relative_to(ROOT)): sorted(m for m in imported_modules(p) if m.split(".")[0] == "daror_runtime")
        for p in sources("hal")
    }
    assert {k: v for k, v in offenders.items() if v} == {}


def test_only_hal_canopen_talks_can() -> None:
    offenders = []
    for package in ("hal", "daror_runtime"):
        for p in sources(package):
            if "canopen" in p.relative_to(ROOT).parts[1:2]:
                continue
            if any(m.split(".")[0] in {"can", "canopen"} for m in imported_modules(p)):
                offenders.append(str(p.relative_to(ROOT)))
    assert offenders == []


@pytest.mark.parametrize("package", ["daror_runtime/models", "daror_runtime/data"])
def test_modelling_code_never_reads_the_simulation(package: str) -> None:
    """Models learn only from measured data: no scenario, no simulator in the modelling code."""
    offenders = [
        str(p.relative_to(ROOT)) for p in sources(package) if any(m.startswith("hal.sim") for m in imported_modules(p))
    ]
    assert offenders == []


def test_no_print_in_library_code() -> None:
    offenders = []
    for package in ("hal", "daror_runtime"):
        for p in sources(package):
            for node in ast.walk(ast.parse(p.read_text(encoding="utf-8"))):
                if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "print":
                    offenders.append(f"{p.relative_to(ROOT)}:{node.lineno}")
    assert offenders == []


def test_no_bare_assert_in_library_code() -> None:
    offenders = [
        f"{p.relative_to(ROOT)}:{node.lineno}"
        for package in ("hal", "daror_runtime")
        for p in sources(package)
        for node in ast.walk(ast.parse(p.read_text(encoding="utf-8")))
        if isinstance(node, ast.Assert)
    ]
    assert offenders == []
