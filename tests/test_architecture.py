"""The import rules of docs/architecture.md, read from the source with ``ast`` (nothing is imported).

Every module under ``cellctl/``, ``drivers/`` and ``analysis/`` is parsed, imports inside functions
and under ``if TYPE_CHECKING:`` included (as are ``importlib.import_module("...")`` and
``__import__("...")`` with a literal name), and held to four rules:

1. ``drivers`` and ``analysis`` import neither ``cellctl`` nor each other;
2. production code imports no simulator: only the simulators' wings (``drivers/*/sim/``, what they
   share in ``drivers/sim/`` and the simulated cell ``cellctl/simcell/``) import a wing, besides the one door ``cellctl sim``
   (:mod:`cellctl.commands.sim_cmd`); tests and benchmarks may import anything;
3. packages do not import each other in a circle. The nodes are the packages and loose modules one
   level under each root (``cellctl.planning``, ``cellctl.motion``, ``cellctl.api``, ``cellctl.config``,
   ``drivers.abb_egm``, ...), a ``sim`` wing being a node of its own (``drivers.abb_egm.sim``,
   ``drivers.sim``);
4. the packages that others build on import only what :data:`FLOORS` lets them of ``cellctl``: the
   contract (``cellctl.api``), the worker (``cellctl.worker``) and the job store (``cellctl.jobstore``)
   know nothing of the daemon, the HMI or each other beyond the contract;
5. inside ``analysis``, design input (``analysis.design``), the registration (``analysis.register``),
   the contracts (``analysis.contracts``) and the report (``analysis.report``) import only the groups
   below them (``ANALYSIS_GROUPS``).

Each failure names the importing file and line.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from collections.abc import Mapping
from dataclasses import dataclass
from itertools import pairwise
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
ROOTS = ("cellctl", "drivers", "analysis")

#: production modules that may import the simulated cell: the ``cellctl sim`` command starts it
SIM_DOORS = {"cellctl.commands.sim_cmd": "cellctl.simcell"}

#: package -> the only nodes of ``cellctl`` it may import (rule 4): the Zenoh contract rests on the
#: configuration alone; the worker speaks the contract and nothing of the daemon; the job store (job
#: records, the plate history, the raw files) is read and written by the daemon, the HMI, the report
#: and the acquisition, and knows none of them
FLOORS: dict[str, frozenset[str]] = {
    "cellctl.api": frozenset({"cellctl.config"}),
    "cellctl.worker": frozenset({"cellctl.api", "cellctl.config"}),
    "cellctl.jobstore": frozenset({"cellctl.api", "cellctl.config"}),
    "cellctl.analysis_job": frozenset({"cellctl.api", "cellctl.config"}),
}

#: every file of ``cellctl/api/``: what both sides of the job protocol speak (keys, models, the cloud
#: codec, sessions) and the two parts of the codec that are contract too, the chunked transfer and
#: its proof (docs/architecture.md says why); a job's parameters from cell.toml are
#: ``cellctl/analysis_job.py``, the field tables of docs/api.md ``tests/api/api_doc.py``
CONTRACT_MODULES = frozenset(
    {"__init__.py", "keys.py", "models.py", "cloud_codec.py", "session.py", "transfer.py", "proof.py"}
)

#: (importer, imported module) -> why it is still there. Each entry must still be needed (a test
#: below fails on a stale one, so the list only shrinks).
PENDING: dict[tuple[str, str], str] = {}


@dataclass(frozen=True)
class Import:
    """One import statement's target: ``importer`` (module) imports ``target`` at ``path:line``."""

    importer: str
    target: str
    path: str
    line: int

    def where(self) -> str:
        return f"{self.path}:{self.line}: {self.importer} imports {self.target}"


def module_name(path: str) -> tuple[str, bool]:
    """``cellctl/daemon/service.py`` -> (``cellctl.daemon.service``, False); a package's ``__init__``
    gives the package name and True."""
    parts = list(Path(path).with_suffix("").parts)
    if parts[-1] == "__init__":
        return ".".join(parts[:-1]), True
    return ".".join(parts), False


def _literal_import_call(node: ast.Call) -> str | None:
    """The module named by ``importlib.import_module("x")``, ``import_module("x")`` or ``__import__("x")``."""
    f = node.func
    name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None
    if name not in ("import_module", "__import__") or not node.args:
        return None
    arg = node.args[0]
    return arg.value if isinstance(arg, ast.Constant) and isinstance(arg.value, str) else None


def imports_of(path: str, source: str, known: set[str]) -> list[Import]:
    """Every import of a module of ours in ``source`` (the file at repository path ``path``).

    ``from package import name`` counts as importing ``package.name`` when that is a module of ours
    (``known``), else ``package``. Relative imports are resolved against the file's package.
    """
    module, is_package = module_name(path)
    package = module if is_package else module.rpartition(".")[0]
    found: list[tuple[str, int]] = []
    for node in ast.walk(ast.parse(source, filename=path)):
        if isinstance(node, ast.Import):
            found += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = package.split(".")
                base = ".".join(base_parts[: len(base_parts) - (node.level - 1)])
                base = f"{base}.{node.module}" if node.module else base
            else:
                base = node.module or ""
            for a in node.names:
                sub = f"{base}.{a.name}"
                found.append((sub if sub in known else base, node.lineno))
        elif isinstance(node, ast.Call) and (name := _literal_import_call(node)):
            found.append((name, node.lineno))
    return [Import(module, t, path, line) for t, line in found if t.split(".")[0] in ROOTS and t != module]


def is_sim(module: str) -> bool:
    """A module of a simulator's wing: ``drivers.<driver>.sim[...]``, the simulators' shared
    ``drivers.sim[...]`` or ``cellctl.simcell[...]``."""
    parts = module.split(".")
    return (parts[0] == "drivers" and "sim" in parts[1:3]) or parts[:2] == ["cellctl", "simcell"]


def node_of(module: str) -> str:
    """The package-level node of a module: ``cellctl.daemon.scan`` -> ``cellctl.daemon``,
    ``drivers.abb_egm.sim.egm`` -> ``drivers.abb_egm.sim``, ``cellctl.config`` -> itself."""
    parts = module.split(".")
    return ".".join(parts[:3] if parts[2:3] == ["sim"] else parts[:2])


def layer_violations(imports: list[Import]) -> list[str]:
    """Rule 1: drivers and analysis import neither cellctl nor each other."""
    out = []
    for imp in imports:
        a, b = imp.importer.split(".")[0], imp.target.split(".")[0]
        if a in ("drivers", "analysis") and b == "cellctl":
            out.append(f"{imp.where()}: {a} never imports cellctl (cellctl composes drivers and analysis)")
        elif {a, b} == {"drivers", "analysis"}:
            out.append(f"{imp.where()}: drivers and analysis never import each other")
    return out


def sim_violations(imports: list[Import], pending: Mapping[tuple[str, str], str] = PENDING) -> list[str]:
    """Rule 2: a simulator's wing is imported only by a wing (or the ``cellctl sim`` door)."""
    out = []
    for imp in imports:
        if not is_sim(imp.target) or is_sim(imp.importer) or (imp.importer, imp.target) in pending:
            continue
        door = SIM_DOORS.get(imp.importer)
        if door is not None and (imp.target == door or imp.target.startswith(door + ".")):
            continue
        out.append(
            f"{imp.where()}: production code never imports a simulator (drivers/*/sim/, drivers/sim/, "
            "cellctl/simcell/); "
            "what client and simulator share lives beside the codec"
        )
    return out


def floor_violations(imports: list[Import], floors: Mapping[str, frozenset[str]] = FLOORS) -> list[str]:
    """Rule 4: a package of :data:`FLOORS` imports of ``cellctl`` only the nodes it lists."""
    out = []
    for imp in imports:
        a, b = node_of(imp.importer), node_of(imp.target)
        allowed = floors.get(a)
        if allowed is None or a == b or not b.startswith("cellctl") or b in allowed:
            continue
        may = ", ".join(sorted(allowed)) or "nothing"
        out.append(f"{imp.where()}: {a} imports of cellctl only {may} (docs/architecture.md)")
    return out


def cycle_violations(imports: list[Import]) -> list[str]:
    """Rule 3: the package-level graph has no cycle. Each cycle is reported with its path and, for
    every edge on it, the first import that makes it."""
    edges: dict[tuple[str, str], Import] = {}
    graph: dict[str, set[str]] = defaultdict(set)
    for imp in sorted(imports, key=lambda i: (i.path, i.line)):
        a, b = node_of(imp.importer), node_of(imp.target)
        if a != b:
            graph[a].add(b)
            edges.setdefault((a, b), imp)
    out = []
    for comp in _strongly_connected(graph):
        if len(comp) < 2:
            continue
        cycle = _a_cycle(sorted(comp)[0], comp, graph)
        hops = "; ".join(edges[(x, y)].where() for x, y in pairwise(cycle))
        out.append(f"import cycle between packages {' -> '.join(cycle)} ({hops})")
    return out


#: what each of analysis' groups may import of the rest of analysis (docs/architecture.md, rule 5):
#: design input is read without the stages, the registration works on the design and the contracts,
#: the contracts are built from the stages' types, the report is made from the stored results alone;
#: none of them reaches up to the pipeline or the synthetic scans.
ANALYSIS_GROUPS: dict[str, set[str]] = {
    "analysis.design": {"analysis.cloud_io"},
    "analysis.register": {"analysis.cloud_io", "analysis.contracts", "analysis.design"},
    "analysis.contracts": {"analysis.design", "analysis.metrics", "analysis.templates"},
    "analysis.report": {"analysis.contracts", "analysis.rework", "analysis.forming"},
    # the forming model and planner work on arrays in the plate frame; the report (heating-plan.json)
    # and the cell call them, never the other way (issue 47)
    "analysis.forming": set(),
}


def analysis_group_violations(imports: list[Import]) -> list[str]:
    """Rule 5: analysis' groups (design input, registration, contracts) import only the nodes below them."""
    out = []
    for imp in imports:
        a, b = node_of(imp.importer), node_of(imp.target)
        allowed = ANALYSIS_GROUPS.get(a)
        if allowed is None or a == b or not b.startswith("analysis.") or b in allowed:
            continue
        out.append(f"{imp.where()}: {a} imports of analysis only {', '.join(sorted(allowed))}")
    return out


def _strongly_connected(graph: Mapping[str, set[str]]) -> list[set[str]]:
    """Tarjan's algorithm, iterative."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    comps: list[set[str]] = []
    nodes = sorted(set(graph) | {w for ws in graph.values() for w in ws})
    for root in nodes:
        if root in index:
            continue
        work = [(root, iter(sorted(graph.get(root, ()))))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is None:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = set()
                    while True:
                        x = stack.pop()
                        on_stack.discard(x)
                        comp.add(x)
                        if x == v:
                            break
                    comps.append(comp)
            elif w not in index:
                index[w] = low[w] = len(index)
                stack.append(w)
                on_stack.add(w)
                work.append((w, iter(sorted(graph.get(w, ())))))
            elif w in on_stack:
                low[v] = min(low[v], index[w])
    return comps


def _a_cycle(start: str, comp: set[str], graph: Mapping[str, set[str]]) -> list[str]:
    """A shortest path start -> ... -> start inside one strongly connected component."""
    prev: dict[str, str] = {}
    frontier = [start]
    while frontier:
        nxt = []
        for v in frontier:
            for w in sorted(graph.get(v, ())):
                if w not in comp:
                    continue
                if w == start:  # walk back from v to start, then close the loop
                    back = [v]
                    while back[-1] != start:
                        back.append(prev[back[-1]])
                    return [*reversed(back), start]
                if w not in prev:
                    prev[w] = v
                    nxt.append(w)
        frontier = nxt
    raise AssertionError(f"{start} is on no cycle of {sorted(comp)}")


def check_sources(files: Mapping[str, str]) -> dict[str, list[str]]:
    """All four rules over ``files`` (repository path -> source); the rule name -> its violations."""
    known = {module_name(p)[0] for p in files}
    imports = [imp for p, src in files.items() for imp in imports_of(p, src, known)]
    return {
        "layers": layer_violations(imports),
        "simulators": sim_violations(imports),
        "cycles": cycle_violations(imports),
        "floors": floor_violations(imports),
    }


def _repository_sources() -> dict[str, str]:
    return {
        str(p.relative_to(REPO)): p.read_text(encoding="utf-8")
        for root in ROOTS
        for p in sorted((REPO / root).rglob("*.py"))
    }


@pytest.fixture(scope="module")
def repository() -> tuple[dict[str, str], list[Import]]:
    files = _repository_sources()
    known = {module_name(p)[0] for p in files}
    return files, [imp for p, src in files.items() for imp in imports_of(p, src, known)]


def test_the_checker_reads_the_whole_tree(repository) -> None:
    files, imports = repository
    for must in ("cellctl/daemon/service.py", "drivers/abb_egm/sim/egm.py", "analysis/pipeline.py"):
        assert must in files
    assert len(files) > 80 and len(imports) > 300, (len(files), len(imports))
    pairs = {(node_of(i.importer), node_of(i.target)) for i in imports}
    # known edges, one of them from an import inside a function
    assert ("cellctl.planning", "cellctl.motion") in pairs
    assert ("cellctl.commands", "cellctl.simcell") in pairs
    assert ("drivers.abb_egm.sim", "drivers.abb_egm") in pairs
    assert ("drivers.laser.sim", "drivers.sim") in pairs  # the simulators' shared fault channel


def test_the_simulators_shared_fault_channel_is_in_their_wing(repository) -> None:
    files, imports = repository
    assert "drivers/sim/fault_channel.py" in files and "drivers/fault_channel.py" not in files
    assert is_sim("drivers.sim.fault_channel") and node_of("drivers.sim.fault_channel") == "drivers.sim"
    importers = {i.importer for i in imports if i.target == "drivers.sim.fault_channel"}
    assert importers == {"drivers.abb_egm.sim.controller", "drivers.laser.sim.sensor"}, importers


def test_drivers_and_analysis_import_neither_cellctl_nor_each_other(repository) -> None:
    violations = layer_violations(repository[1])
    assert not violations, "\n".join(violations)


def test_production_code_imports_no_simulator(repository) -> None:
    violations = sim_violations(repository[1])
    assert not violations, "\n".join(violations)


def test_packages_do_not_import_each_other_in_a_circle(repository) -> None:
    violations = cycle_violations(repository[1])
    assert not violations, "\n".join(violations)


def test_the_contract_the_worker_and_the_job_store_import_only_their_floors(repository) -> None:
    violations = floor_violations(repository[1])
    assert not violations, "\n".join(violations)


def test_the_packages_hold_what_they_say(repository) -> None:
    """Issue 45: the worker, the job dispatch and the job store have packages of their own; api/
    keeps the contract (keys, models, codec, session) and no side of the job protocol: of the
    transfer, what one side alone does (serving designs, collecting and storing results, the design
    cache) lives on that side."""
    files, _ = repository
    for module in ("settings", "child", "process", "service", "heap", "design_cache"):
        assert f"cellctl/worker/{module}.py" in files
    for module in ("jobs", "records", "history", "rawstore"):
        assert f"cellctl/jobstore/{module}.py" in files
    for module in ("dispatch", "design_server", "result_collector"):
        assert f"cellctl/daemon/{module}.py" in files
    one_side = {"DesignServer", "ResultCollector", "store_results", "cache_design", "cached_design"}
    defined = {n.name for n in ast.parse(files["cellctl/api/transfer.py"]).body if hasattr(n, "name")}
    assert not defined & one_side, f"cellctl/api/transfer.py defines {sorted(defined & one_side)}"
    gone = ("cellctl/worker.py", "cellctl/heap.py", "cellctl/api/dispatch.py", "cellctl/daemon/jobs.py",
            "cellctl/daemon/history.py", "cellctl/daemon/records.py", "cellctl/acquisition/rawstore.py")  # fmt: skip
    assert not [p for p in gone if p in files]
    held = {p.removeprefix("cellctl/api/") for p in files if p.startswith("cellctl/api/")}
    assert held == CONTRACT_MODULES, (
        f"cellctl/api/ holds {sorted(held - CONTRACT_MODULES)} beyond the contract"
    )


def test_analysis_is_grouped_by_stage_design_input_and_contracts(repository) -> None:
    files, imports = repository
    for group, modules in {
        "register": ("transforms", "height_field", "coarse", "icp", "onesided", "fit", "locate"),
        "design": ("mesh", "cad", "cad_write", "outline", "moulded", "template_table", "plates"),
        "contracts": ("job", "settings", "placement", "results"),
        "report": ("load", "plots", "text", "html_page", "pdf", "csv_table", "write"),
    }.items():
        for m in modules:
            assert f"analysis/{group}/{m}.py" in files and f"analysis/{m}.py" not in files, (group, m)
    assert "analysis/register.py" not in files
    violations = analysis_group_violations(imports)
    assert not violations, "\n".join(violations)


def test_checker_finds_analysis_design_input_importing_a_stage() -> None:
    files = {
        "analysis/design/outline.py": "from analysis.templates import DetectionLine\n",
        "analysis/templates.py": "from analysis.design.mesh import TriMesh\n",
        "analysis/design/mesh.py": "",
        "analysis/register/fit.py": "from analysis.design.mesh import TriMesh\nimport analysis.pipeline\n",
        "analysis/pipeline.py": "",
    }
    known = {module_name(p)[0] for p in files}
    found = analysis_group_violations([i for p, src in files.items() for i in imports_of(p, src, known)])
    assert [f.split(": ")[0] for f in found] == ["analysis/design/outline.py:1", "analysis/register/fit.py:2"]


def test_every_pending_exception_is_still_needed(repository) -> None:
    found = {(i.importer, i.target) for i in repository[1]}
    stale = [f"{k[0]} -> {k[1]} ({why})" for k, why in PENDING.items() if k not in found]
    assert not stale, "no longer imported: remove from PENDING: " + "; ".join(stale)


# ------------------------------------------------------------------------ the checker on planted code


def test_checker_finds_a_driver_importing_cellctl_inside_a_function() -> None:
    found = check_sources(
        {
            "drivers/laser/client.py": "import numpy\n\n\ndef f():\n    from cellctl.config import load_config\n",
            "cellctl/config.py": "",
        }
    )
    assert found["layers"] == [
        "drivers/laser/client.py:5: drivers.laser.client imports cellctl.config: "
        "drivers never imports cellctl (cellctl composes drivers and analysis)"
    ]


def test_checker_finds_analysis_and_drivers_importing_each_other() -> None:
    found = check_sources(
        {
            "analysis/segment.py": "import drivers.laser.protocol\n",
            "drivers/laser/protocol.py": "",
            "drivers/abb_egm/kinematics.py": "import importlib\nm = importlib.import_module('analysis.mesh')\n",
            "analysis/mesh.py": "",
        }
    )
    assert len(found["layers"]) == 2
    assert found["layers"][0].startswith(
        "analysis/segment.py:1: analysis.segment imports drivers.laser.protocol"
    )
    assert found["layers"][1].startswith("drivers/abb_egm/kinematics.py:2: ")


def test_checker_finds_production_code_importing_a_simulator() -> None:
    found = check_sources(
        {
            "drivers/abb_egm/rws_client.py": "from .sim import model\n",
            "drivers/abb_egm/sim/__init__.py": "",
            "drivers/abb_egm/sim/model.py": "from drivers.abb_egm.rapid_values import format_num\n",
            "drivers/abb_egm/rapid_values.py": "",
            "cellctl/daemon/service.py": "def g():\n    from cellctl.simcell.service import main_sync\n",
            "cellctl/simcell/service.py": "from drivers.laser.sim.sensor import LaserSimulator\n",
            "drivers/laser/sim/sensor.py": "",
            "cellctl/commands/sim_cmd.py": "from cellctl.simcell.service import main_sync\n",
        }
    )
    sims = found["simulators"]
    assert [s.split(": ")[0:2] for s in sims] == [
        ["drivers/abb_egm/rws_client.py:1", "drivers.abb_egm.rws_client imports drivers.abb_egm.sim.model"],
        ["cellctl/daemon/service.py:2", "cellctl.daemon.service imports cellctl.simcell.service"],
    ]


def test_checker_finds_production_code_importing_the_simulators_shared_wing() -> None:
    found = check_sources(
        {
            "drivers/sim/__init__.py": "",
            "drivers/sim/fault_channel.py": "import json\n",
            "drivers/laser/sim/sensor.py": "from drivers.sim.fault_channel import start_fault_server\n",
            "drivers/abb_egm/sim/controller.py": "from drivers.sim import fault_channel\n",
            "drivers/runtime.py": "def f():\n    from drivers.sim.fault_channel import send_fault_request\n",
            "cellctl/daemon/service.py": "import drivers.sim.fault_channel\n",
        }
    )
    assert [s.split(": ")[0:2] for s in found["simulators"]] == [
        ["drivers/runtime.py:2", "drivers.runtime imports drivers.sim.fault_channel"],
        ["cellctl/daemon/service.py:1", "cellctl.daemon.service imports drivers.sim.fault_channel"],
    ]
    assert found["layers"] == [] and found["cycles"] == []


def test_checker_finds_a_cycle_between_packages_and_names_each_import() -> None:
    found = check_sources(
        {
            "cellctl/planning/planner.py": "from cellctl.motion.envelope import SafetyEnvelope\n",
            "cellctl/motion/envelope.py": "",
            "cellctl/motion/executor.py": "import os\n\n\ndef run():\n    from cellctl.planning import plan\n",
            "cellctl/planning/__init__.py": "",
            "cellctl/planning/plan.py": "",
            "cellctl/config.py": "",
            "cellctl/daemon/service.py": "import cellctl.config\nimport cellctl.planning.plan\n",
        }
    )
    assert found["cycles"] == [
        "import cycle between packages cellctl.motion -> cellctl.planning -> cellctl.motion "
        "(cellctl/motion/executor.py:5: cellctl.motion.executor imports cellctl.planning.plan; "
        "cellctl/planning/planner.py:1: cellctl.planning.planner imports cellctl.motion.envelope)"
    ]


def test_checker_passes_a_tree_that_keeps_the_rules() -> None:
    found = check_sources(
        {
            "drivers/abb_egm/codec.py": "from . import egm_pb2\n",
            "drivers/abb_egm/egm_pb2.py": "",
            "drivers/abb_egm/sim/egm.py": "from drivers.abb_egm.codec import decode\n",
            "analysis/register.py": "from analysis.mesh import TriMesh\n",
            "analysis/mesh.py": "",
            "cellctl/motion/executor.py": "from drivers.abb_egm.codec import decode\n",
            "cellctl/planning/planner.py": "from cellctl.motion import executor\nimport analysis.register\n",
        }
    )
    assert found == {"layers": [], "simulators": [], "cycles": [], "floors": []}


def test_checker_finds_a_floor_package_importing_above_its_floor() -> None:
    found = check_sources(
        {
            "cellctl/api/session.py": "def f():\n    from cellctl.daemon.dispatch import Dispatcher\n",
            "cellctl/daemon/dispatch.py": "from cellctl.api.session import subscribe\n",
            "cellctl/worker/service.py": "from cellctl.api.keys import Keys\nimport cellctl.jobstore.jobs\n",
            "cellctl/jobstore/jobs.py": "from cellctl.api.models import JobState\n",
            "cellctl/api/keys.py": "import cellctl.config\n",
            "cellctl/api/models.py": "",
            "cellctl/config.py": "",
        }
    )
    assert found["floors"] == [
        "cellctl/api/session.py:2: cellctl.api.session imports cellctl.daemon.dispatch: "
        "cellctl.api imports of cellctl only cellctl.config (docs/architecture.md)",
        "cellctl/worker/service.py:2: cellctl.worker.service imports cellctl.jobstore.jobs: "
        "cellctl.worker imports of cellctl only cellctl.api, cellctl.config (docs/architecture.md)",
    ]
