"""The dependency direction narf <- fitting <- pipelines (and inside pipelines/), and no file I/O inside narf/."""

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN = {"narf": ("fitting", "pipelines"), "fitting": ("pipelines",)}
GLUE = (
    "pipelines.fit_session",
    "pipelines.autoencoder_session",
    "pipelines.evaluation",
    "pipelines.autoencoder_evaluation",
    "pipelines.video",
    "pipelines.autoencoder_video",
    "pipelines.mesh_export",
    "pipelines.rigid_session",
)
#: pipelines sub-package -> the parts of pipelines/ it must not import (see pipelines/__init__.py)
PIPELINES_FORBIDDEN = {
    "datasets": ("pipelines.body", "pipelines.calibration", "pipelines.synthetic", "pipelines.cli", *GLUE),
    "body": ("pipelines.calibration", "pipelines.synthetic", "pipelines.cli", *GLUE),
    "calibration": ("pipelines.body", "pipelines.synthetic", "pipelines.cli", *GLUE),
    "synthetic": ("pipelines.cli", *GLUE),
    "experiments": ("pipelines.cli.experiments",),  # it runs narf-fit (cli.fit); its own CLI sits above it
}
GLUE_FORBIDDEN = ("pipelines.cli",)


def _modules(path: Path) -> set[str]:
    """Every module imported by a file, at any depth (lazy imports inside functions count)."""
    tree = ast.parse(path.read_text())
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
    return names


def _hits(modules: set[str], forbidden: tuple[str, ...]) -> list[str]:
    return sorted(m for m in modules for f in forbidden if m == f or m.startswith(f + "."))


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


def test_glue_does_not_import_the_clis():
    for name in GLUE:
        path = ROOT / (name.replace(".", "/") + ".py")
        assert not _hits(_modules(path), GLUE_FORBIDDEN), f"{path.relative_to(ROOT)} imports a CLI module"


def test_only_glue_at_the_top_of_pipelines():
    top = sorted(p.stem for p in (ROOT / "pipelines").glob("*.py") if p.stem != "__init__")
    assert top == sorted(name.split(".")[1] for name in GLUE)


def test_narf_does_no_file_io():
    for path in (ROOT / "narf").rglob("*.py"):
        text = path.read_text()
        for call in ("open(", "np.load", "torch.load", "torch.save", "imread", "imwrite"):
            assert call not in text, f"{path.relative_to(ROOT)} calls {call}"
