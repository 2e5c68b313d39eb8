"""The layers of docs/design.md, kept by reading every module's imports (ast, nothing is imported).

sim never imports envs or agent; envs never imports agent; agent never imports the CLIs or bench; the car's
runtime code (perception, decision, the camera-only drivers) never imports training, deploy tooling, the renderer,
highway-env or pybullet, and of the simulator only its dependency-free modules (those that import nothing but the
standard library, numpy and each other, such as ``sim/spec.py``); the camera-only drivers never import the
privileged ones; there is no import cycle inside ``agent/``. Imports under ``if TYPE_CHECKING:`` are types only
and do not count.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("sim", "envs", "agent", "data")
CLIS = ("drive", "train", "bench", "drive_cli", "train_cli", "cli")  # towndrive.drive_cli etc. (prefix removed)
CAMERA_ONLY_DRIVERS = ("agent.agent_driver", "agent.pilotnet_driver", "agent.agent_overlay", "agent.overlays")
PRIVILEGED_DRIVERS = ("agent.autopilot", "agent.rl_driver", "agent.rl_features")
RUNTIME_ROOMS = ("agent.perception", "agent.decision")
PURE_LIBRARIES = {"__future__", "math", "dataclasses", "typing", "numbers", "collections", "functools", "enum",
                  "numpy", "itertools", "abc"}
HEAVY = ("pybullet", "highway_env", "gymnasium")


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _type_checking_block(node: ast.AST) -> bool:
    return isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)


def imports_of(source: str, name: str, is_package: bool = False) -> set[str]:
    """The modules ``source`` (module ``name``) imports at run time, anywhere in it (lazy imports in functions
    count), resolved to absolute names without the ``towndrive.`` prefix."""
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        if _type_checking_block(node):
            for child in node.orelse:  # type: ignore[attr-defined]
                visit(child)
            return
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".") if is_package else name.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            found.add(module)
            for alias in node.names:  # `from agent import x` may name a submodule
                found.add(f"{module}.{alias.name}")
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(ast.parse(source))
    # The installed names (towndrive.sim, ...) are the repository's folders (sim, ...).
    return {f.removeprefix("towndrive.") for f in found if f != "towndrive"}


def project_imports() -> dict[str, set[str]]:
    """Each project module's run-time imports."""
    graph: dict[str, set[str]] = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            name = module_name(path)
            graph[name] = imports_of(path.read_text(), name, path.name == "__init__.py")
    return graph


def within(module: str, prefixes: tuple[str, ...] | str) -> bool:
    prefixes = (prefixes,) if isinstance(prefixes, str) else prefixes
    return any(module == p or module.startswith(p + ".") for p in prefixes)


def pure_sim_modules(graph: dict[str, set[str]]) -> set[str]:
    """sim modules that import only the standard library's pure parts, numpy and other such sim modules."""
    pure = {m for m in graph if within(m, "sim")}
    changed = True
    while changed:
        changed = False
        for m in sorted(pure):
            for imp in graph[m]:
                top = imp.split(".")[0]
                ok = (top in PURE_LIBRARIES or imp in pure or (top == "sim" and imp.rsplit(".", 1)[0] in pure)
                      or imp == "sim")
                if not ok:
                    pure.discard(m)
                    changed = True
                    break
    return pure


def violations(graph: dict[str, set[str]]) -> list[str]:
    """Every import that breaks a layer rule, as ``importer -> imported: rule``."""
    pure = pure_sim_modules(graph)
    out = []
    for m, imps in graph.items():
        for imp in sorted(imps):
            top = imp.split(".")[0]
            if top in CLIS:
                out.append(f"{m} -> {imp}: nothing imports the command-line tools or bench")
            if within(m, "sim") and top in ("envs", "agent"):
                out.append(f"{m} -> {imp}: sim knows no env or agent")
            if within(m, "envs") and top == "agent":
                out.append(f"{m} -> {imp}: envs knows no agent")
            runtime = within(m, RUNTIME_ROOMS) or within(m, CAMERA_ONLY_DRIVERS)
            if runtime:
                if within(imp, ("agent.training", "agent.deploy")):
                    out.append(f"{m} -> {imp}: the car's runtime code never imports training or deploy tooling")
                if top in HEAVY:
                    out.append(f"{m} -> {imp}: the car's runtime code never imports the simulator's libraries")
                if top == "sim" and imp != "sim" and imp not in pure and imp.rsplit(".", 1)[0] not in pure:
                    out.append(f"{m} -> {imp}: the car's runtime code imports only sim's dependency-free modules")
                if top == "envs" and imp not in ("envs.driver_context",) and not imp.startswith("envs.driver_context."):
                    out.append(f"{m} -> {imp}: the car's runtime code takes a DriverContext, not the env")
            if within(m, CAMERA_ONLY_DRIVERS) and within(imp, PRIVILEGED_DRIVERS):
                out.append(f"{m} -> {imp}: a camera-only driver never imports a privileged one")
            if within(m, "agent.perception") and within(imp, "agent.decision"):
                out.append(f"{m} -> {imp}: perception reports measurements; it never imports decision")
    return out


def cycles(graph: dict[str, set[str]], prefix: str = "agent") -> list[list[str]]:
    """Import cycles among the modules under ``prefix`` (each found once, by depth-first search)."""
    nodes = {m for m in graph if within(m, prefix)}
    edges = {m: {i for i in graph[m] if i in nodes and i != m} for m in nodes}
    found, state, stack = [], dict.fromkeys(nodes, 0), []

    def dfs(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for n in sorted(edges[m]):
            if state[n] == 1:
                found.append(stack[stack.index(n):] + [n])
            elif state[n] == 0:
                dfs(n)
        stack.pop()
        state[m] = 2

    for m in sorted(nodes):
        if state[m] == 0:
            dfs(m)
    return found


def test_no_layer_is_reached_up_or_across() -> None:
    found = violations(project_imports())
    assert not found, "\n".join(found)


def test_no_import_cycle_inside_agent() -> None:
    found = cycles(project_imports())
    assert not found, "\n".join(" -> ".join(c) for c in found)


def test_sim_spec_is_dependency_free() -> None:
    """The facts module is what the car's runtime code may read of the simulator."""
    pure = pure_sim_modules(project_imports())
    assert {"sim.spec", "sim.idm", "sim.checks"} <= pure
    assert "sim.render" not in pure and "sim.traffic" not in pure


@pytest.mark.parametrize(("module", "source", "rule"), [
    ("sim.world", "from envs.drive_env import DriveEnv", "sim knows no env"),
    ("envs.evaluation", "from agent.autopilot import Autopilot", "envs knows no agent"),
    ("agent.drivers", "import drive", "command-line tools"),
    ("agent.perception.lanes", "from sim.render import CameraConfig", "dependency-free"),
    ("agent.decision.controller", "from sim.traffic import idm_acceleration", "dependency-free"),
    ("agent.decision.controller", "import highway_env", "simulator's libraries"),
    ("agent.perception.detector", "from agent.training.autolabel import CLASSES", "never imports training"),
    ("agent.pilotnet_driver", "from agent.autopilot import PID", "privileged"),
    ("agent.agent_driver", "from envs.drive_env import BLIND_SPOT_CAMERA", "DriverContext"),
    ("agent.perception.objects", "from agent.decision.controller import Scene", "never imports decision"),
])
def test_each_rule_catches_its_violation(module: str, source: str, rule: str) -> None:
    """Each rule fails on a deliberate violation (the ones the layout was reshaped to remove)."""
    graph = project_imports()
    graph[module] = graph[module] | imports_of(source, module)
    assert any(rule in v for v in violations(graph)), violations(graph)


def test_a_cycle_is_caught() -> None:
    graph = project_imports()
    graph["agent.decision.blind_spot"] = graph["agent.decision.blind_spot"] | {"agent.agent_driver"}
    assert cycles(graph)


def test_type_checking_imports_do_not_count() -> None:
    source = "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from envs.drive_env import DriveEnv\n"
    assert imports_of(source, "agent.x") == {"typing", "typing.TYPE_CHECKING"}
