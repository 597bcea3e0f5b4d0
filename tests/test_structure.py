"""The package structure (docs/internals/layout.md): read every module's imports with ast and check the
rules that keep the data flow readable."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("controller", "plant_fmu", "cosim", "bridge")


def _modules():
    for pkg in PACKAGES:
        for f in sorted((ROOT / pkg).rglob("*.py")):
            rel = f.relative_to(ROOT).with_suffix("")
            parts = list(rel.parts)
            is_pkg = parts[-1] == "__init__"
            if is_pkg:
                parts = parts[:-1]
            yield ".".join(parts), f, is_pkg


def _imports(name, path, is_pkg):
    """(imported module, top_level) for every import of a project module in the file."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    top = set(id(n) for n in tree.body)
    pkg = name if is_pkg else name.rpartition(".")[0]
    out = []
    for node in ast.walk(tree):
        at_top = id(node) in top
        if isinstance(node, ast.Import):
            for a in node.names:
                out.append((a.name, at_top))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg.split(".")
                base = base[:len(base) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.append((mod, at_top))
            for a in node.names:  # `from pkg import module`
                out.append((f"{mod}.{a.name}", at_top))
    known = {m for m, _, _ in _modules()}
    res = []
    for mod, at_top in out:
        # resolve to the longest known project module
        parts = mod.split(".")
        while parts and ".".join(parts) not in known:
            parts.pop()
        if parts:
            res.append((".".join(parts), at_top))
    return res


GRAPH = {name: _imports(name, f, is_pkg) for name, f, is_pkg in _modules()}


def test_every_package_is_scanned():
    assert {n.split(".")[0] for n in GRAPH} == set(PACKAGES)
    assert len(GRAPH) > 40


def find_cycles(edges: dict) -> list:
    """Every cycle a depth-first search meets in the directed graph ``edges``."""
    state, stack, cycles = {}, [], []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for d in sorted(edges.get(m, ())):
            if state.get(d) == 1:
                cycles.append(stack[stack.index(d):] + [d])
            elif d not in state:
                visit(d)
        stack.pop()
        state[m] = 2

    for m in sorted(edges):
        if m not in state:
            visit(m)
    return cycles


def test_no_import_cycle_between_modules():
    # every import, at the top or inside a function (a function-local import is still a
    # dependency; hiding it in a function would only hide the cycle). A package's __init__
    # importing its own submodules is how a package exposes them, not a cycle of the data flow.
    edges = {m: {d for d, _ in deps if d != m and not m.startswith(d + ".")}
             for m, deps in GRAPH.items()}
    cycles = find_cycles(edges)
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


def is_cli(module: str) -> bool:
    """The command-line modules (docs/internals/layout.md), which import the job they run in its handler."""
    last = module.split(".")
    return "cli" in last[1:] or last[-1].endswith("_cli")


# the function-local imports of the project's own modules outside the command line, and why
# (docs/internals/layout.md)
LAZY = {
    ("cosim.master", "cosim.fastloop"): "the compiled loop's numba, only for a plant that has "
                                        "one: an agent process (its plant a vehicle) runs "
                                        "without numba (bridge.swarm.aot)",
}


def test_project_modules_are_imported_at_the_top():
    """docs/internals/layout.md: modules import the project's modules at the top; only the command-line
    modules import the job they run inside its handler (start-up of `se3sync --help`), and the
    imports of `LAZY` are where they are for the reason it gives."""
    bad = sorted({f"{m} imports {d} inside a function" for m, deps in GRAPH.items()
                  if not is_cli(m) for d, top in deps if not top and (m, d) not in LAZY})
    assert not bad, "\n".join(bad)


def test_controller_errors_do_not_load_the_kernels():
    """The one lazy import of the project's own code (controller/__init__): the error classes and
    the state layout load without numba, so `se3sync --help` and error paths stay light."""
    import subprocess
    import sys

    code = ("import sys, controller, controller.errors, controller.layout; "
            "assert 'numba' not in sys.modules, 'numba loaded'; "
            "from controller import HybridController, se3, kernels; "
            "assert 'numba' in sys.modules and controller.se3 is se3; "
            "assert set(controller.__all__) <= set(dir(controller))")
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


# bridge/'s subpackages by job (docs/internals/layout.md): the link and plant stand alone, and
# the vehicles and the swarm each build on it, never on each other
BRIDGE_FORBIDDEN = {("mavlink", "vehicles"), ("mavlink", "swarm"), ("vehicles", "swarm"),
                    ("swarm", "vehicles")}


def test_layering():
    bad = []
    for m, deps in GRAPH.items():
        top = m.split(".")[0]
        for d, _ in deps:
            dtop = d.split(".")[0]
            if top == "controller" and dtop != "controller":
                bad.append(f"{m} imports {d} (controller/ imports nothing outside it)")
            if top == "plant_fmu" and dtop in ("cosim", "bridge"):
                bad.append(f"{m} imports {d} (plant_fmu/ does not import cosim or bridge)")
            if top == "cosim" and dtop == "bridge":
                bad.append(f"{m} imports {d} (cosim/ finds bridge through entry points only)")
            sub, dsub = m.split(".")[:2], d.split(".")[:2]
            if top == dtop == "bridge" and len(sub) == len(dsub) == 2 and sub[1] != dsub[1] \
                    and (sub[1], dsub[1]) in BRIDGE_FORBIDDEN:
                bad.append(f"{m} imports {d} (bridge.{sub[1]} does not import bridge.{dsub[1]})")
    assert not bad, "\n".join(bad)


def test_no_private_module_of_another_package():
    bad = []
    for m, deps in GRAPH.items():
        for d, _ in deps:
            if d.split(".")[0] != m.split(".")[0] and any(p.startswith("_") and p != "__init__"
                                                            for p in d.split(".")[1:]):
                bad.append(f"{m} imports the private {d}")
    assert not bad, "\n".join(bad)


def test_the_checks_see_a_cycle_and_a_private_import():
    """The scanner itself: relative imports resolve, and a cycle would be found."""
    deps = dict(GRAPH["cosim.master"])
    assert deps.get("controller.kernels") is True and "cosim.controllers" in deps
    assert "controller._kernels" in dict(GRAPH["controller.law"])
    assert "cosim.log.reader" in dict(GRAPH["cosim.log.plot"])  # `from .reader import ...`
    # the two cycles issue 11 found on the old layout, as they were
    old = {"bridge.config": {"cosim.scenario"}, "cosim.scenario": {"bridge.config"},
           "cosim.sweep": {"cosim.sweep_report"}, "cosim.sweep_report": {"cosim.sweep"},
           "cosim.master": {"controller.kernels"}}
    assert len(find_cycles(old)) == 2
    # the checks see function-local imports: the two cycles that hid in functions before
    hidden = {"cosim.master": {"cosim.fastloop"}, "cosim.fastloop": {"cosim.master"}}
    assert len(find_cycles(hidden)) == 1
    assert is_cli("cosim.cli.run") and is_cli("bridge.vehicles.sim_cli") and is_cli("plant_fmu.cli")
    assert not is_cli("cosim.master") and not is_cli("controller.kernels")
