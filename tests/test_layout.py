"""The code base reads top-down: no import cycle among the project's modules, and every command the documents
give exists with the options they use."""

from __future__ import annotations

import ast
import contextlib
import importlib
import io
import re
from collections import defaultdict
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("nrsfm", "prn", "baselines", "benchmarks")
DOCUMENTS = ("README.md", "benchmarks/README.md")


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for f in (ROOT / pkg).rglob("*.py"):
            name = ".".join(f.relative_to(ROOT).with_suffix("").parts)
            out[name.removesuffix(".__init__")] = f
    return out


def import_graph() -> dict[str, set[str]]:
    """Module -> the project's modules it imports, at any depth of its code (a function's lazy import counts too);
    a module's own parent packages are left out (a package's ``__init__`` gathers its submodules)."""
    mods = _modules()
    graph: dict[str, set[str]] = defaultdict(set)
    for name, path in mods.items():
        is_package = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = name.split(".")
                    parts = parts[: len(parts) - node.level + (1 if is_package else 0)]
                    base = ".".join(parts + ([base] if base else []))
                targets = [base] + [f"{base}.{a.name}" for a in node.names]
            else:
                continue
            for target in targets:
                while target and target not in mods:
                    target = target.rpartition(".")[0]
                if target and target != name and not name.startswith(target + "."):
                    graph[name].add(target)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(set(graph) | {w for ws in graph.values() for w in ws}):
        if v not in index:
            visit(v)
    return found


def test_no_import_cycle_among_the_project_modules():
    assert cycles(import_graph()) == []


def test_the_cycle_finder_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def documented_commands() -> list[tuple[str, str, list[str]]]:
    """(document, module, options) of every ``python -m MODULE ...`` command in the documents' code, the
    ``--option`` words of each (placeholders such as ``benchmarks.<table>`` or ``studies.NAME`` left out)."""
    out = []
    for doc in DOCUMENTS:
        path = ROOT / doc
        if not path.exists():
            continue
        text = path.read_text()
        code = "\n".join(re.findall(r"```[a-z]*\n(.*?)```", text, re.S) + re.findall(r"`([^`\n]+)`", text))
        for line in code.splitlines():
            for m in re.finditer(r"python -m ([\w.]+)([^|;&#]*)", line):
                module = m.group(1)
                if module.split(".")[0] in PACKAGES and re.fullmatch(r"[a-z_][a-z0-9_]*(\.[a-z_][a-z0-9_]*)*", module):
                    out.append((doc, module, re.findall(r"(--[\w-]+)", m.group(2))))
    return out


def _help(module: str) -> str:
    mod = importlib.import_module(module)
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), pytest.raises(SystemExit) as exit_info:
        mod.main(["--help"])
    assert exit_info.value.code == 0, module
    return buf.getvalue()


def test_every_documented_command_exists_and_accepts_its_options():
    commands = documented_commands()
    assert len({m for _, m, _ in commands}) >= 8, "expected the documents to give the table commands"
    helps: dict[str, str] = {}
    for doc, module, options in commands:
        if module not in helps:
            helps[module] = _help(module)
        unknown = [o for o in options if not re.search(rf"(?<![\w-]){re.escape(o)}(?![\w-])", helps[module])]
        assert not unknown, f"{doc}: python -m {module} does not accept {unknown}"


def test_every_study_is_listed_with_what_it_backs_and_every_listed_study_exists():
    text = (ROOT / "benchmarks" / "README.md").read_text().split("## Studies behind the defaults", 1)[1]
    listed = set(re.findall(r"^\| `(\w+)` \| (?=\S)", text, re.M))
    present = {p.stem for p in (ROOT / "benchmarks" / "studies").glob("*.py") if p.stem != "__init__"}
    assert listed == present
