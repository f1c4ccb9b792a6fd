"""An eager PyTorch re-implementation of the cdrl variants `main` and `closed_loop_minus`.

It exists to pin cdrl's JAX programs against an independent implementation (same weights
and data give the same loss, gradients and carries: tests/test_torch_reference.py) and to
give the benchmarks a conventional baseline (benchmarks/train_throughput.py and
experiments/learning/time_to_quality.py). Import it from the repository root as
`from reference import torch_model`; it needs the `bench` extra (torch).

For any `cdrl.models.arch.ArchConfig`:

- observation encoder: (frames - arch.obs_mean) / arch.obs_std, then the `arch.encoder`
  conv table (`nn.Conv2d`), SELU after every layer;
- observation decoder: its mirror of `nn.ConvTranspose2d` (PyTorch padding semantics),
  SELU inside, logits at the output (loss: BCE with logits, averaged over every pixel of
  every predicted frame of the chunk);
- core: one LSTM (gate order forget, input, output, update along the 4*H axis;
  z = x @ w_input + h @ w_recurrent + bias, kept in cdrl's [in, 4H] layout) followed by the
  FC layer (one dense layer + SELU);
- `main`: k_t = E_o(o_t); h_t = LSTM(k_t); d_{t+1} = FC(h_t); õ_{t+1} = D_o(d_{t+1}). As in
  cdrl (and because it is the fast eager formulation too), the encoder runs over all T*B
  frames at once, then the LSTM loop, then the decoder over all T*B codes at once;
- `closed_loop_minus`: x_t = o_t - sigmoid(previous logits) (õ_0 = 0), then main on x_t;
  the fed-back prediction keeps its gradient, so the encoder and decoder run inside the
  time loop;
- episode starts (`is_first[t, b]`) reset stream b's carry (LSTM state and, for the closed
  loop, the fed-back prediction) to zeros before step t; the incoming carry of a chunk is
  detached (truncated BPTT).

Carries are tuples: `(h, c)` for main, `(h, c, pred_obs)` for closed_loop_minus;
`carry_from_cdrl` / `carry_to_numpy` convert from / to cdrl's carry pytrees.

The train step is `torch.optim.SGD(lr, momentum)`: buf <- m * buf + g; w <- w - lr * buf,
which is optax.sgd with momentum (cdrl's optimiser). cdrl's step also computes the per-group
norm ratios ||g|| / ||w|| of the divergence monitor and keeps the old state on a non-finite
or diverging step; `train_step(..., monitor=True)` computes the same ratios and the finite
check as tensors (no host round trip) so that the two do comparable work.
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from cdrl.models.arch import ArchConfig

VARIANTS = ("main", "closed_loop_minus")


class TorchModel(nn.Module):
    """`main` or `closed_loop_minus` for the architecture `arch` (see the module docstring)."""

    def __init__(self, arch: ArchConfig, variant_name: str = "main"):
        super().__init__()
        if variant_name not in VARIANTS:
            raise ValueError(f"torch reference has {VARIANTS}, not {variant_name!r}")
        self.arch = arch
        self.variant_name = variant_name
        self.closed_loop = variant_name == "closed_loop_minus"
        chans = [1] + [s.features for s in arch.encoder]
        self.enc = nn.ModuleList(
            nn.Conv2d(chans[i], s.features, s.kernel, s.stride, s.padding) for i, s in enumerate(arch.encoder)
        )
        n = len(arch.encoder)
        self.dec = nn.ModuleList(
            nn.ConvTranspose2d(chans[n - i], chans[n - 1 - i], s.kernel, s.stride, s.padding)
            for i, s in enumerate(reversed(arch.encoder))
        )
        code, hidden = arch.obs_code, arch.lstm_size
        self.w_input = nn.Parameter(torch.zeros(code, 4 * hidden))
        self.w_recurrent = nn.Parameter(torch.zeros(hidden, 4 * hidden))
        self.lstm_bias = nn.Parameter(torch.zeros(4 * hidden))
        self.fc = nn.Linear(hidden, code)

    # ------------------------------------------------------------------ pieces
    def encode(self, frames: torch.Tensor) -> torch.Tensor:
        """Frames `[N, H, W]` -> codes `[N, obs_code]`; they enter as (frames - mean) / std."""
        x = (frames.unsqueeze(1) - self.arch.obs_mean) / self.arch.obs_std
        for conv in self.enc:
            x = F.selu(conv(x))
        return x.reshape(x.shape[0], -1)

    def decode_logits(self, codes: torch.Tensor) -> torch.Tensor:
        """Codes `[N, obs_code]` -> logits `[N, H, W]`."""
        x = codes.reshape(codes.shape[0], codes.shape[1], 1, 1)
        last = len(self.dec) - 1
        for i, deconv in enumerate(self.dec):
            x = deconv(x)
            if i < last:
                x = F.selu(x)
        return x[:, 0]

    def lstm_cell(self, h, c, x_proj):
        """One step; `x_proj` = x @ w_input (the input projection, possibly precomputed)."""
        z = x_proj + h @ self.w_recurrent + self.lstm_bias
        f, i, o, u = z.chunk(4, dim=-1)
        c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(u)
        h = torch.sigmoid(o) * torch.tanh(c)
        return h, c

    def init_carry(self, batch: int):
        z = torch.zeros(batch, self.arch.lstm_size)
        if self.closed_loop:
            s = self.arch.image_size
            return (z, z.clone(), torch.zeros(batch, s, s))
        return (z, z.clone())

    # ------------------------------------------------------------------ unrolls
    def unroll(self, carry, obs: torch.Tensor, is_first: torch.Tensor):
        """Time-major `obs` `[T, B, H, W]`, `is_first` `[T, B]` -> (logits `[T, B, H, W]`, carry)."""
        return (self._unroll_closed if self.closed_loop else self._unroll_main)(carry, obs, is_first)

    def _unroll_main(self, carry, obs, is_first):
        T, B = obs.shape[:2]
        h, c = carry
        ks = self.encode(obs.reshape((T * B,) + obs.shape[2:]))
        xs = (ks @ self.w_input).reshape(T, B, -1)  # input projection of every step at once
        reset = is_first.unsqueeze(-1)  # [T, B, 1]
        zero = h.new_zeros(())
        hs = []
        for t in range(T):
            h, c = torch.where(reset[t], zero, h), torch.where(reset[t], zero, c)
            h, c = self.lstm_cell(h, c, xs[t])
            hs.append(h)
        d = F.selu(self.fc(torch.stack(hs).reshape(T * B, -1)))
        logits = self.decode_logits(d).reshape(obs.shape)
        return logits, (h, c)

    def _unroll_closed(self, carry, obs, is_first):
        T = obs.shape[0]
        h, c, pred = carry
        reset = is_first.unsqueeze(-1)  # [T, B, 1]
        zero = h.new_zeros(())
        out = []
        for t in range(T):
            r = reset[t]
            h, c, pred = torch.where(r, zero, h), torch.where(r, zero, c), torch.where(r.unsqueeze(-1), zero, pred)
            k = self.encode(obs[t] - pred)
            h, c = self.lstm_cell(h, c, k @ self.w_input)
            logits = self.decode_logits(F.selu(self.fc(h)))
            pred = torch.sigmoid(logits)  # fed back with its gradient
            out.append(logits)
        return torch.stack(out), (h, c, pred)


def as_float(frames: torch.Tensor) -> torch.Tensor:
    """uint8 frames to [0, 1]; float frames unchanged (cdrl.data.frames.as_float)."""
    if frames.dtype == torch.uint8:
        return frames.to(torch.float32) / 255.0
    return frames.to(torch.float32)


def chunk_loss(model: TorchModel, carry, obs, next_obs, is_first):
    """cdrl.training.step.chunk_loss: BCE of the chunk's predictions from `carry` (cut: TBPTT).

    Time-major `obs`, `next_obs` `[T, B, H, W]` (float in [0, 1] or uint8), `is_first`
    `[T, B]` bool. Returns `(loss, final_carry)`.
    """
    carry = tuple(x.detach() for x in carry)
    logits, carry = model.unroll(carry, as_float(obs), is_first)
    loss = F.binary_cross_entropy_with_logits(logits, as_float(next_obs))
    return loss, carry


def make_optimizer(model: TorchModel, lr: float = 0.1, momentum: float = 0.9) -> torch.optim.SGD:
    return torch.optim.SGD(model.parameters(), lr=lr, momentum=momentum)


def norm_ratios(model: TorchModel) -> torch.Tensor:
    """||grad|| / ||param|| per parameter tensor (0 where the parameter is all zero), in the
    order of `param_names(model)`."""
    params = [tensor for _, tensor, _, _ in _pairs(model)]
    p_norm = torch.stack(torch._foreach_norm(params))
    g_norm = torch.stack(torch._foreach_norm([p.grad for p in params]))
    return torch.where(p_norm > 0, g_norm / torch.where(p_norm > 0, p_norm, torch.ones_like(p_norm)), 0.0)


def train_step(model, opt, carry, obs, next_obs, is_first, monitor: bool = False):
    """One SGD-momentum step on a chunk. Returns (loss, detached final carry, ratios or None)."""
    opt.zero_grad(set_to_none=True)
    loss, carry = chunk_loss(model, carry, obs, next_obs, is_first)
    loss.backward()
    ratios = None
    if monitor:
        with torch.no_grad():
            ratios = norm_ratios(model)
            ratios = torch.where(torch.isfinite(loss), ratios, torch.inf)
    opt.step()
    return loss.detach(), tuple(x.detach() for x in carry), ratios


# ---------------------------------------------------------------------------- cdrl layout


def _conv_w(kernel) -> np.ndarray:  # HWIO -> OIHW
    return np.asarray(kernel).transpose(3, 2, 0, 1)


def _deconv_w(kernel) -> np.ndarray:  # [kh, kw, in, out] -> ConvTranspose2d [in, out, kh, kw]
    return np.asarray(kernel).transpose(2, 3, 0, 1)


def _pairs(model: TorchModel):
    """(cdrl path, torch tensor, to_torch, to_cdrl) for every parameter."""
    out = []
    for i, conv in enumerate(model.enc):
        out.append((("obs_enc", f"conv{i}", "kernel"), conv.weight, _conv_w, lambda w: w.transpose(2, 3, 1, 0)))
        out.append((("obs_enc", f"conv{i}", "bias"), conv.bias, np.asarray, np.asarray))
    for i, deconv in enumerate(model.dec):
        out.append((("obs_dec", f"deconv{i}", "kernel"), deconv.weight, _deconv_w, lambda w: w.transpose(2, 3, 0, 1)))
        out.append((("obs_dec", f"deconv{i}", "bias"), deconv.bias, np.asarray, np.asarray))
    out.append((("lstm", "w_input"), model.w_input, np.asarray, np.asarray))
    out.append((("lstm", "w_recurrent"), model.w_recurrent, np.asarray, np.asarray))
    out.append((("lstm", "bias"), model.lstm_bias, np.asarray, np.asarray))
    out.append((("fc", "dense0", "kernel"), model.fc.weight, lambda k: np.asarray(k).T, lambda w: w.T))
    out.append((("fc", "dense0", "bias"), model.fc.bias, np.asarray, np.asarray))
    return out


def param_names(model: TorchModel) -> list[str]:
    """cdrl's '/'-joined names of the parameters (e.g. 'obs_enc/conv0/kernel'), in the order
    `norm_ratios` uses."""
    return ["/".join(path) for path, *_ in _pairs(model)]


def _get(tree, path):
    for key in path:
        tree = tree[key]
    return tree


def _put(tree: dict, path, value) -> None:
    for key in path[:-1]:
        tree = tree.setdefault(key, {})
    tree[path[-1]] = value


def load_cdrl_params(model: TorchModel, params) -> TorchModel:
    """Copy a cdrl params pytree (`variant.init(key)`, `state.params`) into `model`."""
    expected = {path for path, *_ in _pairs(model)}
    got = set()

    def walk(tree, prefix=()):
        for k, v in tree.items():
            if isinstance(v, dict):
                walk(v, prefix + (k,))
            else:
                got.add(prefix + (k,))

    walk(params)
    if got != expected:
        raise ValueError(f"parameter trees differ: missing {sorted(expected - got)}, extra {sorted(got - expected)}")
    with torch.no_grad():
        for path, tensor, to_torch, _ in _pairs(model):
            value = torch.from_numpy(np.array(to_torch(np.asarray(_get(params, path))), dtype=np.float32, order="C"))
            if value.shape != tensor.shape:
                raise ValueError(f"{'/'.join(path)}: cdrl shape maps to {tuple(value.shape)}, torch has {tuple(tensor.shape)}")
            tensor.copy_(value)
    return model


def _as_cdrl(model: TorchModel, which) -> dict:
    tree: dict = {}
    for path, tensor, _, to_cdrl in _pairs(model):
        t = which(tensor)
        _put(tree, path, None if t is None else np.ascontiguousarray(to_cdrl(t.detach().cpu().numpy())))
    return tree


def grads_as_cdrl(model: TorchModel) -> dict:
    """The gradients (after `backward`) in cdrl's params layout, as numpy arrays."""
    return _as_cdrl(model, lambda p: p.grad)


def params_as_cdrl(model: TorchModel) -> dict:
    """The parameters in cdrl's params layout, as numpy arrays."""
    return _as_cdrl(model, lambda p: p)


def carry_from_cdrl(carry) -> tuple:
    """cdrl carry (`LSTMState` for main, {'lstm', 'pred_obs'} for closed loops) -> torch tuple."""
    t = lambda x: torch.from_numpy(np.array(x, dtype=np.float32))  # noqa: E731
    if isinstance(carry, dict):
        return (t(carry["lstm"].h), t(carry["lstm"].c), t(carry["pred_obs"]))
    return (t(carry.h), t(carry.c))


def carry_to_numpy(carry) -> tuple:
    return tuple(x.detach().cpu().numpy() for x in carry)
