"""Subsystems reach each other through narrow ports, not through each other's insides: a scan
of the product code (no module imports another's private names, reads the patrol's ``core``
or asks ``hasattr`` of a subsystem), and the ports themselves without I/O (the session table
cannot be written around; the patrol's accessors are what a subsystem reads)."""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import pytest

from brasidas.messages import SessionClosed, SessionOpened
from platformd.session_table import Session, SessionTable

ROOT = Path(__file__).resolve().parent.parent
PRODUCT = ("brasidas", "platformd", "stationd")
PATROL_OWNER = ROOT / "platformd" / "autonomy" / "patrol.py"
"""The one module that may look into the patrol's core: the actor that owns it."""


@functools.cache
def product_modules() -> list[tuple[Path, ast.Module]]:
    return [
        (path, ast.parse(path.read_text(), str(path)))
        for package in PRODUCT
        for path in sorted((ROOT / package).rglob("*.py"))
    ]


def where(path: Path, node: ast.AST) -> str:
    return f"{path.relative_to(ROOT)}:{getattr(node, 'lineno', 0)}: {ast.unparse(node)}"


def test_no_module_imports_another_modules_private_names() -> None:
    found = [
        where(path, node)
        for path, tree in product_modules()
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom)
        and (node.module or "").split(".")[0] in PRODUCT
        and any(a.name.startswith("_") and not a.name.startswith("__") for a in node.names)
    ]
    assert found == []


def test_only_the_patrol_actor_reads_the_patrols_core() -> None:
    """Other subsystems read ``route``, ``area``, ``map_revision``, ``state`` and change
    the patrol through its methods (``stop_patrol``, ``update_map``, ...)."""
    found = [
        where(path, node)
        for path, tree in product_modules()
        if path != PATROL_OWNER
        for node in ast.walk(tree)
        if isinstance(node, ast.Attribute)
        and node.attr == "core"
        and ast.unparse(node.value).split(".")[-1] == "patrol"
    ]
    assert found == []


def test_no_subsystem_is_asked_what_it_has() -> None:
    """A port is a typed attribute: ``hasattr`` on a subsystem hides a rename from mypy."""
    found = [
        where(path, node)
        for path, tree in product_modules()
        for node in ast.walk(tree)
        if isinstance(node, ast.Call)
        and isinstance(node.func, ast.Name)
        and node.func.id == "hasattr"
    ]
    assert found == []


def test_the_session_table_is_read_only_but_through_open_and_close() -> None:
    announced: list[SessionOpened | SessionClosed] = []
    table = SessionTable(announce=announced.append)
    session = Session("token-1", "station-1", "127.0.0.1", None, 0.0, 0.0)
    with pytest.raises(TypeError):
        table.sessions["token-1"] = session  # type: ignore[index]
    assert announced == []
    assert len(table) == 0
    table.open(session)
    assert table.sessions == {"token-1": session}
    assert table.get("token-1") is session
    assert table.close("token-1", "timeout") is session
    assert [type(event) for event in announced] == [SessionOpened, SessionClosed]
    assert dict(table.sessions) == {}
