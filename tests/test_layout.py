"""The package layout: imports run one way between folders, there is no import circle (lazy imports included), and no
module imports another module's private name."""

from __future__ import annotations

import ast
from itertools import pairwise
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "monai_probreg"
TIERS = {  # a folder may import its own tier and the tiers below it, never above
    "utils": 0,
    "blocks": 1,
    "networks": 1,
    "losses": 1,
    "metrics": 1,
    "uncertainty": 2,
    "spatial": 2,
    "weights": 2,
    "data": 3,  # datasets, transforms, augmentation, synthetic subjects: built on spatial's geometry, never under it
    "engines": 4,
    "registration": 5,  # the product's path, one scan read -> affine -> network -> refine -> quality -> written
    "cli": 6,  # the command: arguments and messages around registration/
    "fitting": 6,  # the sidecars' fits: registers through the engines and registration/, never through the command
}


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> list[tuple[str, list[str]]]:
    """(module, names) of every ``monai_probreg`` import in the file, at any depth (lazy ones too)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("monai_probreg"):
            found.append((node.module, [a.name for a in node.names]))
        elif isinstance(node, ast.Import):
            found += [(a.name, []) for a in node.names if a.name.startswith("monai_probreg")]
    return found


MODULES = {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def _folder(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 2 or (len(parts) == 2 and parts[1] in TIERS) else None


def test_every_folder_has_a_tier():
    folders = {p.parent.name for p in PACKAGE.rglob("*.py") if p.parent != PACKAGE}
    assert folders == set(TIERS), f"expected the folders {sorted(TIERS)}, got {sorted(folders)}"
    assert sorted(p.name for p in PACKAGE.glob("*.py")) == ["__init__.py"], "modules belong in a folder"


@pytest.mark.parametrize("module", sorted(MODULES))
def test_imports_run_one_way_and_take_no_private_names(module):
    own = _folder(module)
    for target, names in _imports(MODULES[module]):
        folder = _folder(target)
        if own is not None and folder is not None:
            assert TIERS[folder] <= TIERS[own], f"{module} (tier {TIERS[own]}) imports {target} (tier {TIERS[folder]})"
        if target == "monai_probreg" and own is not None:  # ``import monai_probreg`` for __version__ is fine
            assert not names, f"{module} imports {names} from the package root; import the defining module instead"
        private = [n for n in names if n.startswith("_")]
        assert not private, f"{module} imports private names {private} from {target}"


def _find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as its nodes in order, the first repeated at the end; None if it has none."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(node: str, stack: list[str]) -> list[str] | None:
        state[node] = 1
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return stack[stack.index(nxt) :] + [nxt]
            if nxt not in state and (cycle := visit(nxt, stack + [nxt])):
                return cycle
        state[node] = 2
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node, [node])):
            return cycle
    return None


def test_no_import_circle_between_folders():
    """Folders import one way: the folder graph (an edge for every import of another folder, at any depth of any
    module, lazy and ``TYPE_CHECKING`` imports included) has no cycle, even between folders of one tier."""
    graph: dict[str, set[str]] = {}
    where: dict[tuple[str, str], str] = {}
    for module, path in MODULES.items():
        own = _folder(module)
        if own is None:
            continue
        for target, _ in _imports(path):
            folder = _folder(target)
            if folder is not None and folder != own:
                graph.setdefault(own, set()).add(folder)
                where.setdefault((own, folder), f"{module} imports {target}")
    cycle = _find_cycle(graph)
    assert cycle is None, (
        "import circle between folders: "
        + " -> ".join(cycle)
        + " ("
        + "; ".join(where[a, b] for a, b in pairwise(cycle))
        + ")"
    )


def test_no_import_circle():
    graph = {}
    for module, path in MODULES.items():
        targets = set()
        for target, names in _imports(path):
            for candidate in [f"{target}.{n}" for n in names] + [target]:
                if candidate in MODULES and candidate != module:
                    targets.add(candidate)
                    break
        graph[module] = targets - {"monai_probreg"}
    cycle = _find_cycle(graph)
    assert cycle is None, "import circle: " + " -> ".join(cycle)
