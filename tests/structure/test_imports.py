"""The package's import graph: no circle, and nothing below the top layer imports the top layer.

Every import counts, at module level or inside a function (an import inside a function is still a
dependency; it only runs later). The top layer (``cli``, ``commands``, ``bench``, ``service``) uses
everything; nothing else may import it, so the numerics, the pipeline and the worker can be used (and
tested) without the command line or the live service.
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("groundstation", "firmware_interface", "hil_replay", "benchkit")
#: the top layer: may import anything, imported by nothing else in the packages
TOP = ("groundstation.__main__", "groundstation.cli", "groundstation.commands", "groundstation.bench",
       "groundstation.service")


def _modules() -> dict[str, Path]:
    mods = {}
    for pkg in PACKAGES:
        for f in (ROOT / pkg).rglob("*.py"):
            name = ".".join(f.relative_to(ROOT).with_suffix("").parts)
            mods[name.removesuffix(".__init__")] = f
    return mods


@functools.cache
def import_graph() -> dict[str, set[str]]:
    """module -> the project modules it imports (anywhere in its source); a package's ``__init__`` is
    not counted as a dependency of its sub-modules' importers (importing ``a.b`` runs ``a``, but
    that is the package's entry, not a design dependency)."""
    mods = _modules()

    def resolve(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {}
    for name, f in mods.items():
        tree = ast.parse(f.read_text())
        base = name if f.name == "__init__.py" else name.rpartition(".")[0]
        deps: set[str] = set()
        for n in ast.walk(tree):
            if isinstance(n, ast.Import):
                targets = [a.name for a in n.names]
            elif isinstance(n, ast.ImportFrom):
                mod = n.module or ""
                if n.level:
                    parts = base.split(".")
                    mod = ".".join(parts[: len(parts) - n.level + 1] + ([mod] if mod else []))
                targets = [f"{mod}.{a.name}" for a in n.names] + [mod]
            else:
                continue
            for t in targets:
                r = resolve(t)
                if r and r != name and not name.startswith(r + ".") and mods[r].name != "__init__.py":
                    deps.add(r)
        graph[name] = deps
    return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = 0
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph.get(root, ()))))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph.get(w, ())))))
                    break
                if w in on:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return out


#: circles still to break: the test fails on any other (none left)
KNOWN_CIRCLES: list[list[str]] = []


def _top(name: str) -> bool:
    return any(name == t or name.startswith(t + ".") for t in TOP)


def test_no_import_circle():
    found = [c for c in circles(import_graph()) if c not in KNOWN_CIRCLES]
    assert not found, "import circles:\n" + "\n".join(" <-> ".join(c) for c in found)


def test_nothing_below_the_top_layer_imports_it():
    up = sorted(f"{m} imports {d}" for m, deps in import_graph().items() if not _top(m)
                for d in deps if _top(d))
    assert not up, "upward imports:\n" + "\n".join(up)


def test_test_and_bench_support_is_not_part_of_the_product():
    """benchkit (known-truth flights of our own model, the reference fit, .rrd read-back) serves the
    tests and the bench commands; the product never needs it, and the simulator does not either."""
    into = sorted(f"{m} imports {d}" for m, deps in import_graph().items()
                  if not m.startswith(("benchkit", "groundstation.bench")) for d in deps if d.startswith("benchkit"))
    assert not into, "\n".join(into)
    assert not any((ROOT / "groundstation" / p).exists() for p in ("sysid/synthetic.py", "sysid/reference.py",
                                                                   "sinks/rerun_inspect.py"))


def test_the_walk_sees_circles_and_function_level_imports():
    g = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert circles(g) == [["a", "b", "c"]]
    graph = import_graph()
    # groundstation.analysis imports the diagnosis inside a function only
    assert "groundstation.gap.diagnose" in graph["groundstation.analysis"]


#: what the numerical packages never import (DESIGN: dsp, sysid, gap and freq do no IO, no networking,
#: no event loop and no clock; plots go through matplotlib in their ``plots`` modules only)
IMPURE = {"asyncio", "serial", "zenoh", "rerun", "time", "socket", "subprocess", "threading", "multiprocessing"}


def _imported_top_names(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    names = {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    names |= {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module and not n.level}
    return names


@pytest.mark.parametrize("package", ["dsp", "sysid", "gap", "freq"])
def test_numerical_packages_are_pure(package):
    bad = []
    for f in sorted((ROOT / "groundstation" / package).rglob("*.py")):
        for name in _imported_top_names(f):
            top = name.split(".")[0]
            if top in IMPURE or (top == "matplotlib" and f.stem != "plots"):
                bad.append(f"{f.relative_to(ROOT)} imports {name}")
            if name.startswith(("groundstation.sinks", "groundstation.service", "groundstation.worker",
                                "groundstation.campaign", "groundstation.analysis", "groundstation.pipeline")):
                bad.append(f"{f.relative_to(ROOT)} imports {name} (a layer above)")
    assert not bad, "\n".join(bad)


#: Imports that stay inside functions, each with its reason; every other import is at module level, so
#: a module's dependencies are in its first lines and an import circle fails at once, not on some later
#: call. (The command line's dispatch imports a command's module only when it runs, through
#: ``importlib.import_module`` in ``cli.py`` and ``commands/bench.py``: one lazy import per command.)
#: Third-party modules, by top-level name (or dotted prefix): heavy at import, needed by a few paths only.
LAZY_THIRD_PARTY = {
    "matplotlib": "plots only (about 0.5 s of CPU to import)",
    "rerun": "the Rerun sink and its figures only (about 0.6 s)",
    "zenoh": "the zenoh sink and its benchmarks only",
    "pyarrow": "the campaign store's Parquet files only",
    "dask": "campaigns on a Dask cluster only",
    "distributed": "campaigns on a Dask cluster only (about 0.5 s)",
    "psutil": "optional (the bench extra): machine-wide CPU accounting of bench campaign",
    "scipy.signal": "about 0.9 s: only tapers other than Hann and the report's spectrum figure",
    "scipy.optimize": "about 0.3 s: differential evolution (the identification's second search) and the "
                      "least-squares fits (frequency domain, reference, command-response structure) load it",
    "scipy.linalg": "the command-response structure's matrix exponential only",
    "pyulog": "PX4 .ulg logs only (0.1 s at every start otherwise)",
    "resource": "Unix only (the import fails elsewhere)",
}
#: Our own modules, by (importing module, imported package or module).
LAZY_OWN = {
    ("groundstation.analysis", "groundstation.gap"):
        "the diagnosis brings scipy.stats (about 0.9 s); `identify` and the API's identify() never need it",
    ("groundstation.worker", "groundstation.campaign.live"):
        "the trend tests bring scipy.stats (about 0.9 s) into the service's own process, which never runs them",
    ("groundstation.service", "groundstation.sinks.rerun_sink"):
        "the Rerun sink imports rerun (about 0.6 s): only when the service is given a Rerun viewer or file",
    ("groundstation.commands.diagnose", "groundstation.gap.plots"):
        "the diagnosis's PNG figures import matplotlib (about 0.5-1 s of CPU): only with --plots",
    ("firmware_interface.readers", "firmware_interface.dfcolumns"):
        "dataflash .bin/.px4log only: pymavlink's DFReader and mavutil (about 0.03 s at every start otherwise)",
    ("groundstation.service", "hil_replay.fc"):
        "the built-in simulated flight controller (scipy.linalg, about 0.5 s): only when no link is given",
}


def _function_imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import statement inside a function of ``path`` (relative ones resolved
    to the name as written, with its dots)."""
    out: list[tuple[int, str]] = []

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Import) and in_function:
                out.extend((child.lineno, a.name) for a in child.names)
            elif isinstance(child, ast.ImportFrom) and in_function:
                out.append((child.lineno, "." * child.level + (child.module or "")))
            else:
                visit(child, in_function or isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda))

    visit(ast.parse(path.read_text()), False)
    return out


def _allowed(importer: str, module: str) -> bool:
    def under(name: str, prefix: str) -> bool:
        return name == prefix or name.startswith(prefix + ".")

    return (any(under(module, p) for p in LAZY_THIRD_PARTY)
            or any(importer == i and under(module, m) for i, m in LAZY_OWN))


def test_imports_are_at_module_level_unless_listed_with_a_reason():
    found = sorted(f"{f.relative_to(ROOT)}:{line} imports {mod} inside a function"
                   for name, f in _modules().items() for line, mod in _function_imports(f)
                   if not _allowed(name, mod))
    assert not found, "\n".join(found)


def test_the_function_import_walk_sees_nested_and_relative_imports(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("import json\n\ndef f():\n    if True:\n        from . import x\n    def g():\n"
                 "        import matplotlib.pyplot\n    return [lambda: __import__('os')]\n\nclass C:\n"
                 "    import sys\n    def h(self):\n        from groundstation.gap import diagnose\n")
    assert _function_imports(f) == [(5, "."), (7, "matplotlib.pyplot"), (13, "groundstation.gap")]
    assert _allowed("x", "matplotlib.pyplot") and not _allowed("x", "matplotlib_extra")
    assert _allowed("groundstation.analysis", "groundstation.gap.diagnose")
    assert not _allowed("groundstation.worker", "groundstation.gap.diagnose")
    assert not _allowed("x", "scipy.stats") and not _allowed("x", ".")
