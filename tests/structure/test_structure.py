"""The house rules that ARCHITECTURE.md states, checked on the source: short functions, short
signatures (settings travel in one typed record), modules under 400 lines, and a data path that
runs one way (every import points to a stage on the left of the order ARCHITECTURE.md states;
identifying code never imports sim/)."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[2] / "torchcal"
MAX_FUNCTION_LINES = 100
MAX_PUBLIC_PARAMS = 10
MAX_MODULE_LINES = 400
# the packages that may make or read simulated data; everything else identifies from measurements
SIM_USERS = ("sim", "studies", "cli")


def _modules() -> list[tuple[str, ast.Module, int]]:
    out = []
    for f in sorted(PKG.rglob("*.py")):
        text = f.read_text()
        out.append((f.relative_to(PKG).as_posix(), ast.parse(text), text.count("\n")))
    return out


MODULES = _modules()


def _imports(rel: str, tree: ast.Module) -> list[str]:
    """Absolute names of the torchcal modules a module imports (relative imports resolved)."""
    pkg = ["torchcal"] + rel.removesuffix(".py").split("/")[:-1]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = pkg[: len(pkg) - node.level + 1] if node.level else []
            out.append(".".join(base + ([node.module] if node.module else [])))
    return [n for n in out if n.startswith("torchcal")]


def _functions(tree: ast.Module):
    return [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]


def test_the_structure_checks_see_the_package():
    # a check that read nothing would pass: make sure it reads what it judges
    assert len(MODULES) > 100 and sum(len(_functions(t)) for _, t, _ in MODULES) > 1000


def test_no_function_is_over_100_lines():
    long = [f"{rel}:{fn.name} ({fn.end_lineno - fn.lineno + 1} lines)" for rel, tree, _ in MODULES
            for fn in _functions(tree) if fn.end_lineno - fn.lineno + 1 > MAX_FUNCTION_LINES]
    assert not long, "split these into named steps: " + ", ".join(long)


def _count_params(fn) -> int:
    a = fn.args
    names = [x.arg for x in a.posonlyargs + a.args + a.kwonlyargs]
    return len(names) - (1 if names and names[0] in ("self", "cls") else 0)


def _constructors() -> list[tuple[str, str, ast.FunctionDef]]:
    """``(module, class, __init__)`` of every public class that writes its own constructor."""
    return [(rel, c.name, fn) for rel, tree, _ in MODULES for c in ast.walk(tree)
            if isinstance(c, ast.ClassDef) and not c.name.startswith("_")
            for fn in c.body if isinstance(fn, ast.FunctionDef) and fn.name == "__init__"]


def test_public_functions_take_at_most_10_parameters():
    long = [f"{rel}:{fn.name} ({_count_params(fn)})" for rel, tree, _ in MODULES for fn in _functions(tree)
            if not fn.name.startswith("_") and _count_params(fn) > MAX_PUBLIC_PARAMS]
    assert not long, "move the settings of these into a torchcal.options.Options record: " + ", ".join(long)


def test_constructors_take_at_most_10_parameters():
    ctors = _constructors()
    assert len(ctors) > 20  # a check that found no constructor would pass
    long = [f"{rel}:{cls}.__init__ ({_count_params(fn)})" for rel, cls, fn in ctors
            if _count_params(fn) > MAX_PUBLIC_PARAMS]
    assert not long, "give these a torchcal.options.Options settings record: " + ", ".join(long)


def test_no_module_is_over_400_lines():
    big = [f"{rel} ({n})" for rel, _, n in MODULES if n > MAX_MODULE_LINES]
    assert not big, "split these modules by concept: " + ", ".join(big)


ARCHITECTURE = PKG.parent / "ARCHITECTURE.md"
# the modules that serve every stage (ARCHITECTURE.md names them); they import only each other
SHARED = {"params", "options", "damping", "outputs", "outputs_lock", "outputs_manifest", "threads", "environment",
          "advice", "version"}


def _stages() -> list[str]:
    """The stages in the order ARCHITECTURE.md states them ("Stages, left to right: ...")."""
    line = next(ln for ln in ARCHITECTURE.read_text().splitlines() if ln.startswith("Stages, left to right:"))
    return [s.strip(" `/.") for s in line.split(":", 1)[1].split(",")]


def _edges() -> list[tuple[str, str, str]]:
    """(module, its top-level package, the top-level package it imports) for every import
    between two different top-level parts of torchcal."""
    out = []
    for rel, tree, _ in MODULES:
        src = rel.removesuffix(".py").split("/")[0]
        for name in _imports(rel, tree):
            dst = name.split(".")[1] if "." in name else ""
            if dst and dst != src:
                out.append((rel, src, dst))
    return out


def test_the_stage_order_names_every_package():
    stages = _stages()
    packages = {p.name for p in PKG.iterdir() if p.is_dir() and (p / "__init__.py").is_file()}
    modules = {p.stem for p in PKG.glob("*.py")} - {"__init__", "__main__"}
    assert set(stages) == packages, f"ARCHITECTURE.md's stages {stages} against the packages {sorted(packages)}"
    assert SHARED == modules, f"modules beside the stages: {sorted(modules)}; ARCHITECTURE.md names {sorted(SHARED)}"


def test_every_import_points_to_the_left():
    rank = {s: i for i, s in enumerate(_stages())}
    edges = [(rel, src, dst) for rel, src, dst in _edges() if src not in ("__init__", "__main__")]
    assert len(edges) > 100  # the check reads the imports it judges
    back = [f"{rel} imports {dst}/" for rel, src, dst in edges
            if (src in SHARED and dst not in SHARED)
            or (src in rank and dst in rank and rank[dst] > rank[src])]
    assert not back, "these import a stage to their right (ARCHITECTURE.md): " + "; ".join(back)


def test_the_order_check_sees_a_backward_import():
    # the results used to write their own reports: that is exactly what must be caught
    rank = {s: i for i, s in enumerate(_stages())}
    assert rank["report"] > rank["pipelines"] > rank["deploy"] and rank["cli"] == len(rank) - 1


def test_identifying_code_never_imports_the_simulators():
    users = [f"{rel} imports {name}" for rel, tree, _ in MODULES if rel.split("/")[0] not in SIM_USERS
             for name in _imports(rel, tree) if name == "torchcal.sim" or name.startswith("torchcal.sim.")]
    assert not users, "; ".join(users)
