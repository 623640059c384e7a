"""Layering of the package: no module imports from a layer above its own (parsed with ast, imports anywhere).

Layers, lowest first (a module may import from its own layer and the layers below it):

| layer | packages and modules | what they hold |
|---|---|---|
| 0 foundations | errors, options, logging, warp_runtime, benchmarking | errors, enums, logger, bench record |
| 1 linalg | linalg | sparse factorization, PCG, line search, CSR assembly |
| 2 data | structures, io | GarmentMesh and mesh checks, files |
| 3 domain | body, sdf, pattern | bodies, body distance fields, sewing patterns and meshing |
| 4 simulation | sim, testing | energies, scenes, solvers, differentiable solve, draping; FD checks |
| 5 rendering | render | PNG renders (used by the command-line modules only) |
| 6 methods | adjust, retarget, datadriven, studies | the three fitting methods, study metrics |
| 7 commands | cli, __main__, batch, adjust.cli, adjust.demo, retarget.cli, datadriven.cli, ... | CLI |

The package root ``torchgarment/__init__.py`` re-exports the errors only. Imports under
``if TYPE_CHECKING:`` and inside functions (lazy imports, for import speed) are held to the same rule.
Modules inside a package import from its submodules, never from the package's own ``__init__`` (which would
be circular).
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "torchgarment"

LAYERS: dict[str, int] = {
    "errors": 0,
    "options": 0,
    "logging": 0,
    "warp_runtime": 0,
    "testing": 4,
    "benchmarking": 0,
    "linalg": 1,
    "structures": 2,
    "io": 2,
    "body": 3,
    "sdf": 3,
    "pattern": 3,
    "sim": 4,
    "render": 5,
    "adjust": 6,
    "retarget": 6,
    "datadriven": 6,
    "studies": 6,
    "cli": 7,
    "__main__": 7,
    "batch": 7,
}
"""Layer of every top-level module or subpackage of torchgarment."""

MODULE_LAYERS: dict[str, int] = {
    "adjust.cli": 7,
    "adjust.grade_cli": 7,
    "adjust.demo": 7,
    "retarget.cli": 7,
    "datadriven.cli": 7,
    "sim.drape_cli": 7,
}
"""Modules in another layer than their package: the command-line modules of the subpackages."""

KNOWN_UPWARD: set[tuple[str, str]] = set()
"""Upward imports that exist today, each to be removed; the test fails when one disappears, so the list only
shrinks."""


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _layer(module: str) -> int:
    """Layer of a module given relative to the package ("" is the package root)."""
    if module == "":
        return 7
    parts = module.split(".")
    for n in range(len(parts), 0, -1):
        if ".".join(parts[:n]) in MODULE_LAYERS:
            return MODULE_LAYERS[".".join(parts[:n])]
    if parts[0] not in LAYERS:
        raise AssertionError(f"torchgarment.{module} is in no layer: add {parts[0]!r} to LAYERS")
    return LAYERS[parts[0]]


def _imports(path: Path, module: str) -> list[tuple[str, list[str], int]]:
    """(imported module relative to torchgarment, imported names, line) of every torchgarment import."""
    out = []
    is_package = path.name == "__init__.py"
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name == "torchgarment" or alias.name.startswith("torchgarment."):
                    out.append((alias.name.removeprefix("torchgarment").lstrip("."), [], node.lineno))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = ["torchgarment", *module.split(".")] if module else ["torchgarment"]
                base = base if is_package else base[:-1]
                base = base[: len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target == "torchgarment" or target.startswith("torchgarment."):
                names = [a.name for a in node.names]
                out.append((target.removeprefix("torchgarment").lstrip("."), names, node.lineno))
    return out


def _all_imports() -> list[tuple[str, str, list[str], int]]:
    rows = []
    for path in sorted(ROOT.rglob("*.py")):
        module = _module_name(path)
        for target, names, line in _imports(path, module):
            rows.append((module, target, names, line))
    return rows


def test_every_module_has_a_layer() -> None:
    for path in sorted(ROOT.rglob("*.py")):
        _layer(_module_name(path))


def test_no_module_imports_from_a_layer_above() -> None:
    upward, seen = [], set()
    for module, target, names, line in _all_imports():
        # `from torchgarment.x import y` may name a submodule y: judge by the deepest module named
        targets = [
            f"{target}.{n}".lstrip(".")
            for n in names
            if (ROOT / Path(*f"{target}.{n}".lstrip(".").split("."))).with_suffix(".py").exists()
        ] or [target]
        for t in targets:
            if target == "" and module != "" and _layer(module) < 7:
                upward.append(
                    f"torchgarment.{module}:{line} imports the package root (import from the module)"
                )
                continue
            if _layer(t) > _layer(module):
                key = (module, t)
                if key in KNOWN_UPWARD:
                    seen.add(key)
                    continue
                upward.append(
                    f"torchgarment.{module}:{line} (layer {_layer(module)}) imports torchgarment.{t} "
                    f"(layer {_layer(t)})"
                )
    assert not upward, "upward imports:\n" + "\n".join(upward)
    assert seen == KNOWN_UPWARD, f"fixed, remove from KNOWN_UPWARD: {sorted(KNOWN_UPWARD - seen)}"


def _is_submodule(package: str, name: str) -> bool:
    folder = ROOT.joinpath(*package.split(".")) if package else ROOT
    return (folder / f"{name}.py").exists() or (folder / name / "__init__.py").exists()


def test_modules_do_not_import_from_their_own_packages() -> None:
    bad = []
    for module, target, names, line in _all_imports():
        parts = module.split(".")
        ancestors = {".".join(parts[:n]) for n in range(1, len(parts))}
        if target in ancestors:
            names = [n for n in names if not _is_submodule(target, n)]
            if names:
                bad.append(
                    f"torchgarment.{module}:{line} imports {names} from its own package "
                    f"torchgarment.{target}: import them from their module"
                )
    assert not bad, "\n".join(bad)
