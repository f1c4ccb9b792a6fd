"""The scripts of benchmarks/ as modules, for the tests of what they compute.

The studies of experiments/ need no loader: they are a package, and the tests import them from
the repository root (pytest's `pythonpath`), e.g. `from experiments.controller import study`."""
import importlib.util
import sys
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def load(name: str):
    """benchmarks/<name>.py as a module; benchmarks/ goes on sys.path first, since the scripts
    import their neighbours (`common`, `followed_play`, ...)."""
    if str(BENCHMARKS) not in sys.path:
        sys.path.append(str(BENCHMARKS))
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
