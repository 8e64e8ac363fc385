"""The layering docs/DEVELOPING.md promises: every import points down the layers (the
import-linter contracts of pyproject.toml, lazy imports included), core packages never reach up
to the config tree, the application layer, the commands or the CLI libraries (nor draw progress
bars: they take a ``(done, total)`` callback and the commands draw the bar), no two modules
import each other in a circle, and ``blockloc --help`` loads none of the heavy libraries."""

from __future__ import annotations

import ast
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parent.parent / "blockloc"
CORE = ("maps", "registration", "tracking", "global_init", "evaluation", "datasets", "sim")
FORBIDDEN = ("blockloc.config", "blockloc.app", "blockloc.commands", "blockloc.cli", "rich", "typer", "tqdm")
#: (module, forbidden package) pairs still allowed (none: core reports progress through callbacks).
ALLOWED: set = set()


def _module_name(path: Path) -> str:
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _imports(path: Path) -> set[str]:
    """Every module a file imports, at the top or inside functions."""
    tree = ast.parse(path.read_text())
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
            out.update(f"{node.module}.{a.name}" for a in node.names)
    return out


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in PKG.rglob("*.py")}


def test_core_packages_do_not_import_config_commands_or_cli_libraries():
    bad, allowed_seen = [], set()
    for name, path in _modules().items():
        if name.split(".")[1:2] and name.split(".")[1] in CORE:
            for imp in _imports(path):
                for f in FORBIDDEN:
                    if imp == f or imp.startswith(f + "."):
                        if (name, f) in ALLOWED:
                            allowed_seen.add((name, f))
                        else:
                            bad.append(f"{name} imports {imp}")
    assert not bad, "\n".join(sorted(bad))
    assert allowed_seen == ALLOWED, f"no longer imported, drop from ALLOWED: {sorted(ALLOWED - allowed_seen)}"


def test_no_import_cycles_between_modules():
    mods = _modules()
    graph = {}
    for name, path in mods.items():
        deps = set()
        for imp in _imports(path):
            # the module itself, or the module a "from pkg import name" names
            for cand in (imp, imp.rsplit(".", 1)[0]):
                if cand in mods and cand != name and not name.startswith(cand + ".") and cand != "blockloc":
                    deps.add(cand)
                    break
        graph[name] = deps
    # a package's __init__ re-exporting its modules is not a cycle of code
    for name in list(graph):
        if mods[name].name == "__init__.py":
            graph[name] = {d for d in graph[name] if not d.startswith(name + ".")}
    cycles, state = [], {}

    def visit(n, stack):
        state[n] = 1
        for d in sorted(graph[n]):
            if state.get(d) == 1:
                cycles.append(stack[stack.index(d):] + [d] if d in stack else [n, d])
            elif d not in state:
                visit(d, stack + [d])
        state[n] = 2

    for n in sorted(graph):
        if n not in state:
            visit(n, [n])
    assert not cycles, "\n".join(" -> ".join(c) for c in cycles)


def test_the_layout_in_developing_md_names_every_module():
    text = (PKG.parent / "docs" / "DEVELOPING.md").read_text()
    block = text.split("## Layout", 1)[1].split("```", 2)[1]
    missing = []
    for name, path in _modules().items():
        stem = path.stem
        if stem.startswith("_") or stem == "__init__":
            continue
        if not any(tok.startswith(stem) for tok in block.replace("/", " ").replace("(", " ").replace(",", " ").split()):
            missing.append(str(path.relative_to(PKG.parent)))
    assert not missing, f"docs/DEVELOPING.md's layout does not name: {missing}"


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(PKG.parent) + os.pathsep + os.environ.get("PYTHONPATH", "")}


def test_import_linter_contracts_hold():
    """pyproject.toml's layers and acyclic-siblings contracts (imports inside functions count)."""
    exe = shutil.which("lint-imports")
    if exe is None:
        (pytest.fail if os.environ.get("CI", "").lower() == "true" else pytest.skip)("import-linter is not installed (pip install -e .[test])")
    proc = subprocess.run([exe, "--no-cache"], cwd=PKG.parent, env=_env(), capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0 and "0 broken" in proc.stdout, proc.stdout[-4000:] + proc.stderr[-2000:]
    assert "blockloc layers point down only KEPT" in proc.stdout


def test_the_contracts_name_every_top_level_module_and_package():
    """A new module or package of blockloc/ must be placed in a layer (else no contract holds it)."""
    import tomllib

    layers = tomllib.loads((PKG.parent / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"][0]
    named = {name.strip("() ") for layer in layers["layers"] for part in layer.split("|") for name in part.split(":")}
    present = {p.stem for p in PKG.glob("*.py") if p.stem != "__init__"} | {
        p.parent.name for p in PKG.glob("*/__init__.py")}
    missing = sorted(present - named)
    assert not missing, f"pyproject.toml's layers contract places no layer for: {missing}"


HEAVY = ("numba", "gtsam", "open3d", "small_gicp", "dask", "distributed", "scipy", "matplotlib", "cyclonedds")


def test_help_loads_no_heavy_library():
    """``blockloc --help`` as the console script runs it: none of the heavy libraries load."""
    code = ("import sys\nsys.argv = ['blockloc', '--help']\nfrom blockloc.cli import main\n"
            "try:\n    main()\nexcept SystemExit:\n    pass\n"
            f"print('LOADED', sorted(m for m in {HEAVY!r} if m in sys.modules))")
    proc = subprocess.run([sys.executable, "-c", code], env=_env(), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "Usage" in proc.stdout and "track" in proc.stdout  # the help was printed
    assert proc.stdout.strip().splitlines()[-1] == "LOADED []", proc.stdout[-500:]
