"""The rooms of the package and who may import whom (docs/architecture.md).

The sender and the receiver run on different machines: neither may import the other, and the receiver
(which runs on the drone) does not import the simulator or the demo either. Two checks: which ``ipt``
modules importing a module really loads (a subprocess), and a static scan of every import statement of
every module (function-level ones included, which the first check cannot see until they run). The scan
also finds import cycles."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest


def _loaded_ipt_modules(module: str) -> list[str]:
    code = f"import json, sys, {module}; print(json.dumps(sorted(m for m in sys.modules if m.startswith('ipt'))))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60)
    loaded: list[str] = json.loads(out.stdout)
    return loaded


@pytest.mark.parametrize(
    "module",
    [
        "ipt.receiver.cli",
        "ipt.receiver.daemon",
        "ipt.receiver.core.pipeline",
        "ipt.receiver.replay",
        "ipt.receiver.outputs.ros.dds",
        "ipt.receiver.outputs.ros.record",
    ],
)
def test_receiver_does_not_import_the_sender(module: str) -> None:
    loaded = _loaded_ipt_modules(module)
    assert module in loaded
    assert [m for m in loaded if m.startswith("ipt.sender")] == []


@pytest.mark.parametrize("module", ["ipt.sender.cli", "ipt.sender.server", "ipt.sender.modulator"])
def test_sender_does_not_import_the_receiver(module: str) -> None:
    loaded = _loaded_ipt_modules(module)
    assert module in loaded
    assert [m for m in loaded if m.startswith("ipt.receiver")] == []


# --- the static scan: every import statement of every module, function-level ones included -----------

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "ipt"

ALLOWED_RECEIVER_TO_SIM: set[tuple[str, str]] = set()
"""Edges from the receiver to the simulator allowed: none. ``ipt-receiver run --source sim`` finds the simulated
camera as an entry point (``ipt.capture_sources`` in pyproject.toml) and hands it to the daemon."""


@dataclass(frozen=True)
class ImportEdge:
    """One import statement (or ``importlib.import_module("ipt...")`` call) of one module."""

    source: str
    """The importing module, e.g. ``ipt.receiver.daemon``."""
    target: str
    """The module imported: ``from ipt.a import b`` is ``ipt.a.b`` when that is a module, else ``ipt.a``."""
    line: int
    module_level: bool
    """Run when the module is imported: not inside a function, not under ``if TYPE_CHECKING:``."""

    def __str__(self) -> str:
        kind = "module level" if self.module_level else "in a function or TYPE_CHECKING"
        return f"{self.source}:{self.line} imports {self.target} ({kind})"


def module_name(path: Path, root: Path) -> str:
    """``ipt/receiver/capture.py`` → ``ipt.receiver.capture``; a package's ``__init__.py`` → the package."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def scan_imports(source: str, module: str, is_package: bool, known: set[str]) -> list[ImportEdge]:
    """Every import of ``ipt`` modules in ``source`` (the text of ``module``): ``import``, ``from ... import``
    (relative ones resolved), and ``importlib.import_module`` / ``__import__`` with a literal name, at any depth."""
    edges: list[ImportEdge] = []
    package = module if is_package else module.rpartition(".")[0]

    def resolve(base: str, names: list[str]) -> list[str]:
        out = [f"{base}.{n}" for n in names if f"{base}.{n}" in known]
        return out if len(out) == len(names) else [*out, base]

    def add(targets: list[str], node: ast.AST, runtime: bool) -> None:
        for target in targets:
            if target == "ipt" or target.startswith("ipt."):
                edges.append(ImportEdge(module, target, getattr(node, "lineno", 0), runtime))

    def visit(node: ast.AST, runtime: bool) -> None:
        if isinstance(node, ast.Import):
            add([a.name for a in node.names], node, runtime)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1])
                base = f"{base}.{node.module}" if node.module else base
            else:
                base = node.module or ""
            add(resolve(base, [a.name for a in node.names]), node, runtime)
        elif isinstance(node, ast.Call):
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else func.id if isinstance(func, ast.Name) else ""
            if name in ("import_module", "__import__") and node.args:
                arg = node.args[0]
                if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
                    add([arg.value], node, runtime)
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
            runtime = False  # runs when called, not when the module is imported
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            for child in node.body:
                visit(child, False)
            for child in node.orelse:
                visit(child, runtime)
            visit(node.test, runtime)
            return
        for child in ast.iter_child_nodes(node):
            visit(child, runtime)

    visit(ast.parse(source), True)
    return edges


def all_imports(root: Path = PACKAGE) -> list[ImportEdge]:
    """The import edges of every ``.py`` file of the package at ``root``."""
    files = sorted(root.rglob("*.py"))
    known = {module_name(p, root.parent) for p in files}
    edges = []
    for path in files:
        name = module_name(path, root.parent)
        edges += scan_imports(path.read_text(encoding="utf-8"), name, path.name == "__init__.py", known)
    return edges


def _under(module: str, *packages: str) -> bool:
    return any(module == p or module.startswith(p + ".") for p in packages)


def import_cycles(edges: list[ImportEdge]) -> list[list[str]]:
    """The strongly connected components (more than one module, or a module importing itself) of the graph
    of module-level imports: each is an import cycle."""
    graph: dict[str, set[str]] = {}
    for e in edges:
        if e.module_level:
            graph.setdefault(e.source, set()).add(e.target)
            graph.setdefault(e.target, set())
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def strong(v: str) -> None:  # Tarjan's algorithm
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1 or v in graph[v]:
                cycles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            strong(v)
    return cycles


def test_the_scan_sees_every_kind_of_import() -> None:
    """The scanner itself: an import in a function, under TYPE_CHECKING, a relative one and an
    ``importlib.import_module`` string are all found (so a clean scan means something)."""
    text = (
        "from __future__ import annotations\n"
        "import importlib\n"
        "from typing import TYPE_CHECKING\n"
        "from . import b\n"
        "from .c import thing\n"
        "if TYPE_CHECKING:\n"
        "    from ipt.sim.arena import SimulatedArena\n"
        "def f():\n"
        "    import ipt.sender.content\n"
        "    return importlib.import_module('ipt.sim.render')\n"
    )
    known = {"ipt.receiver.a", "ipt.receiver.b", "ipt.receiver.c", "ipt.sim.arena"}
    edges = {(e.target, e.line, e.module_level) for e in scan_imports(text, "ipt.receiver.a", False, known)}
    assert edges == {
        ("ipt.receiver.b", 4, True),
        ("ipt.receiver.c", 5, True),
        ("ipt.sim.arena", 7, False),
        ("ipt.sender.content", 9, False),
        ("ipt.sim.render", 10, False),
    }
    assert import_cycles([ImportEdge("ipt.a", "ipt.b", 1, True), ImportEdge("ipt.b", "ipt.a", 1, True)]) == [
        ["ipt.a", "ipt.b"]
    ]
    assert import_cycles([ImportEdge("ipt.a", "ipt.b", 1, True), ImportEdge("ipt.b", "ipt.a", 1, False)]) == []


def test_the_scan_covers_the_package() -> None:
    edges = all_imports()
    sources = {e.source for e in edges}
    assert {"ipt.receiver.daemon", "ipt.receiver.cli", "ipt.sender.server", "ipt.sim.demo"} <= sources
    # function-level imports are seen too: the receiver's command line imports its capture module inside one
    inside = [e for e in edges if e.source == "ipt.receiver.cli" and not e.module_level]
    assert any(e.target.startswith("ipt.receiver.capture") for e in inside)


def test_the_receiver_imports_neither_the_sender_nor_the_simulator_nor_the_demo() -> None:
    """Statically, every import statement of ``ipt/receiver`` (function-level and TYPE_CHECKING ones
    included), with the one edge of :data:`ALLOWED_RECEIVER_TO_SIM`, which must stay inside a function."""
    bad = [
        str(e)
        for e in all_imports()
        if _under(e.source, "ipt.receiver")
        and _under(e.target, "ipt.sender", "ipt.sim", "ipt.demo")
        and ((e.source, e.target) not in ALLOWED_RECEIVER_TO_SIM or e.module_level)
    ]
    assert bad == []


def test_the_sender_does_not_import_the_receiver_statically() -> None:
    bad = [str(e) for e in all_imports() if _under(e.source, "ipt.sender") and _under(e.target, "ipt.receiver")]
    assert bad == [], "ipt/sender imports the receiver (the sender's half of issue 18 removes it)"


def test_no_import_cycle_among_module_level_imports() -> None:
    """No cycle in the graph of the imports run when a module is imported (module level, outside
    ``if TYPE_CHECKING:``). Imports inside functions run later and may close a loop without harm, so
    they are not counted; a cycle of module-level imports breaks or half-initialises a module depending
    on which side is imported first."""
    assert import_cycles(all_imports()) == []


def test_no_import_cycle_in_the_receiver_counting_function_level_imports() -> None:
    """In the receiver, no cycle even when the imports inside functions are counted (the detector and its
    helper process's module share the C wrapper, :mod:`ipt.receiver.detect.apriltag_c`, instead of each other)."""
    edges = [ImportEdge(e.source, e.target, e.line, True) for e in all_imports() if _under(e.source, "ipt.receiver")]
    assert import_cycles(edges) == []


def _reason_literals(path: Path) -> set[str]:
    """The reasons a module gives a frame (``FrameReason.X`` as that text, a bare string as itself): the
    fifth argument of ``FrameResult(...)``, what is assigned to ``reason`` (or unpacked into it), and what a
    ``..._problem`` function or the gates' ``doubt`` (its answers worked out in ``_doubt``) returns."""
    found: set[str] = set()
    tree = ast.parse(path.read_text(encoding="utf-8"))

    def text(node: ast.AST) -> None:
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            found.add(node.value)  # a bare text: the test below fails on it
        elif isinstance(node, ast.Attribute) and getattr(node.value, "id", None) == "FrameReason":
            found.add(f"FrameReason.{node.attr}")
        elif isinstance(node, ast.IfExp):  # FrameReason.FIRST_FRAME if ... else FrameReason.NO_TAGS
            text(node.body)
            text(node.orelse)

    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "FrameResult" and len(node.args) >= 5:
            text(node.args[4])
        elif isinstance(node, ast.Assign):
            for target in node.targets:
                if isinstance(target, ast.Name) and target.id == "reason":
                    text(node.value)
                elif isinstance(target, ast.Tuple) and isinstance(node.value, ast.Tuple):
                    for t, v in zip(target.elts, node.value.elts, strict=False):
                        if isinstance(t, ast.Name) and t.id == "reason":
                            text(v)
        elif isinstance(node, ast.FunctionDef) and (node.name.endswith("_problem") or node.name in ("doubt", "_doubt")):
            for ret in ast.walk(node):
                if isinstance(ret, ast.Return) and ret.value is not None:
                    text(ret.value)
    return found


def test_every_reason_the_receiver_gives_is_a_frame_reason() -> None:
    from ipt.receiver.core.reasons import FrameReason

    receiver = PACKAGE / "receiver" / "core"
    files = ("pipeline.py", "paperway.py", "gates.py", "framecheck.py")
    found = set().union(*(_reason_literals(receiver / n) for n in files))
    named = {f"FrameReason.{r.name}" for r in FrameReason}
    wanted = {"POSE", "FIRST_FRAME", "NO_TAGS", "TIME_GAP", "DARK", "MOTION_JUMP"}
    assert {f"FrameReason.{n}" for n in wanted} <= found  # the scan finds them
    assert found - named == set(), "a reason given as bare text, or a name that is not a FrameReason"


# --- sizes: no module over 600 lines, no function over 80 (issue 32, target 6) -------------------------

MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80

ALLOWED_LONG_MODULES: set[str] = set()
"""Modules allowed over the limit for now (none: remove an entry as its module comes under it; the test below
fails on an entry that no longer needs it)."""
ALLOWED_LONG_FUNCTIONS: set[tuple[str, str]] = set()
"""The same for functions."""


def module_sizes(source: str) -> tuple[int, list[tuple[str, int, int]]]:
    """The lines of a module, and (qualified name, first line, lines) of each function in it, nested ones
    and methods included; a function counts from its ``def`` line to its last line (decorators not
    counted, its docstring and comments counted)."""
    found: list[tuple[str, int, int]] = []

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                name = f"{prefix}{child.name}"
                found.append((name, child.lineno, (child.end_lineno or child.lineno) - child.lineno + 1))
                visit(child, f"{name}.")
            elif isinstance(child, ast.ClassDef):
                visit(child, f"{prefix}{child.name}.")
            else:
                visit(child, prefix)

    visit(ast.parse(source), "")
    return len(source.splitlines()), found


def _sizes_over_the_limits(root: Path = PACKAGE) -> tuple[dict[str, int], dict[tuple[str, str], int]]:
    modules: dict[str, int] = {}
    functions: dict[tuple[str, str], int] = {}
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root.parent).as_posix()
        lines, defs = module_sizes(path.read_text(encoding="utf-8"))
        if lines > MAX_MODULE_LINES:
            modules[rel] = lines
        for name, _, n in defs:
            if n > MAX_FUNCTION_LINES:
                functions[(rel, name.rpartition(".")[2])] = n
    return modules, functions


def test_the_size_scan_sees_nested_functions_and_methods() -> None:
    body = "".join(f"    x{i} = {i}\n" for i in range(79))
    text = (
        "class A:\n"
        "    def short(self):\n"
        "        return 1\n"
        "\n"
        "    async def long(self):\n" + "".join(f"    {line}" for line in body.splitlines(keepends=True)) + "\n"
        "def outer():\n"
        "    def inner():\n" + "".join(f"    {line}" for line in body.splitlines(keepends=True)) + "    return inner\n"
    )
    lines, defs = module_sizes(text)
    assert lines == len(text.splitlines())
    sizes = {name: n for name, _, n in defs}
    assert sizes == {"A.short": 2, "A.long": 80, "outer": 82, "outer.inner": 80}


def test_no_module_over_600_lines_and_no_function_over_80() -> None:
    """The whole package, with the allow-list above and nothing else; an allowed entry that is no longer over
    its limit must leave the list, so that it only ever shrinks."""
    modules, functions = _sizes_over_the_limits()
    assert {m: n for m, n in modules.items() if m not in ALLOWED_LONG_MODULES} == {}
    assert {f: n for f, n in functions.items() if f not in ALLOWED_LONG_FUNCTIONS} == {}
    assert ALLOWED_LONG_MODULES - set(modules) == set(), "under the limit now: remove it from ALLOWED_LONG_MODULES"
    assert ALLOWED_LONG_FUNCTIONS - set(functions) == set(), "under the limit now: remove it from the allow-list"


CORE_FORBIDDEN_STDLIB = ("asyncio", "socket", "subprocess", "multiprocessing", "selectors", "concurrent")


def _stdlib_imports(path: Path) -> list[tuple[str, int]]:
    """The top-level names of every ``import`` and ``from ... import`` of a file, at any depth, with lines."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found += [(a.name.partition(".")[0], node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            found.append((node.module.partition(".")[0], node.lineno))
    return found


def test_the_receiver_core_is_pure() -> None:
    """``ipt/receiver/core`` (the per-frame stages) imports nothing of the detector, capture or outputs rooms
    and no process, socket or event-loop machinery: the detector (and its helper process) is handed to the
    pipeline by whoever builds it (issue 32)."""
    edges = [e for e in all_imports() if _under(e.source, "ipt.receiver.core")]
    assert any(e.target == "ipt.receiver.core.kernels" for e in edges)  # the scan sees the core's imports
    bad = [
        str(e)
        for e in edges
        if _under(e.target, "ipt.receiver.detect", "ipt.receiver.capture", "ipt.receiver.outputs")
        or _under(e.target, "ipt.receiver.daemon", "ipt.receiver.replay", "ipt.receiver.cli")
    ]
    core = PACKAGE / "receiver" / "core"
    bad += [
        f"{path.relative_to(ROOT)}:{line} imports {name}"
        for path in sorted(core.rglob("*.py"))
        for name, line in _stdlib_imports(path)
        if name in CORE_FORBIDDEN_STDLIB
    ]
    assert bad == []


def test_the_stdlib_scan_sees_function_level_imports() -> None:
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "m.py"
        path.write_text("import os\ndef f():\n    import subprocess\n    from asyncio import sleep\n", encoding="utf-8")
        assert _stdlib_imports(path) == [("os", 1), ("subprocess", 3), ("asyncio", 4)]


# --- tests step time instead of sleeping (issue 32, target 3) -----------------------------------------

MAX_TEST_SLEEPS = 10
TESTS = Path(__file__).resolve().parent
SLEEPS = {("time", "sleep"), ("asyncio", "sleep")}


def sleep_calls(source: str) -> list[tuple[int, str]]:
    """(line, text) of every call of ``time.sleep`` or ``asyncio.sleep`` in a module, however it was imported:
    ``time.sleep``, ``import time as t; t.sleep``, ``from asyncio import sleep as nap; nap``. Text inside strings
    (a script a test hands to a subprocess) is not code of the tests and is not counted."""
    tree = ast.parse(source)
    modules: dict[str, str] = {}  # local name -> "time" / "asyncio"
    functions: set[str] = set()  # local names bound to a sleep itself
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name in ("time", "asyncio"):
                    modules[alias.asname or alias.name] = alias.name
        elif isinstance(node, ast.ImportFrom) and node.module in ("time", "asyncio"):
            for alias in node.names:
                if (node.module, alias.name) in SLEEPS:
                    functions.add(alias.asname or alias.name)
    lines = source.splitlines()
    found: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        func = node.func
        hit = isinstance(func, ast.Name) and func.id in functions
        if isinstance(func, ast.Attribute) and isinstance(func.value, ast.Name):
            hit = hit or (modules.get(func.value.id), func.attr) in SLEEPS
        if hit:
            found.append((node.lineno, lines[node.lineno - 1].strip()))
    return sorted(found)


def test_the_sleep_scan_sees_aliases_and_skips_strings() -> None:
    text = (
        "import time\nimport asyncio as aio\nfrom time import sleep as nap\nfrom asyncio import sleep\n"
        "time.sleep(1)\naio.sleep(0)\nnap(2)\nsleep(3)\nx = 'time.sleep(4)'\nobj.sleep(5)\nt = time\n"
    )
    assert [n for n, _ in sleep_calls(text)] == [5, 6, 7, 8]


def test_at_most_ten_sleeps_in_the_tests_each_saying_why() -> None:
    """Daemon tests step an injected clock (:class:`ipt.runtime.SteppedClock`) or wait for a condition; the
    few sleeps left are real (another process, the kernel, a thread's pace) and say so in a comment."""
    calls: list[str] = []
    silent: list[str] = []
    for path in sorted(TESTS.rglob("*.py")):
        source = path.read_text(encoding="utf-8")
        lines = source.splitlines()
        for n, text in sleep_calls(source):
            where = f"{path.relative_to(TESTS).as_posix()}:{n}: {text}"
            calls.append(where)
            if "#" not in lines[n - 1] and not lines[n - 2].strip().startswith("#"):
                silent.append(where)
    assert len(calls) <= MAX_TEST_SLEEPS, "\n".join(calls)
    assert silent == [], "a sleep without a comment saying why it must be real:\n" + "\n".join(silent)


def _core_parts_problems(path: Path) -> list[str]:
    """What in one module of ``ipt/receiver/core`` goes behind another module's back: a private name imported
    from another ``ipt`` module, or a class built on a class of another core module (a mix-in reaching into
    the state its host sets up) rather than holding it and calling it."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found = []
    imported_core_names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("ipt"):
            for alias in node.names:
                if alias.name.startswith("_"):
                    found.append(f"{path.name}:{node.lineno} imports {node.module}.{alias.name}")
                if node.module.startswith("ipt.receiver.core"):
                    imported_core_names.add(alias.asname or alias.name)
    for node in ast.walk(tree):
        if isinstance(node, ast.ClassDef):
            found += [
                f"{path.name}:{node.lineno} {node.name} is built on {base.id}"
                for base in node.bases
                if isinstance(base, ast.Name) and base.id in imported_core_names
            ]
    return found


def test_the_pipeline_is_made_of_parts_it_calls() -> None:
    """Issue 32, target 2: the pipeline holds its gates, bridge, second look and the paper's way and calls
    them; no core module imports another's private name (the frame, pair and candidate records are public,
    in ``history``)."""
    core = PACKAGE / "receiver" / "core"
    assert (core / "pipeline.py").exists()  # the scan reads the core
    problems = [p for path in sorted(core.rglob("*.py")) for p in _core_parts_problems(path)]
    assert problems == []


def test_the_parts_scan_sees_a_mix_in_and_a_private_import() -> None:
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "m.py"
        path.write_text(
            "from ipt.receiver.core.gates import PoseGates\nfrom ipt.receiver.core.frameresult import _Frame\n"
            "class Pipeline(PoseGates):\n    pass\n",
            encoding="utf-8",
        )
        assert _core_parts_problems(path) == [
            "m.py:2 imports ipt.receiver.core.frameresult._Frame",
            "m.py:3 Pipeline is built on PoseGates",
        ]
