"""The shape of the evaluation, CLI and viz packages: no import cycles, no unexplained giants.

Module-level imports only (imports inside functions are how a lower module reaches an optional
or heavy one on demand, and cannot form a cycle at import time).
"""

from __future__ import annotations

import ast
from pathlib import Path

import graffmatch

PACKAGE = Path(graffmatch.__file__).parent
CHECKED = ("evaluation", "cli", "viz")
MAX_LINES = 500


def _module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for sub in CHECKED for p in sorted((PACKAGE / sub).rglob("*.py"))}


def _top_level_imports(path: Path, known: set[str]) -> set[str]:
    out: set[str] = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        else:
            continue
        out |= {n for n in names if n in known}
    return out


def test_no_import_cycles() -> None:
    mods = _modules()
    graph = {m: _top_level_imports(p, set(mods)) - {m} for m, p in mods.items()}
    # a package's __init__ importing its own submodules is not a cycle of concepts
    for m in graph:
        graph[m] = {d for d in graph[m] if not d.startswith(m + ".")}
    state: dict[str, int] = {}
    cycles: list[list[str]] = []

    def visit(m: str, stack: list[str]) -> None:
        state[m] = 1
        for d in sorted(graph[m]):
            if state.get(d) == 1:
                cycles.append([*stack[stack.index(d) :], d] if d in stack else [m, d])
            elif d not in state:
                visit(d, [*stack, d])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert not cycles, f"import cycles: {cycles}"
    # the cycle this layout removed stays removed
    assert "graffmatch.evaluation.runner" not in graph["graffmatch.evaluation.report"]


def test_large_modules_say_why() -> None:
    unexplained = []
    for name, path in _modules().items():
        n = len(path.read_text().splitlines())
        doc = ast.get_docstring(ast.parse(path.read_text())) or ""
        if n > MAX_LINES and "500 lines" not in doc:
            unexplained.append(f"{name} ({n} lines)")
    assert not unexplained, f"over {MAX_LINES} lines without a reason in the docstring"


def test_every_module_past_600_lines_says_why() -> None:
    """The whole package, not only the CHECKED layers: a module past 600 lines says in its
    docstring why it is not split by concept."""
    unexplained = []
    for path in sorted(PACKAGE.rglob("*.py")):
        text = path.read_text()
        doc = ast.get_docstring(ast.parse(text)) or ""
        if len(text.splitlines()) > 600 and not ("500 lines" in doc or "600 lines" in doc):
            unexplained.append(f"{path.relative_to(PACKAGE)} ({len(text.splitlines())} lines)")
    assert not unexplained, f"over 600 lines without a reason in the docstring: {unexplained}"


def test_old_import_paths_still_work() -> None:
    from graffmatch.cli.report_views import write_report_views
    from graffmatch.evaluation import expectations, figures, places, records, tables, tasks
    from graffmatch.evaluation import loop_closure_dataset as lcd
    from graffmatch.evaluation.loop_closures import (
        LoopClosureConfig,
        LoopClosureDataset,
        check_validity,
        plot_dataset_details,
    )
    from graffmatch.evaluation.report import check_expectations, fig_lmr, summarize, table1
    from graffmatch.evaluation.runner import (
        StudyConfig,
        compare_runs,
        execute_task,
        load_records,
        record_path,
    )
    from graffmatch.viz import report_views

    assert summarize is tables.summarize and table1 is tables.table1
    assert check_expectations is expectations.check_expectations and fig_lmr is figures.fig_lmr
    assert StudyConfig is records.StudyConfig and load_records is records.load_records
    assert record_path is records.record_path and execute_task is tasks.execute_task
    assert LoopClosureConfig is places.LoopClosureConfig and check_validity is places.check_validity
    assert LoopClosureDataset is lcd.LoopClosureDataset
    assert plot_dataset_details is figures.plot_dataset_details
    assert write_report_views is report_views.write_report_views
    assert callable(compare_runs)
