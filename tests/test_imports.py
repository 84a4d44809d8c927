"""torchsim's import graph has no cycle, and no module of it is named after a standard-library module.

Every ``import`` statement in the installed packages (``torchsim``, ``torchsim.envs`` from ``envs/``,
``torchsim.algos`` from ``algos/``), at module level and inside functions, is an edge from its module to the
torchsim module it names (``from torchsim import x`` names the submodule ``x`` when there is one, else the package).
A parent package that a submodule import initialises is not an edge: Python runs it first, whatever it imports.
"""

import ast
import pathlib
import sys

ROOT = pathlib.Path(__file__).resolve().parent.parent
PACKAGES = {"torchsim": ROOT / "torchsim", "torchsim.envs": ROOT / "envs", "torchsim.algos": ROOT / "algos"}


def _modules() -> dict[str, pathlib.Path]:
    """Every module of the installed packages by dotted name (a package by its ``__init__.py``)."""
    found = {}
    for package, folder in PACKAGES.items():
        for path in folder.rglob("*.py"):
            parts = path.relative_to(folder).with_suffix("").parts
            name = ".".join((package, *parts))
            found[name.removesuffix(".__init__")] = path
    return found


def _resolve(name: str, modules: dict) -> str | None:
    """The torchsim module an imported dotted name loads: itself, or the longest module prefix of it."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def _edges(module: str, path: pathlib.Path, modules: dict) -> set[str]:
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    edges = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: from the package, one level up per extra dot
                anchor = package.split(".")[:len(package.split(".")) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            # ``from a import b``: the submodule a.b if there is one, else the module a
            targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base for alias in node.names]
        else:
            continue
        edges |= {t for t in (_resolve(name, modules) for name in targets if name.startswith("torchsim")) if t}
    edges.discard(module)
    return edges


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as a path, or None."""
    state, stack = {}, []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == "open":
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        stack.pop()
        state[node] = "done"
        return None

    for node in sorted(graph):
        if node not in state and (found := visit(node)):
            return found
    return None


def test_import_graph_has_no_cycle():
    modules = _modules()
    graph = {name: _edges(name, path, modules) for name, path in modules.items()}
    # the walk sees real edges, at module level and inside functions
    assert graph["torchsim.envs.base"] >= {"torchsim", "torchsim.io_urdf"}
    assert graph["torchsim.execution.stepper"] >= {"torchsim.execution.kernel.step", "torchsim.pipeline"}
    cycle = _cycle(graph)
    assert cycle is None, " -> ".join(cycle)


def test_the_engine_imports_no_recipe_or_env():
    modules = _modules()
    engine = [name for name in modules if not name.startswith(("torchsim.envs", "torchsim.algos"))]
    for name in engine:
        reached = {t for t in _edges(name, modules[name], modules) if t.startswith(("torchsim.envs", "torchsim.algos"))}
        assert not reached, f"{name} imports {reached}"


#: The physics: what a step computes. How a step runs lives in torchsim.execution, which imports these, never
#: the other way round; the front door (torchsim/__init__) and the entry points join the two.
NOT_PHYSICS = ("torchsim.execution", "torchsim.render", "torchsim.envs", "torchsim.algos", "torchsim.train",
               "torchsim.evaluate", "torchsim.progress")


def test_the_physics_imports_no_execution():
    modules = _modules()
    physics = [name for name in modules if name != "torchsim" and not name.startswith(NOT_PHYSICS)]
    assert {"torchsim.pipeline", "torchsim.methods.spring", "torchsim.io_mjcf", "torchsim.spatial"} <= set(physics)
    for name in physics:
        reached = {t for t in _edges(name, modules[name], modules) if t.startswith("torchsim.execution")}
        assert not reached, f"the physics module {name} imports {reached}"


def test_the_cycle_finder_finds_cycles():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert _cycle({"a": {"b"}, "b": set()}) is None


def test_no_module_shadows_the_standard_library():
    names = {path.stem for folder in PACKAGES.values() for path in folder.rglob("*.py")}
    assert not names & sys.stdlib_module_names, names & sys.stdlib_module_names


def test_pyproject_installs_every_package():
    """A non-editable install (``pip install .``) ships only the packages pyproject names: every folder with an
    ``__init__.py`` must be among them, or the installed ``torchsim.envs`` fails to import its subpackage."""
    import tomllib

    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    folders = {name: ROOT / path for name, path in config["package-dir"].items()}
    packages = {name for name, path in _modules().items() if path.name == "__init__.py"}
    assert set(config["packages"]) == packages, set(config["packages"]) ^ packages
    for package, folder in PACKAGES.items():  # the mapping the tests read is the one pyproject installs
        assert folders.get(package, ROOT / package).resolve() == folder.resolve(), package
