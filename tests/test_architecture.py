"""The dependency direction narf <- fitting <- pipelines (and inside pipelines/), an acyclic import graph, and no
file I/O inside narf/ (docs/design.md, "Layout")."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("narf", "fitting", "pipelines", "bench")
FORBIDDEN = {"narf": ("fitting", "pipelines"), "fitting": ("pipelines",)}
ABOVE_DATA = ("pipelines.runs", "pipelines.viewer", "pipelines.experiments", "pipelines.cli")
#: pipelines sub-package -> the parts of pipelines/ it must not import (see pipelines/__init__.py and docs/design.md)
PIPELINES_FORBIDDEN = {
    "datasets": ("pipelines.body", "pipelines.calibration", "pipelines.prepare", "pipelines.synthetic", *ABOVE_DATA),
    "body": ("pipelines.calibration", "pipelines.prepare", "pipelines.synthetic", *ABOVE_DATA),
    "calibration": ("pipelines.body", "pipelines.prepare", "pipelines.synthetic", *ABOVE_DATA),
    "prepare": ("pipelines.calibration", "pipelines.synthetic", *ABOVE_DATA),
    "synthetic": ("pipelines.prepare", *ABOVE_DATA),
    "runs": ("pipelines.prepare", "pipelines.viewer", "pipelines.experiments", "pipelines.cli"),
    "viewer": ("pipelines.prepare", "pipelines.experiments", "pipelines.cli"),
    "experiments": ("pipelines.prepare", "pipelines.viewer", "pipelines.cli"),
}


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules(path: Path) -> set[str]:
    """Every module a file imports, at any depth (lazy imports inside functions count); ``from package import name``
    counts ``package.name`` when that is a module of the project."""
    tree = ast.parse(path.read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


def _project_modules() -> dict[str, Path]:
    return {_module_name(p): p for package in PACKAGES for p in (ROOT / package).rglob("*.py")}


def _graph() -> dict[str, set[str]]:
    """Project module -> the project modules it imports (a package's ``__init__`` is the package's name)."""
    modules = _project_modules()
    return {name: {m for m in _modules(path) if m in modules and m != name} for name, path in modules.items()}


def _hits(modules: set[str], forbidden: tuple[str, ...]) -> list[str]:
    return sorted(m for m in modules for f in forbidden if m == f or m.startswith(f + "."))


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """A cycle of ``graph`` as [a, b, ..., a], or None (depth-first search with three colours)."""
    colour, stack = dict.fromkeys(graph, 0), []

    def visit(node: str) -> list[str] | None:
        colour[node] = 1
        stack.append(node)
        for child in sorted(graph.get(node, ())):
            if colour.get(child) == 1:
                return stack[stack.index(child) :] + [child]
            if colour.get(child) == 0 and (cycle := visit(child)):
                return cycle
        stack.pop()
        colour[node] = 2
        return None

    return next((cycle for node in sorted(graph) if colour[node] == 0 and (cycle := visit(node))), None)


def test_find_cycle_finds_one():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


def test_import_graph_is_acyclic():
    graph = _graph()
    assert "pipelines.runs.kinds" in graph and "pipelines.runs.fit" in graph["pipelines.cli.fit"]
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_dependency_direction(package):
    for path in (ROOT / package).rglob("*.py"):
        bad = {m.split(".")[0] for m in _modules(path)} & set(FORBIDDEN[package])
        assert not bad, f"{path.relative_to(ROOT)} imports {sorted(bad)}"


@pytest.mark.parametrize("package", sorted(PIPELINES_FORBIDDEN))
def test_pipelines_subpackage_direction(package):
    files = list((ROOT / "pipelines" / package).rglob("*.py"))
    assert files, f"pipelines/{package} is missing"
    for path in files:
        bad = _hits(_modules(path), PIPELINES_FORBIDDEN[package])
        assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


def test_every_pipelines_subpackage_has_a_row():
    """A new sub-package gets its place in the plan before it gets code (``cli`` sits above everything)."""
    folders = {p.name for p in (ROOT / "pipelines").iterdir() if (p / "__init__.py").is_file()}
    assert folders == set(PIPELINES_FORBIDDEN) | {"cli"}


def test_nothing_at_the_top_of_pipelines():
    assert sorted(p.name for p in (ROOT / "pipelines").glob("*.py")) == ["__init__.py"]


def test_narf_does_no_file_io():
    for path in (ROOT / "narf").rglob("*.py"):
        text = path.read_text()
        for call in ("open(", "np.load", "torch.load", "torch.save", "imread", "imwrite"):
            assert call not in text, f"{path.relative_to(ROOT)} calls {call}"


def test_every_source_folder_is_a_package():
    """setuptools' find_packages (pyproject.toml) installs only folders with an ``__init__.py``."""
    for package in ("narf", "fitting", "pipelines"):
        for folder in {p.parent for p in (ROOT / package).rglob("*.py")}:
            assert (folder / "__init__.py").is_file(), f"{folder.relative_to(ROOT)} has no __init__.py"
