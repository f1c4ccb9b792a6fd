"""Training over several devices with `jax.sharding`: meshes, data parallelism, and stacks of
independent problems (a sweep's configurations) laid out over a mesh axis.

A mesh takes the first `count` devices of `jax.devices()` (every device of every process when
`count` is 0), ordered by process, so each process holds one contiguous block of a sharded axis.

- `DataParallel`: one run's B episode streams over the mesh axis `data`. The chunk's batch
  axis and the carry's batch axis are sharded, parameters and optimiser state replicated;
  the loss is a batch mean, so `jax.jit` with these shardings all-reduces the gradients and
  the step computes what the one-device step computes (up to the order of float sums).
- `ConfigAxis`: a sweep's leading config axis over the mesh axis `config` (padded to a
  multiple of the device count); the step runs under `jax.shard_map`, each device training its
  block of configurations with the one-device program and no communication. Each process
  feeds and reads only the configurations it holds (`local`).

With several processes (`jax.distributed`), every process calls the same jitted programs on
global arrays; host data becomes a global array with `jax.make_array_from_callback` (every
process holds the whole value, as a data-parallel run's chunk) or
`multihost_utils.host_local_array_to_global_array` (each process holds its block).
"""
from __future__ import annotations

import dataclasses
import functools
import math

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec as P

from cdrl.training.step import TrainState, train_step_fn

DATA = "data"
CONFIG = "config"


def mesh_devices(count: int) -> list:
    """The first `count` devices (0: all), every process's in process order. Raises
    `ValueError` naming `devices` when there are fewer, or when several processes would not
    all take part."""
    devices = sorted(jax.devices(), key=lambda d: (d.process_index, d.id))
    if count < 0:
        raise ValueError(f"devices must be >= 0 (0: every device), got {count}")
    if count > len(devices):
        raise ValueError(f"devices={count}, but only {len(devices)} {devices[0].platform} device(s) are available "
                         f"over {jax.process_count()} process(es); use --devices {len(devices)} or fewer (0: all)")
    if jax.process_count() > 1 and count not in (0, len(devices)):
        raise ValueError(f"devices={count} leaves processes out: {jax.process_count()} processes hold "
                         f"{len(devices)} devices and every one takes part; use --devices 0 (all)")
    return devices[:count] if count else devices


def device_mesh(count: int, axis: str) -> Mesh:
    """A one-axis mesh of `mesh_devices(count)`."""
    return Mesh(np.array(mesh_devices(count)), (axis,))


def put_global(value, sharding: NamedSharding):
    """A global array of `value` (the same host value on every process) with `sharding`."""
    value = np.asarray(value)
    return jax.make_array_from_callback(value.shape, sharding, lambda index: value[index])


def local_copy(tree):
    """A replicated global pytree as arrays on this process's first device (for host-side
    work: evaluation, logging)."""
    return jax.tree.map(lambda x: x.addressable_data(0), tree)


@dataclasses.dataclass(frozen=True)
class DataParallel:
    """A run's B streams over the mesh axis `data` (see the module docstring)."""

    mesh: Mesh

    @classmethod
    def create(cls, devices: int, batch: int) -> "DataParallel | None":
        """The layout of a run with `devices` devices (0: all); None for one device, whose
        run keeps the one-device program. `ValueError` when B does not split evenly."""
        mesh = device_mesh(devices, DATA)
        if mesh.size == 1:
            return None
        if batch % mesh.size:
            raise ValueError(f"batch {batch} does not split over {mesh.size} devices: data-parallel training gives "
                             f"each device B / devices episode streams, so --batch must be a multiple of {mesh.size}")
        return cls(mesh)

    @property
    def replicated(self) -> NamedSharding:
        return NamedSharding(self.mesh, P())

    def state_shardings(self, state: TrainState) -> TrainState:
        """Parameters, optimiser state and step replicated; the carry sharded on its batch axis."""
        batch = NamedSharding(self.mesh, P(DATA))
        return TrainState(params=jax.tree.map(lambda _: self.replicated, state.params),
                          opt_state=jax.tree.map(lambda _: self.replicated, state.opt_state),
                          carry=jax.tree.map(lambda _: batch, state.carry), step=self.replicated)

    def place_state(self, state: TrainState) -> TrainState:
        return jax.tree.map(put_global, state, self.state_shardings(state))

    def place(self, tree):
        """Hyper-parameters (or any small pytree) replicated on every device."""
        return jax.tree.map(lambda x: put_global(x, self.replicated), tree)

    def place_chunk(self, chunk):
        """A time-major chunk [T, B, ...] with its batch axis sharded."""
        sharding = NamedSharding(self.mesh, P(None, DATA))
        return jax.tree.map(lambda x: put_global(x, sharding), chunk)

    def step(self, variant, state: TrainState):
        """The jitted train step with this layout's shardings (the state donated)."""
        return _data_parallel_step(variant, self.mesh, jax.tree.structure(state),
                                   tuple(jax.tree.leaves(self.state_shardings(state))))


@functools.lru_cache(maxsize=8)
def _data_parallel_step(variant, mesh: Mesh, treedef, leaf_shardings: tuple):
    shardings = jax.tree.unflatten(treedef, leaf_shardings)
    return jax.jit(functools.partial(train_step_fn, variant), donate_argnums=0,
                   out_shardings=(shardings, NamedSharding(mesh, P())))


@dataclasses.dataclass(frozen=True)
class ConfigAxis:
    """A stack of `configs` independent problems over the mesh axis `config`, padded to
    `padded` (a multiple of the device count). `mesh` None: one device, nothing sharded."""

    mesh: Mesh | None
    configs: int

    @classmethod
    def create(cls, devices: int, configs: int) -> "ConfigAxis":
        mesh = device_mesh(devices, CONFIG)
        return cls(mesh if mesh.size > 1 or jax.process_count() > 1 else None, configs)

    @property
    def size(self) -> int:
        return 1 if self.mesh is None else self.mesh.size

    @property
    def padded(self) -> int:
        return math.ceil(self.configs / self.size) * self.size

    @property
    def local(self) -> range:
        """The (padded) indices of the configurations this process holds, in order."""
        if self.mesh is None:
            return range(self.padded)
        per = self.padded // self.size
        mine = [k for k, d in enumerate(self.mesh.devices.flat) if d.process_index == jax.process_index()]
        return range(mine[0] * per, (mine[-1] + 1) * per)

    def owner(self, i: int) -> int:
        """The process that holds configuration `i`."""
        if self.mesh is None:
            return jax.process_index()
        return int(self.mesh.devices.flat[i // (self.padded // self.size)].process_index)

    def to_global(self, local_tree):
        """This process's block (leading axis `len(local)`) as global arrays."""
        if self.mesh is None:
            return local_tree
        return multihost_utils.host_local_array_to_global_array(local_tree, self.mesh, P(CONFIG))

    def to_local(self, global_tree):
        """This process's block of global arrays (the inverse of `to_global`)."""
        if self.mesh is None:
            return global_tree
        return multihost_utils.global_array_to_host_local_array(global_tree, self.mesh, P(CONFIG))

    def replicated_one(self, tree, i: int):
        """Configuration `i` of a global stack, replicated on every device (an all-gather):
        what a checkpoint of several processes saves (`cdrl.runs.sweep`)."""
        return _take_replicated(self.mesh)(tree, i)


def shard_configs(fn, mesh: Mesh):
    """`fn` (a function of arrays with a leading config axis, vmapped over it) run by every
    device of `mesh` on its block of configurations, with no communication."""
    return jax.shard_map(fn, mesh=mesh, in_specs=P(CONFIG), out_specs=P(CONFIG))


@functools.lru_cache(maxsize=4)
def _take_replicated(mesh: Mesh):
    return jax.jit(lambda tree, i: jax.tree.map(lambda x: x[i], tree), out_shardings=NamedSharding(mesh, P()))
