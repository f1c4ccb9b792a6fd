"""The package's layering: no import cycle between cdrl's modules, and each sub-package
imports only from the layers below it (the order in `cdrl/__init__.py`'s docstring)."""
import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent / "cdrl"
LAYERS = ["models", "data", "training", "evaluation", "learners", "runs", "analysis", "cli"]


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def cdrl_imports(path: Path) -> set[str]:
    """Every cdrl module `path` imports, at any depth of the file (lazy imports count)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.startswith("cdrl")}
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("cdrl"):
            # `from cdrl.models import nets` imports the module cdrl.models.nets
            subs = {f"{node.module}.{a.name}" for a in node.names
                    if (ROOT.parent / Path(*node.module.split("."), a.name + ".py")).exists()}
            found |= subs if len(subs) == len(node.names) else subs | {node.module}
    return found


MODULES = {module_name(p): p for p in ROOT.rglob("*.py")}
# A module's own parent packages are imported before it by Python itself: not edges.
GRAPH = {m: {i for i in cdrl_imports(p) if i in MODULES and i != m and not m.startswith(i + ".")}
         for m, p in MODULES.items()}


def layer(module: str) -> int | None:
    parts = module.split(".")
    return LAYERS.index(parts[1]) if len(parts) > 1 and parts[1] in LAYERS else None


def test_no_import_cycle():
    state: dict[str, int] = {}

    def visit(m, path):
        if state.get(m) == 1:
            cycle = path[path.index(m):] + [m]
            pytest.fail("import cycle: " + " -> ".join(cycle))
        if state.get(m) == 2:
            return
        state[m] = 1
        for n in sorted(GRAPH[m]):
            visit(n, path + [m])
        state[m] = 2

    for m in sorted(GRAPH):
        visit(m, [])


def test_subpackages_import_only_lower_layers():
    wrong = [f"{m} imports {n}" for m, deps in GRAPH.items() for n in deps
             if layer(m) is not None and layer(n) is not None and layer(n) > layer(m)]
    assert not wrong, "\n".join(wrong)


def test_the_checker_sees_imports():
    """The graph is not empty by accident: known edges are present."""
    assert "cdrl.models.nets" in GRAPH["cdrl.models.base"]
    assert "cdrl.runs.rundir" in GRAPH["cdrl.runs.offline"]
    assert "cdrl.runs.train" in GRAPH["cdrl.cli"]  # a lazy import inside a function


def test_one_host_loop_serves_every_kind_of_run():
    """Every kind of run steps through `cdrl.training.loop.host_loop`: the offline run, the
    online runs (controllers and PPO), the sweep and `fit`; and only the host loop draws a
    training progress bar (data collection has its own)."""
    def calls(module: str, name: str) -> bool:
        tree = ast.parse(MODULES[module].read_text())
        return any(isinstance(n, ast.Call) and getattr(n.func, "id", getattr(n.func, "attr", None)) == name
                   for n in ast.walk(tree))

    for module in ("cdrl.runs.offline", "cdrl.runs.online", "cdrl.runs.grid", "cdrl.runs.sweep", "cdrl.training.loop"):
        assert calls(module, "host_loop"), f"{module} does not run through host_loop"
    bars = sorted(m for m, p in MODULES.items() if "tqdm" in cdrl_imports_any(p))
    assert bars == ["cdrl.data.collect", "cdrl.training.loop"], bars


def cdrl_imports_any(path: Path) -> set[str]:
    """Top-level names of every module `path` imports."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module.split(".")[0])
    return names


REPO = ROOT.parent
# benchmarks/ measures speed and scaling only; the research studies live in experiments/.
BENCHMARK_SCRIPTS = {"common.py", "env_throughput.py", "layer_timings.py", "malloc_throughput.py", "online_throughput.py",
                     "op_profile.py", "scaling.py", "sweep_throughput.py", "train_throughput.py"}


def repo_modules() -> list[Path]:
    """Every Python module of the repository outside virtual environments and hidden folders."""
    return [p for p in REPO.rglob("*.py")
            if not any(part.startswith(".") or part in ("venv", "build") for part in p.relative_to(REPO).parts)]


def test_benchmarks_hold_throughput_and_scaling_only():
    scripts = {p.name for p in (REPO / "benchmarks").glob("*.py")}
    assert scripts == BENCHMARK_SCRIPTS, f"new in benchmarks/: {sorted(scripts - BENCHMARK_SCRIPTS)}; " \
                                         f"gone: {sorted(BENCHMARK_SCRIPTS - scripts)} (studies go in experiments/)"


def test_each_study_has_its_log_and_its_results_stay_beside_it():
    studies = [p for p in (REPO / "experiments").iterdir() if p.is_dir() and (p / "__init__.py").is_file()]
    assert {p.name for p in studies} >= {"controller", "control_probes", "learning", "world_models"}
    for study in studies:
        log = (study / "LOG.md").read_text()
        for result in (study / "results").glob("*"):
            assert f"results/{result.name}" in log, f"{result} is not named in {study.name}/LOG.md"


def test_no_two_modules_share_a_basename():
    by_name: dict[str, list[str]] = {}
    for p in repo_modules():
        if p.name != "__init__.py":
            by_name.setdefault(p.name, []).append(str(p.relative_to(REPO)))
    shared = {name: paths for name, paths in by_name.items() if len(paths) > 1}
    assert not shared, f"modules that share a basename: {shared}"


def test_the_library_imports_no_study_benchmark_or_reference():
    """cdrl is installed alone (pyproject's package discovery): it cannot import the folders
    that stay in the repository."""
    outside = {"experiments", "benchmarks", "reference"}
    wrong = [str(p.relative_to(REPO)) for p in ROOT.rglob("*.py") if cdrl_imports_any(p) & outside]
    assert not wrong, wrong
