"""The convolution passes' batching rule: under `vmap` over configurations (a sweep) every pass
equals the unbatched pass run configuration by configuration, in values and gradients, and the
vmapped train step holds no grouped convolution (which XLA's CPU backend runs group by group)."""
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from cdrl.models import TINY, conv, make_variant
from cdrl.runs.config import RunConfig
from cdrl.runs.sweep import Grid, init_sweep, sweep_step_fn
from cdrl.data.stream import Chunk
from jaxprs import equations

CONFIGS = 3


def _layer_loss(kind, x, kernel, stride, padding):
    fn = conv.conv2d if kind == "conv" else conv.conv_transpose
    y = fn(x, kernel, stride, padding)
    return jnp.sum(jnp.sin(y)), y


@pytest.mark.parametrize("kind, c_in, shared_kernel", [("conv", 4, False), ("conv", 1, False), ("conv", 4, True),
                                                       ("transpose", 4, False), ("transpose", 4, True)])
def test_each_pass_under_vmap_equals_the_pass_per_configuration(kind, c_in, shared_kernel):
    """Frames and kernels batched (each configuration its own), or frames alone (a shared
    kernel, folded into the frames): values and both gradients equal the unbatched pass's."""
    rng = np.random.default_rng(0)
    size, k, stride, padding, c_out = (12, 4, 2, 1, 5) if kind == "conv" else (6, 4, 2, 1, 5)
    x = jnp.asarray(rng.normal(size=(CONFIGS, 9, size, size, c_in)), jnp.float32)  # 9 frames: two kernel-gradient tiles
    shape = (k, k, c_in, c_out)
    kernel = jnp.asarray(rng.normal(size=shape if shared_kernel else (CONFIGS,) + shape), jnp.float32)
    grad = jax.value_and_grad(functools.partial(_layer_loss, kind), argnums=(0, 1), has_aux=True)
    ((_, y), (dx, dk)) = jax.jit(jax.vmap(lambda a, b: grad(a, b, stride, padding),
                                          in_axes=(0, None if shared_kernel else 0)))(x, kernel)
    for i in range(CONFIGS):
        ki = kernel if shared_kernel else kernel[i]
        (_, y_i), (dx_i, dk_i) = jax.jit(lambda a, b: grad(a, b, stride, padding))(x[i], ki)
        np.testing.assert_allclose(y[i], y_i, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(dx[i], dx_i, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(dk[i], dk_i, rtol=1e-4, atol=1e-4)


def test_a_vmapped_train_step_holds_no_grouped_convolution():
    variant = make_variant("main", TINY)
    cfgs = Grid(lr=(0.5, 1.0)).configs(RunConfig(variant="main", preset="tiny", batch=2, unroll=3, recipe="tuned"))
    states, hps = init_sweep(variant, cfgs)
    t, b, s = 3, 2, TINY.image_size
    frames = jnp.zeros((len(cfgs), t + 1, b, s, s), jnp.uint8)
    chunks = Chunk(obs=frames[:, :-1], next_obs=frames[:, 1:], action=jnp.zeros((len(cfgs), t, b, 3)),
                   reward=jnp.zeros((len(cfgs), t, b)), is_first=jnp.zeros((len(cfgs), t, b), bool))
    alive = jnp.ones((len(cfgs),), bool)
    jaxpr = jax.make_jaxpr(functools.partial(sweep_step_fn, variant))(states, hps, alive, chunks).jaxpr
    convs = equations(jaxpr, "conv_general_dilated")
    assert convs, "the checker found no convolution at all"
    grouped = [e for e in convs if e.params["feature_group_count"] > 1 or e.params["batch_group_count"] > 1]
    assert not grouped, f"{len(grouped)} of {len(convs)} convolutions are grouped"
