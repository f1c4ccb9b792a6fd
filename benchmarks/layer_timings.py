"""Per-layer forward and backward times of the observation encoder, the LSTM and the decoder:
cdrl's jitted layers against PyTorch's eager `nn.Conv2d` / `nn.ConvTranspose2d` / LSTM loop.

For every layer of the preset's encoder and decoder, at N = T * B frames (what one train step
of `main` pushes through it: `--unroll` T, each `--batches` B), both frameworks get the same
input, weights and output cotangent, and run

  * forward: the layer and its SELU (the decoder's last layer: no SELU);
  * forward + backward: the same, then the gradients of <output, cotangent> with respect to
    the kernel, the bias and the input (not the input for the encoder's first layer, whose
    input is the data: neither framework computes that gradient in training).

backward = (forward + backward) - forward, from the medians. cdrl's functions are
`cdrl.models.conv.conv2d_selu` / `conv_transpose_selu` (the layers as training runs them; the
last decoder layer `conv_transpose` plus its bias), each jitted
on its own; an XLA program of one layer misses the fusions across layers that the whole
train step has, so the sum of the rows is not the step time (the README's train-throughput
table has that). The LSTM row is T steps of the cell over B streams (forward: a
`lax.scan` / a Python loop; backward through time), input projection included.

With `--bf16` every row also times cdrl's same layer on bfloat16 arrays (input, weights and
cotangent cast; the layer computed as XLA's backend computes bfloat16), `ratio_bf16` = float32
time / bfloat16 time (> 1: bfloat16 faster), and its forward's largest deviation from float32's
relative to the output's scale: whether a bfloat16 option would pay on this CPU, layer by layer.

Every repeat times cdrl then torch back to back (`--repeats`, each the median of
`--inner` calls); the table gives medians and the ratio torch time / cdrl time (> 1: cdrl
faster). Prints the table, then ONE JSON line (`--out FILE` writes it there too).

    .venv/bin/python benchmarks/layer_timings.py --out benchmarks/results/layer_timings.json
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from common import emit, spread, warn_if_busy  # noqa: E402


def _parse() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="thesis")
    ap.add_argument("--unroll", type=int, default=32, help="T (frames per stream per step)")
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 8], help="batch sizes B")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--inner", type=int, default=3, help="calls per repeat (their median is the repeat's time)")
    ap.add_argument("--torch-threads", type=int, default=None, help="default os.cpu_count()")
    ap.add_argument("--bf16", action="store_true", help="also time cdrl's layers on bfloat16 arrays")
    ap.add_argument("--onednn", action="store_true",
                    help="also time every convolution with cdrl's oneDNN backend (`--conv onednn`) beside its XLA "
                         "one, after every torch row")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    for name in ("unroll", "repeats", "inner"):
        if getattr(args, name) < 1:
            ap.error(f"--{name} must be >= 1, got {getattr(args, name)}")
    if any(b < 1 for b in args.batches):
        ap.error(f"--batches must be >= 1, got {args.batches}")
    return args


def _median_time(fn, inner: int) -> float:
    ts = []
    for _ in range(inner):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def _layers(arch):
    """(name, kind, spec, c_in, c_out, in_size, selu) for every conv layer, encoder first."""
    from cdrl.models.nets import _decoder_layers

    out, c_in = [], 1
    sizes = arch.encoder_sizes
    for i, spec in enumerate(arch.encoder):
        out.append((f"enc{i}", "conv", spec, c_in, spec.features, sizes[i], True))
        c_in = spec.features
    dec = _decoder_layers(arch)
    dsizes = arch.decoder_sizes
    for i, (spec, ci, co) in enumerate(dec):
        out.append((f"dec{i}", "deconv", spec, ci, co, dsizes[i], i < len(dec) - 1))
    return out


def _cdrl_layer(kind, spec, selu: bool, input_grad: bool, backend: str = "auto"):
    """The layer's jitted forward and forward + backward, its convolution on `backend`
    (`cdrl.models.conv.formulation`)."""
    import jax
    import jax.numpy as jnp

    from cdrl.models import conv

    op = conv.conv2d if kind == "conv" else conv.conv_transpose
    op_selu = conv.conv2d_selu if kind == "conv" else conv.conv_transpose_selu

    def fwd(x, k, b):  # as `cdrl.models.nets` runs the layer
        if selu:
            return op_selu(x, k, b, spec.stride, spec.padding, backend)
        return op(x, k, spec.stride, spec.padding, backend) + b

    def fwd_bwd(x, k, b, ct):
        argnums = (0, 1, 2) if input_grad else (1, 2)
        return jax.grad(lambda *a: jnp.vdot(fwd(*a), ct), argnums=argnums)(x, k, b)

    return jax.jit(fwd), jax.jit(fwd_bwd)


def _torch_layer(kind, spec, c_in, c_out):
    import torch

    cls = torch.nn.Conv2d if kind == "conv" else torch.nn.ConvTranspose2d
    return cls(c_in, c_out, spec.kernel, spec.stride, spec.padding)


def bench_conv(layer, n: int, args, onednn: bool = False) -> dict:
    """One convolution layer: cdrl (XLA's formulation) against torch; with `onednn`, cdrl's
    oneDNN backend against cdrl's XLA formulation instead (no torch: see `main`)."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    import torch
    import torch.nn.functional as F

    name, kind, spec, c_in, c_out, size, selu = layer
    input_grad = name != "enc0"
    rng = np.random.default_rng(0)
    x = rng.standard_normal((n, size, size, c_in), dtype=np.float32)
    out_size = spec.out_size(size) if kind == "conv" else spec.transposed_out_size(size)
    ct = rng.standard_normal((n, out_size, out_size, c_out), dtype=np.float32)
    fwd, fwd_bwd = _cdrl_layer(kind, spec, selu, input_grad)
    tl = _torch_layer(kind, spec, c_in, c_out)
    k_hwio = rng.standard_normal((spec.kernel, spec.kernel, c_in, c_out), dtype=np.float32) * 0.1
    b = np.zeros((c_out,), np.float32)
    with torch.no_grad():  # same weights: HWIO -> OIHW (conv), [kh, kw, in, out] -> [in, out, kh, kw] (deconv)
        w = k_hwio.transpose(3, 2, 0, 1) if kind == "conv" else k_hwio.transpose(2, 3, 0, 1)
        tl.weight.copy_(torch.from_numpy(np.ascontiguousarray(w)))
        tl.bias.zero_()
    jx, jk, jb, jct = (jnp.asarray(a) for a in (x, k_hwio, b, ct))
    tx = torch.from_numpy(np.ascontiguousarray(x.transpose(0, 3, 1, 2))).requires_grad_(input_grad)
    tct = torch.from_numpy(np.ascontiguousarray(ct.transpose(0, 3, 1, 2)))

    def t_fwd():
        with torch.no_grad():
            y = tl(tx)
            return F.selu(y) if selu else y

    def t_fwd_bwd():
        tl.zero_grad(set_to_none=True)
        tx.grad = None
        y = tl(tx)
        y = F.selu(y) if selu else y
        y.backward(tct)

    def c_fwd():
        jax.block_until_ready(fwd(jx, jk, jb))

    def c_fwd_bwd():
        jax.block_until_ready(fwd_bwd(jx, jk, jb, jct))

    fns = {"cdrl": {"fwd": c_fwd, "fwd_bwd": c_fwd_bwd}, "torch": {"fwd": t_fwd, "fwd_bwd": t_fwd_bwd}}
    extra = _bf16_fns(fns, fwd, fwd_bwd, (jx, jk, jb), (jct,)) if args.bf16 and not onednn else {}
    if onednn:  # the same layer with oneDNN's convolutions, checked against XLA's
        o_fwd, o_fwd_bwd = _cdrl_layer(kind, spec, selu, input_grad, "onednn")
        del fns["torch"]
        fns["cdrl_onednn"] = {"fwd": lambda: jax.block_until_ready(o_fwd(jx, jk, jb)),
                              "fwd_bwd": lambda: jax.block_until_ready(o_fwd_bwd(jx, jk, jb, jct))}
        for got, want in zip(jax.tree.leaves(o_fwd_bwd(jx, jk, jb, jct)), jax.tree.leaves(fwd_bwd(jx, jk, jb, jct))):
            np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-3,
                                       atol=1e-3 * float(np.abs(np.asarray(want)).max()))
    # Same function: cdrl's forward equals torch's (a wrong formulation must not be timed).
    np.testing.assert_allclose(np.asarray(fwd(jx, jk, jb)), t_fwd().numpy().transpose(0, 2, 3, 1),
                               rtol=2e-3, atol=2e-3 * float(np.abs(ct).max()))
    for fw in fns.values():
        for f in fw.values():
            f()  # compile / warm up
    return _time_pairs(fns, args) | extra | {
        "layer": name, "kind": kind, "c_in": c_in, "c_out": c_out, "in_size": size, "out_size": out_size,
        "frames": n}


def bench_lstm(arch, T: int, B: int, args) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np
    import torch

    from cdrl.models import nets

    code, H = arch.obs_code, arch.lstm_size
    rng = np.random.default_rng(0)
    k = rng.standard_normal((T, B, code), dtype=np.float32)
    ct = rng.standard_normal((T, B, H), dtype=np.float32)
    params = nets.init_lstm(jax.random.PRNGKey(0), code, H)

    def unroll(p, ks):
        def body(s, x):
            s = nets.lstm_cell(p, s, x)
            return s, s.h
        return jax.lax.scan(body, nets.lstm_zeros(B, H), ks)[1]

    fwd = jax.jit(unroll)
    fwd_bwd = jax.jit(jax.grad(lambda p, ks, c: jnp.vdot(unroll(p, ks), c), argnums=(0, 1)))
    jk, jct = jnp.asarray(k), jnp.asarray(ct)
    tw_in = torch.from_numpy(np.asarray(params["w_input"])).requires_grad_(True)
    tw_rec = torch.from_numpy(np.asarray(params["w_recurrent"])).requires_grad_(True)
    tb = torch.from_numpy(np.asarray(params["bias"])).requires_grad_(True)
    tk = torch.from_numpy(k).requires_grad_(True)
    tct = torch.from_numpy(ct)

    def t_unroll():
        h = c = torch.zeros(B, H)
        xs = tk @ tw_in
        hs = []
        for t in range(T):
            z = xs[t] + h @ tw_rec + tb
            f, i, o, u = z.chunk(4, dim=-1)
            c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(u)
            h = torch.sigmoid(o) * torch.tanh(c)
            hs.append(h)
        return torch.stack(hs)

    def t_fwd():
        with torch.no_grad():
            t_unroll()

    def t_fwd_bwd():
        for p in (tw_in, tw_rec, tb, tk):
            p.grad = None
        t_unroll().backward(tct)

    def c_fwd():
        jax.block_until_ready(fwd(params, jk))

    def c_fwd_bwd():
        jax.block_until_ready(fwd_bwd(params, jk, jct))

    fns = {"cdrl": {"fwd": c_fwd, "fwd_bwd": c_fwd_bwd}, "torch": {"fwd": t_fwd, "fwd_bwd": t_fwd_bwd}}
    extra = _bf16_fns(fns, fwd, fwd_bwd, (params, jk), (jct,)) if args.bf16 else {}
    with torch.no_grad():
        np.testing.assert_allclose(np.asarray(fwd(params, jk)), t_unroll().numpy(), rtol=1e-4, atol=1e-4)
    for fw in fns.values():
        for f in fw.values():
            f()
    return _time_pairs(fns, args) | extra | {
        "layer": "lstm", "kind": "lstm", "c_in": code, "c_out": H, "in_size": 1, "out_size": 1, "frames": T * B}


def _bf16_fns(fns: dict, fwd, fwd_bwd, inputs: tuple, cotangents: tuple) -> dict:
    """Add cdrl's layer on bfloat16 copies of `inputs` and `cotangents` to `fns` (as
    "cdrl_bf16"); returns its forward's largest deviation from float32's, relative to the
    largest float32 output."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    def half(tree):
        return jax.tree.map(lambda a: a.astype(jnp.bfloat16), tree)

    h_in, h_ct = half(inputs), half(cotangents)
    fns["cdrl_bf16"] = {"fwd": lambda: jax.block_until_ready(fwd(*h_in)),
                        "fwd_bwd": lambda: jax.block_until_ready(fwd_bwd(*h_in, *h_ct))}
    full = np.asarray(fwd(*inputs), np.float32)
    low = np.asarray(fwd(*h_in).astype(jnp.float32))
    return {"bf16_max_rel_dev": float(np.abs(low - full).max() / max(float(np.abs(full).max()), 1e-12))}


def _time_pairs(fns: dict, args) -> dict:
    """Alternating repeats of each framework's {"fwd", "fwd_bwd"} functions (cdrl, torch, and
    cdrl_bf16 where given); per framework and pass the median time in ms and its spread."""
    times = {(fw, p): [] for fw in fns for p in ("fwd", "fwd_bwd")}
    for _ in range(args.repeats):
        for p in ("fwd", "fwd_bwd"):
            for fw in fns:
                times[(fw, p)].append(_median_time(fns[fw][p], args.inner))
    out = {}
    for fw in fns:
        f = statistics.median(times[(fw, "fwd")])
        fb = statistics.median(times[(fw, "fwd_bwd")])
        out[fw] = {"fwd_ms": 1e3 * f, "bwd_ms": 1e3 * (fb - f), "fwd_bwd_ms": 1e3 * fb,
                   "fwd_bwd_ms_spread": {k: 1e3 * v for k, v in spread(times[(fw, "fwd_bwd")]).items()}}
    if "torch" in fns:
        out["ratio_fwd"] = out["torch"]["fwd_ms"] / out["cdrl"]["fwd_ms"]
        out["ratio_fwd_bwd"] = out["torch"]["fwd_bwd_ms"] / out["cdrl"]["fwd_bwd_ms"]
        out["ratio_fwd_bwd_repeats"] = [t / c for c, t in zip(times[("cdrl", "fwd_bwd")], times[("torch", "fwd_bwd")])]
    if "cdrl_onednn" in fns:  # > 1: oneDNN's convolutions faster than XLA's
        out["ratio_onednn_vs_xla"] = out["cdrl"]["fwd_bwd_ms"] / out["cdrl_onednn"]["fwd_bwd_ms"]
        out["ratio_onednn_vs_xla_repeats"] = [x / o for x, o in zip(times[("cdrl", "fwd_bwd")],
                                                                     times[("cdrl_onednn", "fwd_bwd")])]
    if "cdrl_bf16" in fns:
        out["ratio_bf16"] = out["cdrl"]["fwd_bwd_ms"] / out["cdrl_bf16"]["fwd_bwd_ms"]
        out["ratio_bf16_repeats"] = [c / h for c, h in zip(times[("cdrl", "fwd_bwd")], times[("cdrl_bf16", "fwd_bwd")])]
    return out


def main() -> None:
    args = _parse()
    import jax
    import torch

    from cdrl.models.arch import preset

    torch.set_num_threads(args.torch_threads or os.cpu_count() or 1)
    arch = preset(args.preset)
    load_start = os.getloadavg()[0]
    rows = []
    for B in args.batches:
        n = args.unroll * B
        for layer in _layers(arch):
            rows.append(bench_conv(layer, n, args) | {"batch": B})
            _print_row(rows[-1])
        rows.append(bench_lstm(arch, args.unroll, B, args) | {"batch": B})
        _print_row(rows[-1])
    if args.onednn:
        # After every torch row: PyTorch shares oneDNN's OpenMP runtime, and the OpenMP teams that
        # oneDNN starts from XLA's threads make it throttle PyTorch's spin-waits from then on.
        for B in args.batches:
            for layer in _layers(arch):
                row = next(r for r in rows if r["batch"] == B and r["layer"] == layer[0])
                beside = bench_conv(layer, args.unroll * B, args, onednn=True)
                row.update(cdrl_onednn=beside["cdrl_onednn"], cdrl_beside_onednn=beside["cdrl"],
                           ratio_onednn_vs_xla=beside["ratio_onednn_vs_xla"],
                           ratio_onednn_vs_xla_repeats=beside["ratio_onednn_vs_xla_repeats"],
                           ratio_onednn_fwd_bwd=row["torch"]["fwd_bwd_ms"] / beside["cdrl_onednn"]["fwd_bwd_ms"])
                _print_onednn_row(row)
    res = {"benchmark": "layer_timings", "preset": args.preset, "unroll": args.unroll, "batches": args.batches,
           "repeats": args.repeats, "inner": args.inner, "cpu_count": os.cpu_count(),
           "torch_threads": torch.get_num_threads(), "jax_version": jax.__version__, "bf16": args.bf16,
           "cpu_bf16_support": _cpu_bf16_flags(), "onednn": args.onednn,
           "torch_version": torch.__version__, "load_avg_start": load_start, "rows": rows}
    for B in args.batches:
        sel = [r for r in rows if r["batch"] == B]
        res[f"total_B{B}"] = {fw: sum(r[fw]["fwd_bwd_ms"] for r in sel) for fw in ("cdrl", "torch", "cdrl_bf16")
                              if fw in sel[0]}
        if args.onednn:  # the LSTM row has no convolution: its XLA time
            res[f"total_B{B}"]["cdrl_onednn"] = sum(r.get("cdrl_onednn", r["cdrl"])["fwd_bwd_ms"] for r in sel)
        print(f"B {B}: sum of rows fwd+bwd: cdrl {res[f'total_B{B}']['cdrl']:.1f} ms, "
              f"torch {res[f'total_B{B}']['torch']:.1f} ms"
              + (f", cdrl in bfloat16 {res[f'total_B{B}']['cdrl_bf16']:.1f} ms" if args.bf16 else "")
              + (f", cdrl on oneDNN {res[f'total_B{B}']['cdrl_onednn']:.1f} ms" if args.onednn else ""))
    res["load_avg_end"] = os.getloadavg()[0]
    warn_if_busy(res, load_start, res["load_avg_end"])
    emit(res, args.out)


def _cpu_bf16_flags() -> list[str]:
    """This CPU's bfloat16 instructions (AVX-512 BF16, AMX) as Linux lists them; [] elsewhere."""
    try:
        flags = next(line for line in Path("/proc/cpuinfo").read_text().splitlines() if line.startswith("flags"))
    except (OSError, StopIteration):
        return []
    return sorted(f for f in flags.split(":", 1)[1].split() if f in ("avx512_bf16", "amx_bf16", "amx_tile"))


def _print_onednn_row(r: dict) -> None:
    o, x = r["cdrl_onednn"], r["cdrl_beside_onednn"]
    print(f"B {r['batch']:2d} {r['layer']:6s} oneDNN fwd {o['fwd_ms']:7.2f} bwd {o['bwd_ms']:7.2f} ms | beside it XLA "
          f"fwd {x['fwd_ms']:7.2f} bwd {x['bwd_ms']:7.2f} ms | fwd+bwd XLA/oneDNN {r['ratio_onednn_vs_xla']:5.2f}, "
          f"torch/oneDNN {r['ratio_onednn_fwd_bwd']:5.2f}", flush=True)


def _print_row(r: dict) -> None:
    c, t = r["cdrl"], r["torch"]
    half = (f" | bf16 fwd+bwd {r['cdrl_bf16']['fwd_bwd_ms']:7.2f} ms, f32/bf16 {r['ratio_bf16']:5.2f}"
            if "cdrl_bf16" in r else "")
    print(f"B {r['batch']:2d} {r['layer']:6s} {r['c_in']:4d}->{r['c_out']:<4d} {r['in_size']:3d}->{r['out_size']:<3d} "
          f"fwd cdrl {c['fwd_ms']:7.2f} torch {t['fwd_ms']:7.2f} ms | bwd cdrl {c['bwd_ms']:7.2f} "
          f"torch {t['bwd_ms']:7.2f} ms | fwd+bwd torch/cdrl {r['ratio_fwd_bwd']:5.2f}{half}", flush=True)


if __name__ == "__main__":
    main()
