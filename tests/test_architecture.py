"""The dependency rules of docs/architecture.md, read from the source (every import
statement counts, inside functions too): jtus's modules in layers that import only
their own layer or lower, no import cycle, imports of jtus modules at the top of each
file (only optional heavy dependencies lazy, each with its reason), no module or
experiment using another module's ``_private`` name, nothing in ``jtus/`` reading
``tests/``. Each rule has a control that shows it can fail."""

from __future__ import annotations

import ast
import os

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _modules():
    """{dotted name: path} of every module under jtus/ (packages as their name)."""
    out = {}
    for d, _, files in os.walk(os.path.join(ROOT, "jtus")):
        for f in files:
            if f.endswith(".py"):
                rel = os.path.relpath(os.path.join(d, f), ROOT)[:-3].replace(os.sep, ".")
                out[rel[:-len(".__init__")] if rel.endswith(".__init__") else rel] = \
                    os.path.join(d, f)
    return out


MODULES = _modules()


def _package_of(name, path):
    return name if path.endswith("__init__.py") else name.rpartition(".")[0]


def _imports(name, path):
    """(imported jtus module, {alias: module}, [(module, attribute)]) of one file."""
    tree = ast.parse(open(path).read(), path)
    targets, aliases, from_names = set(), {}, []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith(("jtus", "tests")):
                    targets.add(a.name)
                    if a.asname:
                        aliases[a.asname] = a.name
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative import
                pkg = _package_of(name, path).split(".")
                base = ".".join(pkg[:len(pkg) - node.level + 1] + ([base] if base else []))
            if not base.startswith(("jtus", "tests")):
                continue
            for a in node.names:
                full = f"{base}.{a.name}"
                if full in MODULES or full.startswith("tests."):
                    targets.add(full)
                    aliases[a.asname or a.name] = full
                else:
                    targets.add(base)
                    from_names.append((base, a.name))
    return targets, aliases, from_names, tree


def _graph():
    graph = {}
    for name, path in MODULES.items():
        targets, _, _, _ = _imports(name, path)
        graph[name] = {t for t in targets if t in MODULES and t != name}
    return graph


def _cycles(graph):
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
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

    for v in graph:
        if v not in index:
            visit(v)
    return out


def _without_package_edges(graph):
    """A package's ``__init__`` importing its own submodules, and those importing
    siblings through the package, is how Python packages work, not a cycle between
    concepts: edges from a submodule to its own package are dropped."""
    return {v: {w for w in ws if not v.startswith(w + ".")} for v, ws in graph.items()}


# docs/architecture.md, "Layers": bottom to top; a module belongs to the layer of the
# longest prefix that names it; every ``__main__`` (a CLI) sits above them all
LAYERS = (
    ("base", ("jtus", "jtus.files", "jtus.timing", "jtus.cli", "jtus.frame")),
    ("numerics", ("jtus.sampling", "jtus.perceptual", "jtus.metrics", "jtus.losses",
                  "jtus.rollout")),
    ("data", ("jtus.data",)),
    ("models", ("jtus.models", "jtus.cost")),
    ("sim", ("jtus.sim",)),
    ("training", ("jtus.config", "jtus.recipe", "jtus.checkpoint", "jtus.loading",
                  "jtus.sharding", "jtus.evaluate", "jtus.train")),
    ("tools", ("jtus.bench", "jtus.profile", "jtus.export", "jtus.upsample",
               "jtus.reference")),
)
# optional heavy dependencies, imported inside the function that needs them; each such
# import carries a ``lazy:`` comment saying why
LAZY = ("torch", "onnx", "jax2onnx", "onnxruntime", "flatbuffers", "imageio", "imageio_ffmpeg",
        "mitsuba", "jtus.reference", "embreex", "trimesh")


def layer_of(module):
    if module.endswith(".__main__"):
        return len(LAYERS)
    best = max(((len(p), i) for i, (_, prefixes) in enumerate(LAYERS) for p in prefixes
                if module == p or module.startswith(p + ".")), default=None)
    assert best is not None, f"{module} is in no layer of LAYERS (docs/architecture.md)"
    return best[1]


def _upward(graph):
    return sorted(f"{v} ({LAYERS[layer_of(v)][0] if layer_of(v) < len(LAYERS) else 'cli'}) "
                  f"imports {w} ({LAYERS[layer_of(w)][0]})"
                  for v, ws in _without_package_edges(graph).items() for w in ws
                  if layer_of(w) > layer_of(v))


def test_every_module_is_in_a_layer():
    for name in MODULES:
        layer_of(name)


def test_no_upward_imports():
    bad = _upward(_graph())
    assert not bad, "imports that run up the layers:\n" + "\n".join(bad)


def test_upward_finder_finds_an_upward_import():
    """The control: ``sim`` reaching up into ``train`` is reported."""
    g = _graph()
    g["jtus.sim.render"] = g["jtus.sim.render"] | {"jtus.train"}
    assert _upward(g) == ["jtus.sim.render (sim) imports jtus.train (training)"]


def _nested_imports(path):
    """``(line, module, text of the line)`` of every import below a file's top level."""
    name = os.path.relpath(path, ROOT)[:-3].replace(os.sep, ".")
    src = open(path).read()
    lines = src.splitlines()
    tree = ast.parse(src, path)
    top = {id(n) for n in tree.body}
    out = []
    for node in ast.walk(tree):
        if isinstance(node, (ast.Import, ast.ImportFrom)) and id(node) not in top:
            if isinstance(node, ast.Import):
                mods = [a.name for a in node.names]
            else:
                base = node.module or ""
                if node.level:
                    pkg = _package_of(name, path).split(".")
                    base = ".".join(pkg[:len(pkg) - node.level + 1] + ([base] if base else []))
                mods = [base]
            out += [(node.lineno, m, lines[node.lineno - 1]) for m in mods]
    return out


def _bad_nested(paths):
    bad = []
    for path in paths:
        for line, mod, text in _nested_imports(path):
            where = f"{os.path.relpath(path, ROOT)}:{line}: {mod}"
            lazy = mod.split(".")[0] in LAZY or mod.startswith(LAZY)
            if not lazy:
                bad.append(where + " (import it at the top of the file)")
            elif "lazy:" not in text:
                bad.append(where + " (an optional dependency: say why it is lazy, '# lazy: ...')")
    return bad


def test_imports_at_the_top_of_each_file():
    bad = _bad_nested(MODULES.values())
    assert not bad, "imports inside functions:\n" + "\n".join(bad)


def test_nested_import_finder_finds_them(tmp_path):
    """The control: a jtus module and a required dependency imported in a function are
    reported, and so is a lazy optional one without its reason; one with it is not."""
    p = tmp_path / "m.py"
    p.write_text("def f():\n    from jtus import train\n    import numpy\n"
                 "    import torch\n    import onnxruntime  # lazy: optional\n")
    bad = _bad_nested([str(p)])
    assert [b.split(": ", 1)[1].split(" ")[0] for b in bad] == ["jtus", "numpy", "torch"], bad


def test_no_import_cycles():
    cycles = _cycles(_without_package_edges(_graph()))
    assert not cycles, f"import cycles between jtus modules: {cycles}"


def test_cycle_finder_finds_a_cycle():
    """The control: the finder reports a planted cycle (so the test above can fail)."""
    g = _without_package_edges(_graph())
    g["jtus.rollout"] = g["jtus.rollout"] | {"jtus.train"}
    assert any({"jtus.rollout", "jtus.train"} <= set(c) for c in _cycles(g))


def test_train_evaluate_one_way():
    g = _graph()
    assert "jtus.evaluate" in g["jtus.train"]
    assert "jtus.train" not in g["jtus.evaluate"]
    for low in ("jtus.models", "jtus.recipe", "jtus.checkpoint", "jtus.config",
                "jtus.data.dataset"):
        assert not {"jtus.train", "jtus.evaluate"} & g[low], low


def _private_uses(paths):
    bad = []
    for path in paths:
        name = os.path.relpath(path, ROOT)[:-3].replace(os.sep, ".")
        _, aliases, from_names, tree = _imports(name, path)
        for mod, attr in from_names:
            if attr.startswith("_") and not attr.startswith("__"):
                bad.append(f"{os.path.relpath(path, ROOT)}: from {mod} import {attr}")
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                    and node.value.id in aliases and node.attr.startswith("_")
                    and not node.attr.startswith("__")
                    and aliases[node.value.id] != name):
                bad.append(f"{os.path.relpath(path, ROOT)}:{node.lineno}: "
                           f"{aliases[node.value.id]}.{node.attr}")
    return bad


def _experiment_files():
    out = []
    for d, _, files in os.walk(os.path.join(ROOT, "experiments")):
        out += [os.path.join(d, f) for f in files if f.endswith(".py")]
    return out


def test_no_private_names_across_modules():
    bad = _private_uses(list(MODULES.values()) + _experiment_files())
    assert not bad, "another module's _private name used:\n" + "\n".join(bad)


def test_private_finder_finds_a_use(tmp_path):
    p = tmp_path / "x.py"
    p.write_text("from jtus import train\nfrom jtus.models.tus import _box\ntrain._plan(1)\n")
    found = _private_uses([str(p)])
    assert len(found) == 2, found


def _reads_tests(paths):
    """Files that import ``tests`` or name a path into ``tests/`` (a module loaded by
    path is a dependency the import graph does not show)."""
    bad = []
    for path in paths:
        name = os.path.relpath(path, ROOT)[:-3].replace(os.sep, ".")
        targets, _, _, tree = _imports(name, path)
        strings = [n.value for n in ast.walk(tree)
                   if isinstance(n, ast.Constant) and isinstance(n.value, str)]
        if any(t.startswith("tests") for t in targets) or any(
                s == "tests" or s.startswith("tests/") for s in strings):
            bad.append(os.path.relpath(path, ROOT))
    return bad


def test_package_never_reads_tests():
    bad = _reads_tests(MODULES.values())
    assert not bad, bad


def test_tests_reader_finds_an_import_and_a_path(tmp_path):
    """The control: an import of ``tests`` and a path joined into ``tests/`` (how the
    bench once loaded its PyTorch reference) are both found."""
    a, b, c = tmp_path / "a.py", tmp_path / "b.py", tmp_path / "c.py"
    a.write_text("from tests import seqdata\n")
    b.write_text("import os\nREF = os.path.join(os.path.dirname(__file__), 'tests', 'r.py')\n")
    c.write_text("import os\nREF = os.path.join(os.path.dirname(__file__), 'jtus', 'r.py')\n")
    assert [os.path.basename(p) for p in _reads_tests([str(a), str(b), str(c)])] == \
        ["a.py", "b.py"]


def _main_block_rebinds(path):
    """Module-level names that a file's ``if __name__ == "__main__":`` block binds
    again (an import or assignment there replaces the module's own name when the file
    runs as ``python -m``, and only then)."""
    tree = ast.parse(open(path).read(), path)
    defined = {n.name for n in tree.body if isinstance(n, (ast.FunctionDef, ast.ClassDef))}
    for n in tree.body:
        if isinstance(n, (ast.Import, ast.ImportFrom)):
            defined |= {(a.asname or a.name).split(".")[0] for a in n.names}
        elif isinstance(n, ast.Assign):
            defined |= {t.id for t in n.targets if isinstance(t, ast.Name)}
    bad = set()
    for n in tree.body:
        if (isinstance(n, ast.If) and isinstance(n.test, ast.Compare)
                and getattr(n.test.left, "id", None) == "__name__"):
            for sub in ast.walk(n):
                if isinstance(sub, (ast.Import, ast.ImportFrom)):
                    bad |= {(a.asname or a.name).split(".")[0] for a in sub.names} & defined
                elif isinstance(sub, ast.Assign):
                    bad |= {t.id for t in sub.targets if isinstance(t, ast.Name)} & defined
    return bad


def test_main_blocks_rebind_no_module_name():
    """``from jtus.cli import run`` in ``jtus/evaluate.py``'s main block replaced its own
    ``run`` when run as ``python -m jtus.evaluate`` (in-process tests call ``main`` and
    missed it)."""
    bad = {name: b for name, path in MODULES.items() if (b := _main_block_rebinds(path))}
    assert not bad, bad


def test_main_block_finder_finds_a_rebinding(tmp_path):
    p = tmp_path / "m.py"
    p.write_text("def run():\n    pass\n\n\nif __name__ == '__main__':\n"
                 "    from jtus.cli import run\n    run(main)\n")
    assert _main_block_rebinds(str(p)) == {"run"}


def test_code_is_lint_clean():
    """``ruff check`` with the project's settings (pyproject.toml: pycodestyle and
    pyflakes, lines of 100) passes over jtus/, experiments/ and tests/: no unused import,
    undefined name or overlong line lands."""
    import subprocess
    import sys

    root = os.path.join(os.path.dirname(__file__), "..")
    r = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", "jtus", "tools",
                        "experiments", "tests"], cwd=root, capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr


MAX_LINES = 60  # docs/architecture.md: a function longer than this is split at its seams


def _long_functions(paths, limit=MAX_LINES):
    out = []
    for path in paths:
        for node in ast.walk(ast.parse(open(path).read(), path)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > limit:
                    out.append(f"{os.path.relpath(path, ROOT)}:{node.lineno}: {node.name} "
                               f"({n} lines)")
    return out


def test_functions_are_short():
    bad = _long_functions(MODULES.values())
    assert not bad, f"functions longer than {MAX_LINES} lines:\n" + "\n".join(bad)


def test_long_function_finder_finds_one(tmp_path):
    p = tmp_path / "m.py"
    p.write_text("def f():\n" + "    x = 1\n" * 3 + "\n\ndef g():\n    pass\n")
    assert [b.split(": ")[1] for b in _long_functions([str(p)], limit=3)] == ["f (4 lines)"]
