"""benchmarks/layer_timings.py: the bfloat16 rows compute in bfloat16 and the ratios read the
right way round (time over time, > 1: the second faster)."""
import types

import jax
import jax.numpy as jnp
import numpy as np

import benchmark_scripts

lt = benchmark_scripts.load("layer_timings")


def test_the_bfloat16_layer_runs_in_bfloat16_and_deviates_from_float32_by_its_rounding():
    from cdrl.models.arch import preset

    name, kind, spec, c_in, c_out, size, selu = lt._layers(preset("tiny"))[1]  # a strided encoder layer
    fwd, fwd_bwd = lt._cdrl_layer(kind, spec, selu, input_grad=True)
    rng = np.random.default_rng(0)
    x = jnp.asarray(rng.standard_normal((4, size, size, c_in)), jnp.float32)
    k = jnp.asarray(rng.standard_normal((spec.kernel, spec.kernel, c_in, c_out)) * 0.3, jnp.float32)
    b = jnp.asarray(rng.standard_normal(c_out) * 0.1, jnp.float32)
    ct = jnp.ones_like(fwd(x, k, b))
    fns = {}
    extra = lt._bf16_fns(fns, fwd, fwd_bwd, (x, k, b), (ct,))
    assert fns["cdrl_bf16"]["fwd"]().dtype == jnp.bfloat16
    assert all(g.dtype == jnp.bfloat16 for g in jax.tree.leaves(fns["cdrl_bf16"]["fwd_bwd"]()))
    # bfloat16 keeps 8 bits of mantissa: a relative error of order 2^-8, never zero here.
    assert 1e-4 < extra["bf16_max_rel_dev"] < 0.05


def test_time_pairs_ratios_are_reference_time_over_time(monkeypatch):
    ms = {"cdrl": {"fwd": 2.0, "fwd_bwd": 6.0}, "torch": {"fwd": 4.0, "fwd_bwd": 9.0},
          "cdrl_bf16": {"fwd": 1.0, "fwd_bwd": 12.0}}
    fns = {fw: {p: (fw, p) for p in passes} for fw, passes in ms.items()}
    monkeypatch.setattr(lt, "_median_time", lambda fn, inner: ms[fn[0]][fn[1]] / 1e3)
    out = lt._time_pairs(fns, types.SimpleNamespace(repeats=3, inner=1))
    assert np.isclose(out["cdrl"]["bwd_ms"], 4.0) and np.isclose(out["cdrl_bf16"]["bwd_ms"], 11.0)
    assert np.isclose(out["ratio_fwd"], 2.0) and np.isclose(out["ratio_fwd_bwd"], 1.5)  # torch / cdrl
    assert np.isclose(out["ratio_bf16"], 0.5)  # cdrl float32 / cdrl bfloat16: bfloat16 twice as slow
    assert np.allclose(out["ratio_bf16_repeats"], [0.5] * 3)
