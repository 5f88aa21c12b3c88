"""The dependency rules of docs/architecture.md, read from the source (every import
statement counts, inside functions too): no import cycle between jtus modules, no
module or experiment using another module's ``_private`` name, nothing in ``jtus/``
importing ``tests/``."""

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


def test_package_never_imports_tests():
    bad = [n for n, p in MODULES.items() if any(t.startswith("tests") for t in _imports(n, p)[0])]
    assert not bad, bad


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
    r = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", "jtus",
                        "experiments", "tests"], cwd=root, capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
