"""The modules of pemamoe/ stack in layers: each imports only modules below it.

The graph is read from the source (ast), not from a running interpreter, and counts every import:
at module level and inside functions alike, `import pemamoe.x`, `from pemamoe import x`,
`from pemamoe.x import y` and the relative forms. An import inside a function does not make a
cycle harmless: it only moves the failure from load time to the first call, and it means the lower
module knows about the higher one. CONTRIBUTING.md ("Layers") draws the stack.
"""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "pemamoe"


def imported_modules(tree: ast.AST, modules: set, package: str = "pemamoe") -> dict:
    """{module of the package: [line, ...]} for every import in `tree` that names one of `modules`.
    `from pemamoe import x` counts as an import of the module x when x is one (else of `__init__`),
    and `import pemamoe` as one of `__init__`."""
    found = {}

    def add(dotted: str, line: int) -> None:
        parts = dotted.split(".")
        if parts[0] != package:
            return
        name = parts[1] if len(parts) > 1 else "__init__"
        if name in modules:
            found.setdefault(name, []).append(line)

    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                add(alias.name, node.lineno)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: `from . import x`, `from .x import y` (one package, no subpackages)
                base = f"{package}.{base}" if base else package
            if base == package:  # `from pemamoe import x`: x is a module, or a name of __init__
                for alias in node.names:
                    add(f"{package}.{alias.name}" if alias.name in modules else package, node.lineno)
            else:
                add(base, node.lineno)
    return found


def import_graph(package_dir: Path, package: str = "pemamoe") -> dict:
    """{module: {imported module: [line, ...]}} over every `*.py` of `package_dir`."""
    files = {p.stem: p for p in sorted(Path(package_dir).glob("*.py"))}
    graph = {}
    for name, path in files.items():
        found = imported_modules(ast.parse(path.read_text(encoding="utf-8"), filename=str(path)), set(files), package)
        found.pop(name, None)  # a module naming itself is no dependency
        graph[name] = found
    return graph


def layers(graph: dict) -> tuple:
    """(layers, rest): layer 0 holds the modules that import no other module of the package, layer
    k those whose imports all lie in layers below k. `rest` holds the modules that no layer takes,
    those on a cycle or above one (empty when the graph has no cycle)."""
    placed, out = set(), []
    while True:
        layer = sorted(m for m in graph if m not in placed and set(graph[m]) <= placed)
        if not layer:
            return out, sorted(set(graph) - placed)
        out.append(layer)
        placed |= set(layer)


def find_cycle(graph: dict) -> list | None:
    """One import cycle as [a, b, ..., a], or None."""
    state = {}  # module -> "open" while on the current path, "done" after

    def visit(module, path):
        state[module] = "open"
        path.append(module)
        for dep in sorted(graph.get(module, {})):
            if state.get(dep) == "open":
                return path[path.index(dep):] + [dep]
            if dep not in state:
                cycle = visit(dep, path)
                if cycle:
                    return cycle
        state[module] = "done"
        path.pop()
        return None

    for module in sorted(graph):
        if module not in state:
            cycle = visit(module, [])
            if cycle:
                return cycle
    return None


def cyclic_groups(graph: dict) -> list:
    """The strongly connected groups of more than one module (every module of a group reaches every
    other through imports), each sorted: all the cycles at once, not one of them."""
    index, low, stack, on_stack, groups = {}, {}, [], set(), []

    def visit(module):
        index[module] = low[module] = len(index)
        stack.append(module)
        on_stack.add(module)
        for dep in graph.get(module, {}):
            if dep not in index:
                visit(dep)
                low[module] = min(low[module], low[dep])
            elif dep in on_stack:
                low[module] = min(low[module], index[dep])
        if low[module] == index[module]:
            group = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                group.append(member)
                if member == module:
                    break
            if len(group) > 1:
                groups.append(sorted(group))

    for module in sorted(graph):
        if module not in index:
            visit(module)
    return sorted(groups)


def describe(graph: dict, package: str = "pemamoe") -> str:
    """A contributor's view: the cycle, with the line of each import on it, and the layers so far."""
    lines = []
    cycle = find_cycle(graph)
    if cycle:
        lines.append("import cycle: " + " -> ".join(cycle))
        for a, b in zip(cycle, cycle[1:]):
            lines.append(f"  {package}/{a}.py imports {b} (line {', '.join(map(str, graph[a][b]))})")
        for group in cyclic_groups(graph):
            lines.append(f"  modules joined by cycles ({len(group)}): {', '.join(group)}")
        lines.append("Break it: move what the lower module needs into it or into a module below both, or pass it "
                     "in as an argument; an import inside a function does not count as a way out.")
    stack, rest = layers(graph)
    lines.append("Layers, lowest first (a module imports only modules of the layers before its own):")
    lines += [f"  {k:2d}: {', '.join(layer)}" for k, layer in enumerate(stack)]
    if rest:
        lines.append(f"  not layered (on a cycle, or importing a module that is): {', '.join(rest)}")
    return "\n".join(lines)


def check_layers(package_dir: Path, package: str = "pemamoe") -> list:
    """The layers of the package; AssertionError naming the cycle when it has one."""
    graph = import_graph(package_dir, package)
    stack, rest = layers(graph)
    assert not rest, describe(graph, package)
    return stack


def test_the_package_has_no_import_cycle():
    stack = check_layers(PACKAGE)
    print(describe(import_graph(PACKAGE)))
    # the lowest layer knows nothing of the rest; the command line is at the top
    assert {"core", "methods", "streams"} <= set(stack[0])
    assert stack[-1] == ["__main__"]


def test_the_scan_sees_imports_inside_functions_and_every_spelling(tmp_path):
    (tmp_path / "a.py").write_text("def f():\n    from pkg.b import x\n")
    (tmp_path / "b.py").write_text("import pkg.c\nfrom . import d\nfrom .e import y\n")
    for name in "cde":
        (tmp_path / f"{name}.py").write_text("")
    (tmp_path / "f.py").write_text("from pkg import b, not_a_module\nimport pkg\n")
    (tmp_path / "__init__.py").write_text("")
    graph = import_graph(tmp_path, "pkg")
    assert graph["a"] == {"b": [2]}
    assert graph["b"] == {"c": [1], "d": [2], "e": [3]}
    assert graph["f"] == {"b": [1], "__init__": [1, 2]}


def test_a_two_module_cycle_fails_and_names_it(tmp_path):
    # the lower module imports the higher one only inside a function: still a cycle
    (tmp_path / "low.py").write_text("def helper():\n    from pkg.high import thing\n    return thing\n")
    (tmp_path / "high.py").write_text("from pkg.low import helper\n\nthing = 1\n")
    (tmp_path / "base.py").write_text("")
    with pytest.raises(AssertionError) as failure:
        check_layers(tmp_path, "pkg")
    message = str(failure.value)
    assert "import cycle: high -> low -> high" in message
    assert "pkg/low.py imports high (line 2)" in message
    assert "modules joined by cycles (2): high, low" in message
    assert "0: base" in message and "not layered (on a cycle, or importing a module that is): high, low" in message


# --- no module takes another module's private names --------------------------------------------------
# A name with a leading underscore is its module's own business: when another module needs it, it
# gets a public name (and every importer is updated), or it moves to the module that uses it.
# Exceptions, each with its reason; an exception that no longer matches an import fails the test.
PRIVATE_IMPORT_EXCEPTIONS = {}  # (module, other module, name): reason


def is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def private_uses(tree: ast.AST, modules: set, package: str = "pemamoe") -> list:
    """[(line, module, name)] for each private name that `tree` takes from a module of the package:
    `from pemamoe.x import _n` and `from .x import _n` (at any depth, inside functions too), and
    `x._n` where x is bound to the module by `import pemamoe.x [as x]`, `from pemamoe import x` or
    `from . import x`. `from pemamoe import _n` counts as a name of `__init__`."""
    found, bound = [], {}  # bound: {expression naming a module: the module}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                parts = alias.name.split(".")
                if parts[0] == package and len(parts) == 2 and parts[1] in modules:
                    bound[alias.asname or alias.name] = parts[1]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = f"{package}.{base}" if base else package
            parts = base.split(".")
            if parts[0] != package:
                continue
            for alias in node.names:
                if base == package and alias.name in modules:
                    bound[alias.asname or alias.name] = alias.name
                elif is_private(alias.name):
                    found.append((node.lineno, parts[1] if len(parts) > 1 else "__init__", alias.name))
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and is_private(node.attr):
            module = bound.get(ast.unparse(node.value))
            if module is not None:
                found.append((node.lineno, module, node.attr))
    return sorted(found)


def private_imports(package_dir: Path, package: str = "pemamoe") -> list:
    """[(module, line, other module, name)]: every private name a module of `package_dir` takes from
    another module of it (a module using its own private names is fine)."""
    files = {p.stem: p for p in sorted(Path(package_dir).glob("*.py"))}
    out = []
    for name, path in files.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        out += [(name, line, other, private) for line, other, private in private_uses(tree, set(files), package)
                if other != name]
    return out


def test_no_module_imports_another_modules_private_names():
    found = private_imports(PACKAGE)
    excused = {(m, other, name) for m, _, other, name in found} & PRIVATE_IMPORT_EXCEPTIONS.keys()
    wrong = [f"pemamoe/{m}.py line {line} takes {name} from pemamoe.{other}"
             for m, line, other, name in found if (m, other, name) not in excused]
    assert not wrong, ("a module uses another module's private name; give it a public name (and update every "
                       "importer, tests included) or move it to the module that uses it:\n  " + "\n  ".join(wrong))
    stale = sorted(PRIVATE_IMPORT_EXCEPTIONS.keys() - excused)
    assert not stale, f"exceptions that no longer match any import (remove them): {stale}"


def test_the_private_name_scan_sees_every_spelling(tmp_path):
    (tmp_path / "a.py").write_text(
        "from pkg.b import public, _hidden\n"
        "from .c import _other as renamed\n"
        "import pkg.d as d_mod\n"
        "from pkg import e\n"
        "import pkg.f\n"
        "def g():\n"
        "    from pkg.b import _inner\n"
        "    return d_mod._x, e._y, pkg.f._z, e.__name__, self_thing._w\n"
        "_own = 1\n")
    for name in "bcdef":
        (tmp_path / f"{name}.py").write_text("")
    (tmp_path / "h.py").write_text("from pkg.h import _mine\n")  # a module's own names are its own
    assert private_imports(tmp_path, "pkg") == [
        ("a", 1, "b", "_hidden"), ("a", 2, "c", "_other"), ("a", 7, "b", "_inner"), ("a", 8, "d", "_x"),
        ("a", 8, "e", "_y"), ("a", 8, "f", "_z")]
