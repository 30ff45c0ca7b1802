"""The code's structure: imports go one way. No import cycle among the project's modules (imports inside
functions included), the library imports neither the recipes nor the environments, and no module imports another
module's private (underscore) name."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"torchrl_reset": ROOT / "torchrl_reset", "torchrl_reset_envs": ROOT / "envs",
            "torchrl_reset_recipes": ROOT / "recipes"}


def modules() -> dict[str, Path]:
    found = {}
    for package, folder in PACKAGES.items():
        for path in folder.rglob("*.py"):
            if "probes" in path.parts:
                continue
            parts = list(path.relative_to(folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found[".".join([package, *parts])] = path
    return found


def imports(name: str, path: Path, known: dict) -> list[tuple[str, list[str]]]:
    """(module imported, names taken from it) for each import of a project module in ``path``, at any depth."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found += [(alias.name, []) for alias in node.names if alias.name.split(".")[0] in PACKAGES]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            if source.split(".")[0] not in PACKAGES:
                continue
            taken = [alias.name for alias in node.names]
            submodules = [f"{source}.{n}" for n in taken if f"{source}.{n}" in known]
            found += [(m, []) for m in submodules]
            found.append((source, [n for n in taken if f"{source}.{n}" not in known]))
    return found


def graph() -> tuple[dict[str, set[str]], list[str]]:
    known = modules()
    edges, private = {m: set() for m in known}, []
    for name, path in known.items():
        for source, taken in imports(name, path, known):
            target = source
            while target not in known and "." in target:
                target = target.rpartition(".")[0]
            if target in known and target != name:
                edges[name].add(target)
            private += [f"{name} imports {source}.{n}" for n in taken if n.startswith("_") and n != "__version__"]
    return edges, private


def find_cycle(edges: dict[str, set[str]]) -> list[str] | None:
    state, stack = {}, []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(edges[node]):
            if state.get(nxt) == "open":
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        stack.pop()
        state[node] = "done"
        return None

    for node in sorted(edges):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def test_the_checker_finds_a_cycle_a_deferred_import_and_a_private_name(tmp_path):
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None
    source = tmp_path / "probe.py"
    source.write_text("import os\nfrom . import tasks\n\ndef f():\n"
                      "    from torchrl_reset_recipes.analysis.runs import _flatten, TASKS\n")
    known = {"torchrl_reset_envs.tasks": None, "torchrl_reset_recipes.analysis.runs": None}
    found = imports("torchrl_reset_envs.probe", source, known)
    assert ("torchrl_reset_envs.tasks", []) in found  # relative
    assert ("torchrl_reset_recipes.analysis.runs", ["_flatten", "TASKS"]) in found  # inside a function
    edges, _ = graph()
    assert "torchrl_reset_recipes.training.hydra_config" in edges["torchrl_reset_recipes.training.config_checks"]


def test_imports_go_one_way():
    edges, private = graph()
    assert len(edges) > 60  # every module was read
    assert find_cycle(edges) is None
    assert private == []
    library = [f"{m} -> {t}" for m, targets in edges.items() if m.split(".")[0] == "torchrl_reset"
               for t in targets if t.split(".")[0] != "torchrl_reset"]
    assert library == []  # torchrl_reset imports neither the recipes nor the environments
