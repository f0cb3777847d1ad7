"""The import rules of docs/architecture.md, checked on the source (no module is imported here).

- no import cycles between the modules of argen and detector (lazy imports included);
- every import inside a function carries its reason: a ``# lazy: ...`` comment on its line or on the line above
  its block of imports;
- each module imports only from its own layer or the layers below it (the pipeline order of the tree);
- detector uses only argen's public data modules, and turns argen's errors into its own in one place.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("argen", "detector")

#: Layers, lowest first: a module may import modules of its own layer or of a lower one. A name ending in "."
#: is a whole subpackage.
LAYERS = [
    ["argen.errors"],
    ["argen.fileio", "argen.settings"],
    ["argen.bop", "argen.h5", "argen.features", "argen.config"],
    ["argen.models."],
    ["argen.sim."],
    ["argen.label", "argen.validate", "argen.preview", "argen.merge", "argen.realism", "argen.real."],
    ["argen.cli."],
    ["detector.errors"],
    ["detector.config", "detector.geometry.", "detector.evaluation.metrics", "detector.evaluation.bop19"],
    ["detector.data.", "detector.evaluation.bop_eval"],
    ["detector.training.", "detector.net_dtype"],
    ["detector.stage1.", "detector.stage2."],
    ["detector.checkpoint", "detector.report"],
    ["detector.infer", "detector.two_stage"],
    ["detector.evaluate", "detector.predict"],
    ["detector.cli."],
]
#: The argen modules detector may import (the label file, BOP reading, frame features, the settings loader, the
#: atomic-write helper, and the one renderer, for BOP19's VSD).
ARGEN_PUBLIC = {"argen.h5", "argen.bop", "argen.features", "argen.settings", "argen.fileio", "argen.sim.render"}


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for f in sorted((REPO / pkg).rglob("*.py")):
            parts = f.relative_to(REPO).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            out[name] = f
    return out


MODULES = _modules()


def _imports(path: Path) -> list[tuple[str, ast.stmt, bool]]:
    """(imported internal module, node, at module level) for every import of ``path``."""
    tree = ast.parse(path.read_text())
    top = set()
    for node in tree.body:  # module level, also inside a top-level if/try
        top.update(id(n) for n in ast.walk(node) if not isinstance(node, (ast.FunctionDef, ast.ClassDef)))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            # "from argen import bop" imports the module argen.bop; "from argen.bop import x" the module argen.bop
            names = [f"{node.module}.{a.name}" if f"{node.module}.{a.name}" in MODULES else node.module
                     for a in node.names]
        else:
            continue
        for name in names:
            if name.split(".")[0] in PACKAGES:
                out.append((name, node, id(node) in top))
    return out


def _layer(module: str) -> int:
    for k, names in enumerate(LAYERS):
        if any(module == n or (n.endswith(".") and module.startswith(n)) for n in names):
            return k
    raise AssertionError(f"{module} is in no layer of tests/test_architecture.py: place it in the tree's order")


def _graph() -> dict[str, set[str]]:
    return {m: {name for name, _, _ in _imports(p) if name in MODULES and name != m} for m, p in MODULES.items()}


def test_every_module_has_a_layer():
    for m in MODULES:
        if MODULES[m].name != "__init__.py":  # package docstrings import nothing
            _layer(m)


def test_no_import_cycles():
    graph = _graph()
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                cycle = stack[stack.index(n):] + [n]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if n not in state:
                visit(n)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)


def test_imports_point_down_the_layers():
    bad = []
    for m, deps in _graph().items():
        if MODULES[m].name == "__init__.py":
            continue  # package docstrings import nothing
        for d in deps:
            if MODULES[d].name == "__init__.py":
                continue
            if _layer(d) > _layer(m):
                bad.append(f"{m} imports {d}, a later stage")
    assert not bad, "\n".join(sorted(bad))


def test_inference_evaluation_and_prediction_stay_apart():
    """eval and predict both infer through detector.infer; evaluate only scores, predict only reads and draws."""
    g = _graph()
    assert "detector.infer" in g["detector.evaluate"] and "detector.infer" in g["detector.predict"]
    assert "detector.predict" not in g["detector.evaluate"] and "detector.evaluate" not in g["detector.predict"]


def test_the_stages_never_import_each_other():
    """stage1/ and stage2/ share only the layers below them (geometry, data, training); detector.infer and
    detector.two_stage are where the two meet."""
    bad = [f"{m} imports {d}" for m, deps in _graph().items() for d in deps
           for a, b in (("detector.stage1", "detector.stage2"), ("detector.stage2", "detector.stage1"))
           if m.startswith(a + ".") and (d == b or d.startswith(b + "."))]
    assert not bad, "\n".join(sorted(bad))


#: What detector/geometry/ may import at module level: numpy, scipy and these of the standard library (open3d only lazily,
#: inside the ICP functions).
GEOMETRY_IMPORTS = {"numpy", "scipy", "__future__", "time", "dataclasses", "math", "os", "concurrent", "detector"}


def test_geometry_is_numpy_only():
    bad = []
    for m, path in MODULES.items():
        if not m.startswith("detector.geometry"):
            continue
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [node.module or ""]
            else:
                continue
            bad += [f"{m}:{node.lineno} imports {n}" for n in names if n.split(".")[0] not in GEOMETRY_IMPORTS
                    or (n.startswith("detector") and not n.startswith("detector.geometry"))]
    assert not bad, "\n".join(bad)


def test_detector_uses_only_argens_public_modules():
    bad = []
    for m, path in MODULES.items():
        if not m.startswith("detector"):
            continue
        for name, node, _ in _imports(path):
            if not name.startswith("argen"):
                continue
            if name == "argen.errors" and m == "detector.errors":
                continue  # the one place that wraps ArgenError
            if name not in ARGEN_PUBLIC:
                bad.append(f"{m}:{node.lineno} imports {name}")
    assert not bad, "detector may import only " + ", ".join(sorted(ARGEN_PUBLIC)) + ":\n" + "\n".join(bad)


def test_lazy_imports_state_their_reason():
    bad = []
    for m, path in MODULES.items():
        lines = path.read_text().splitlines()
        tree = ast.parse("\n".join(lines))
        top = set()
        for node in tree.body:
            if not isinstance(node, (ast.FunctionDef, ast.ClassDef)):
                top.update(id(n) for n in ast.walk(node))
        imports = sorted((n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))
                          and id(n) not in top), key=lambda n: n.lineno)
        start_of = {line: i.lineno for i in imports for line in range(i.lineno, i.end_lineno + 1)}  # 1-based
        for n in imports:
            if any("# lazy:" in lines[k] for k in range(n.lineno - 1, n.end_lineno)):
                continue
            above = n.lineno - 1  # 1-based line above; climb over the imports of the same block
            while above in start_of:
                above = start_of[above] - 1
            if above >= 1 and lines[above - 1].strip().startswith("# lazy:"):
                continue
            where = path.relative_to(REPO) if path.is_relative_to(REPO) else path
            bad.append(f"{where}:{n.lineno}: {lines[n.lineno - 1].strip()}")
    assert not bad, "imports inside functions need a '# lazy: reason' comment:\n" + "\n".join(bad)


def test_the_rules_catch_a_cycle_and_a_forbidden_import(tmp_path, monkeypatch):
    """The checks above are not vacuous: a cycle, a detector import of argen's internals, an import up the layers
    and a lazy import without its reason are found."""
    fake = {"argen.a": tmp_path / "a.py", "argen.b": tmp_path / "b.py", "detector.x": tmp_path / "x.py",
            "argen.h5": tmp_path / "h5.py"}
    fake["argen.a"].write_text("from argen.b import f\n")
    fake["argen.b"].write_text("def f():\n    from argen.a import g  # lazy: test\n")
    fake["detector.x"].write_text("from argen.sim.capture import run_capture\n\n\ndef g():\n    import os\n")
    fake["argen.h5"].write_text("from argen.sim.capture import run_capture\n")
    monkeypatch.setattr(sys.modules[__name__], "MODULES", {**fake, "argen.sim.capture": tmp_path / "c.py"})
    (tmp_path / "c.py").write_text("")
    with pytest.raises(pytest.fail.Exception, match="argen.a -> argen.b -> argen.a"):
        test_no_import_cycles()
    with pytest.raises(AssertionError, match="detector.x:1 imports argen.sim.capture"):
        test_detector_uses_only_argens_public_modules()
    with pytest.raises(AssertionError, match="x.py:5: import os"):
        test_lazy_imports_state_their_reason()
    monkeypatch.setattr(sys.modules[__name__], "MODULES", {"argen.h5": fake["argen.h5"],
                                                           "argen.sim.capture": tmp_path / "c.py"})
    with pytest.raises(AssertionError, match="argen.h5 imports argen.sim.capture, a later stage"):
        test_imports_point_down_the_layers()
