"""The line between the motion side and the task side of ``motiond.runtime`` (docs/daemon.md).

The motion side (``MotionCore``) is to move into a process of its own; that is only possible while the
task side uses nothing of it but the interface its module docstring lists. These tests read the task
side's modules and check it: every name they use on the motion core is one the docstring names, none
is private, and no task module touches the planner or the cycle runner itself.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import motiond.runtime.motion as motion_module

RUNTIME = Path(motion_module.__file__).resolve().parent
TASK_MODULES = ("machine", "jobs", "run_from_line", "service", "status")


def _motion_names(tree: ast.AST) -> set[str]:
    """Attributes read or written on ``<anything>.motion`` or on a local named ``motion``."""
    found = set()
    for node in ast.walk(tree):
        if not isinstance(node, ast.Attribute):
            continue
        v = node.value
        if (isinstance(v, ast.Attribute) and v.attr == "motion") or (
                isinstance(v, ast.Name) and v.id == "motion"):
            found.add(node.attr)
    return found


def _self_names(tree: ast.AST) -> set[str]:
    return {node.attr for node in ast.walk(tree) if isinstance(node, ast.Attribute)
            and isinstance(node.value, ast.Name) and node.value.id == "self"}


def test_the_task_side_uses_only_the_documented_interface() -> None:
    doc = motion_module.__doc__ or ""
    documented = set(re.findall(r"``(\w+)``|MotionCore\.(\w+)`", doc))
    documented_names = {a or b for a, b in documented}
    used: dict[str, set[str]] = {}
    for name in TASK_MODULES:
        tree = ast.parse((RUNTIME / f"{name}.py").read_text(encoding="utf-8"))
        for attr in _motion_names(tree):
            used.setdefault(attr, set()).add(name)
    assert used, "the task side uses the motion core somewhere (the parse found nothing)"
    private = {a: m for a, m in used.items() if a.startswith("_")}
    assert not private, f"task modules reach into the motion core's private state: {private}"
    undocumented = {a: sorted(m) for a, m in used.items() if a not in documented_names}
    assert not undocumented, ("task modules use motion core names its docstring does not list as "
                              f"interface: {undocumented}")
    for a in used:  # and each one exists
        assert hasattr(motion_module.MotionCore, a) or a in _instance_attributes(), a


def _instance_attributes() -> set[str]:
    import motiond.runtime.cycle as cycle_module

    tree = ast.parse(Path(cycle_module.__file__).read_text(encoding="utf-8"))
    return _self_names(tree)


def test_no_task_module_touches_the_planner_or_the_runner() -> None:
    for name in TASK_MODULES:
        tree = ast.parse((RUNTIME / f"{name}.py").read_text(encoding="utf-8"))
        touched = _self_names(tree) & {"planner", "runner", "_cmdq", "_calls"}
        assert not touched, f"motiond/runtime/{name}.py uses self.{touched}: the motion side's own"
