"""The `cdrl` command's malloc: which library `CDRL_MALLOC` picks, the environment it re-executes
with, and the re-execution itself (a harmless system library preloaded in place of tcmalloc,
so that the test runs where tcmalloc is not installed)."""
import ctypes
import json
import os
import subprocess
import sys

import pytest

from cdrl import cli
from cdrl.runs.allocator import PRELOADED_ENV, allocator_library, preload_environment

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="LD_PRELOAD and /proc are Linux's")


def _harmless_library() -> str:
    """The path of glibc's libanl, which Python does not load by itself."""
    try:
        ctypes.CDLL("libanl.so.1")
    except OSError:
        pytest.skip("no libanl.so.1 (not glibc)")
    with open("/proc/self/maps") as maps:
        return next(line.split()[-1] for line in maps if "libanl" in line)


def test_the_choice_of_library(tmp_path):
    assert allocator_library("system") is None
    lib = tmp_path / "libmymalloc.so"
    lib.write_bytes(b"")
    assert allocator_library(str(lib)) == str(lib)
    with pytest.raises(ValueError, match=r"CDRL_MALLOC='/no/such/libtcmalloc.so'.*no such file"):
        allocator_library("/no/such/libtcmalloc.so")


def test_the_environment_to_reexecute_with():
    env = preload_environment({"LD_PRELOAD": "/opt/a.so /opt/b.so", "HOME": "/h"}, "libtcmalloc_minimal.so.4")
    assert env == {"LD_PRELOAD": "libtcmalloc_minimal.so.4:/opt/a.so:/opt/b.so", "HOME": "/h",
                   PRELOADED_ENV: "libtcmalloc_minimal.so.4", "TCMALLOC_LARGE_ALLOC_REPORT_THRESHOLD": str(2**40)}
    assert preload_environment({}, None) is None  # the system's malloc
    assert preload_environment({PRELOADED_ENV: "x.so"}, "libtcmalloc_minimal.so.4") is None  # re-executed already
    assert preload_environment({"LD_PRELOAD": "/usr/lib/libtcmalloc_minimal.so.4"}, "libtcmalloc_minimal.so.4") is None


SNIPPET = """
import json, os, sys
from cdrl.runs.allocator import reexec_with_allocator
reexec_with_allocator()
with open("/proc/self/maps") as maps:
    mapped = os.path.basename(os.environ["WANT"]) in maps.read()
print(json.dumps({"preloaded": os.environ.get("CDRL_MALLOC_PRELOADED"), "mapped": mapped, "args": sys.argv[1:]}))
"""


def test_the_process_reexecutes_once_with_the_library_loaded_and_its_arguments_kept():
    lib = _harmless_library()
    env = {k: v for k, v in os.environ.items() if k not in (PRELOADED_ENV, "LD_PRELOAD")}
    out = subprocess.run([sys.executable, "-c", SNIPPET, "train", "--steps", "3"], capture_output=True, text=True,
                         env={**env, "CDRL_MALLOC": lib, "WANT": lib}, timeout=120)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.strip().splitlines()
    assert len(lines) == 1  # the first process was replaced before it printed
    assert json.loads(lines[0]) == {"preloaded": lib, "mapped": True, "args": ["train", "--steps", "3"]}
    # with the system's malloc nothing is preloaded and nothing re-executes
    out = subprocess.run([sys.executable, "-c", SNIPPET], capture_output=True, text=True,
                         env={**env, "CDRL_MALLOC": "system", "WANT": lib}, timeout=120)
    assert json.loads(out.stdout) == {"preloaded": None, "mapped": False, "args": []}


def test_the_command_names_a_bad_choice(monkeypatch, capsys):
    monkeypatch.setenv("CDRL_MALLOC", "/no/such/lib.so")
    monkeypatch.delenv(PRELOADED_ENV, raising=False)
    assert cli.main() == 2
    assert "CDRL_MALLOC='/no/such/lib.so'" in capsys.readouterr().err
