"""The code's layout stays readable: one import circle (``jig.compat`` and ``jig.native``, which
the firmware needs), and every module says in a docstring what it is for.

An import inside a function counts too: it hides a circle, it does not remove it.
"""

import ast
import os

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PACKAGES = (("firmware", "jig"), ("tools", "motorjig"))
KNOWN_CIRCLES = [{"jig.compat", "jig.native"}]


def modules():
    out = {}
    for base, pkg in PACKAGES:
        for folder, _dirs, files in os.walk(os.path.join(ROOT, base, pkg)):
            for f in files:
                if f.endswith(".py"):
                    path = os.path.join(folder, f)
                    name = os.path.relpath(path, os.path.join(ROOT, base))[:-3].replace(os.sep, ".")
                    out[name[:-9] if name.endswith(".__init__") else name] = path
    return out


def import_graph(mods):
    edges = {m: set() for m in mods}
    for m, path in mods.items():
        with open(path) as f:
            tree = ast.parse(f.read())
        pkg = m if path.endswith("__init__.py") else m.rsplit(".", 1)[0]
        for node in ast.walk(tree):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = pkg.split(".")
                    base = ".".join(parts[:len(parts) - node.level + 1] + ([node.module] if node.module else []))
                targets = [base] + [base + "." + a.name for a in node.names]
            # a module's own packages are imported before it: no circle through them
            edges[m] |= {t for t in targets if t in mods and t != m and not m.startswith(t + ".")}
    return edges


def circles(edges):
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = set()
            while True:
                w = stack.pop()
                on.discard(w)
                comp.add(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(comp)

    for v in edges:
        if v not in index:
            visit(v)
    return out


def test_the_only_import_circle_is_the_firmwares_known_one():
    found = circles(import_graph(modules()))
    assert sorted(map(sorted, found)) == sorted(map(sorted, KNOWN_CIRCLES)), found


def test_the_circle_finder_finds_a_circle():
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [{"a", "b", "c"}]


@pytest.mark.parametrize("name", sorted(modules()))
def test_every_module_says_what_it_is_for(name):
    with open(modules()[name]) as f:
        doc = ast.get_docstring(ast.parse(f.read()))
    assert doc and len(doc) > 20, "%s has no docstring saying what it is for" % name
