"""benchmarks/op_profile.py: the trace's operations summed per call and by kind, and each
operation's shape and origin read from a compiled program's text."""

import jax
import jax.numpy as jnp
import pytest

import benchmark_scripts

op = benchmark_scripts.load("op_profile")


def _event(name, dur, ph="X"):
    return {"name": name, "ph": ph, "dur": dur, "pid": 1, "tid": 1, "ts": 0}


def test_operation_times_sum_each_operation_per_call_without_the_runtimes_events():
    events = [
        _event("ynn_fusion.3", 1000), _event("ynn_fusion.3", 3000),  # two threads or two calls
        _event("select_add_fusion.21", 500), _event("ynn_fusion.4", 2000),
        _event("ThunkExecutor::Execute", 90000), _event("CommonPjRtLoadedExecutable::ExecuteHelper", 80000),
        _event("$array.py:298 __float__", 70000), _event("while.5", 60000), _event("PjitFunction(step)", 50000),
        _event("ynn_fusion.3", 4000, ph="i"),  # an instant event: no duration of its own
        {"name": "copy.1", "ph": "X", "pid": 1, "tid": 1, "ts": 0},  # no duration
    ]
    times = op.operation_times(events, calls=2)
    assert times == pytest.approx({"ynn_fusion.3": 2.0, "select_add_fusion.21": 0.25, "ynn_fusion.4": 1.0})
    kinds = op.by_kind(times)
    assert kinds == pytest.approx({"ynn_fusion": 3.0, "select_add_fusion": 0.25})
    assert list(kinds) == ["ynn_fusion", "select_add_fusion"]  # largest first
    assert op.kind("select_exponential-minus-one_fusion.18") == "select_exponential-minus-one_fusion"
    assert op.kind("copy") == "copy"


def test_operation_sources_name_each_instructions_shape_and_jax_operation():
    def f(x, w):
        return jnp.sin(x @ w).sum(axis=0)

    x, w = jnp.ones((64, 32)), jnp.ones((32, 16))
    text = jax.jit(f).lower(x, w).compile().as_text()
    sources = op.operation_sources(text)
    products = [s for s in sources.values() if s["source"].endswith("/dot_general")]
    assert products and all(s["shape"].startswith("f32[64,16]") for s in products)
    sums = [s for s in sources.values() if s["source"].endswith("/reduce_sum")]
    assert sums and any(s["shape"].startswith("f32[16]") for s in sums)
    assert any(s == {"shape": "f32[64,32]{1,0}", "source": "x"} for s in sources.values())  # the argument x
