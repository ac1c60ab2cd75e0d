"""The import graph has no upward edge: bytes → frames → forces → listeners
→ service → API, each layer importing only the ones below it.

Reproduce by hand: ``python -m pytest tests/test_layers.py -q`` prints every
offending import (file:line → module) when there is one.
"""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# (module prefix, rank): a module may import modules of its own rank or below.
# The longest matching prefix decides.
LAYERS = [
    ("service.protocol", 0), ("service.protocol_decoder", 0), ("service.protocol_sequence", 0), ("service.protocol_bulk", 0),
    ("service.physics", 0), ("service.latency", 0), ("service.sched", 0), ("service.clock_map", 0), ("service.recent", 0),
    ("service.readings", 1), ("service.board_info", 1), ("service.interpreter", 1), ("service.identify", 1),
    ("service.reconstruct", 2),
    ("service.history", 3), ("service.fanout", 3), ("service.record", 3), ("service.sources", 3),
    ("service.net", 3),
    ("service.calibration.registry", 3), ("service.calibration.book", 3),
    ("service.pipeline", 4), ("service.pipeline_changes", 4), ("service.handover", 4), ("service.readout", 4), ("service.board", 4),
    ("service.remote_board", 4), ("service.gateway", 5),
    ("service.live_service", 5), ("service.health", 5), ("service.replay", 5), ("service.robot_config", 5),
    ("service.api", 6), ("service.reports", 6), ("service.client", 6), ("service.client_zenoh", 6),
    ("service.calibration", 6),
    ("service.cli", 7), ("service.cli_options", 7), ("service.cli_commands", 7), ("service.cli_recordings", 7),
    ("service.cli_serve", 7), ("service.cli_link", 7), ("service.cli_zenoh", 7),
    ("service.cli_signals", 7),
]
# Peers that must not know each other.
APART = [("service.api", "service.reports"), ("service.reports", "service.api"), ("service.client", "service.api")]
# Who may run the simulator: the CLI's `sim` command and the bench's scenarios.
SIMULATOR_USERS = ("service.cli_commands", "service.reports")
SIMULATOR_MAY_IMPORT = ("service.protocol", "service.physics")


def rank(module: str) -> int | None:
    best = None
    for prefix, value in LAYERS:
        if (module == prefix or module.startswith(prefix + ".")) and (best is None or len(prefix) > len(best[0])):
            best = (prefix, value)
    return None if best is None else best[1]


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(path: Path, module: str | None = None) -> list[tuple[int, str]]:
    """(line, absolute module) of every import in ``path`` (the module
    ``module``, by default its name in the tree), relative ones resolved."""
    package = (module or module_name(path)).split(".")
    if path.name != "__init__.py":
        package = package[:-1]
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            module = ".".join([*base, *(node.module.split(".") if node.module else [])])
            out.append((node.lineno, module))
            out += [(node.lineno, f"{module}.{alias.name}") for alias in node.names if rank(f"{module}.{alias.name}") is not None
                    and module in ("service", "service.reconstruct", "service.physics", "service.record")]
        elif isinstance(node, ast.Import):
            out += [(node.lineno, alias.name) for alias in node.names]
    return out


def sources(package: str) -> list[Path]:
    return sorted((ROOT / package).rglob("*.py"))


def test_every_service_module_has_a_layer():
    unplaced = [module_name(p) for p in sources("service") if rank(module_name(p)) is None and p.name != "__init__.py"]
    assert unplaced == []


def test_no_service_module_imports_a_layer_above_it():
    upward = []
    for path in sources("service"):
        here = module_name(path)
        for line, target in imports(path):
            there = rank(target)
            if there is not None and rank(here) is not None and there > rank(here):
                upward.append(f"{path.relative_to(ROOT)}:{line} ({here}) → {target}")
            if any(here.startswith(a) and target.startswith(b) for a, b in APART):
                upward.append(f"{path.relative_to(ROOT)}:{line} ({here}) → {target}, a peer it must not know")
            if target.startswith("firmware_sim") and not here.startswith(SIMULATOR_USERS):
                upward.append(f"{path.relative_to(ROOT)}:{line} ({here}) → {target}: the simulator")
    assert upward == []


def test_the_simulator_depends_only_on_the_protocol_and_the_physics():
    wrong = [f"{path.relative_to(ROOT)}:{line} → {target}" for path in sources("firmware_sim")
             for line, target in imports(path)
             if target.startswith("service") and not target.startswith(SIMULATOR_MAY_IMPORT)]
    assert wrong == []


def test_the_check_sees_an_upward_import(tmp_path):
    """The checker itself: an upward edge planted in a physics module is found."""
    planted = tmp_path / "planted.py"
    planted.write_text("from ..pipeline import Pipeline\nfrom . import tables\n")
    found = [target for _, target in imports(planted, "service.physics.planted")
             if rank(target) > rank("service.physics.planted")]
    assert found == ["service.pipeline"]
