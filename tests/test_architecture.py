"""The dependency direction narf <- fitting <- pipelines, and no file I/O inside narf/."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN = {"narf": ("fitting", "pipelines"), "fitting": ("pipelines",)}


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module.split(".")[0])
    return names


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_dependency_direction(package):
    for path in (ROOT / package).rglob("*.py"):
        bad = _imports(path) & set(FORBIDDEN[package])
        assert not bad, f"{path.relative_to(ROOT)} imports {sorted(bad)}"


def test_narf_does_no_file_io():
    for path in (ROOT / "narf").rglob("*.py"):
        text = path.read_text()
        for call in ("open(", "np.load", "torch.load", "torch.save", "imread", "imwrite"):
            assert call not in text, f"{path.relative_to(ROOT)} calls {call}"
