"""cdrl: closed-loop recurrent world models and controllers in JAX.

Sub-packages, lowest layer first (each imports only from those above it in this list):

- `cdrl.models`: architecture presets, networks, the variants and their registry;
- `cdrl.data`: episodes, on-disk data sets and their collection, T-step chunk streams;
- `cdrl.training`: the norm-ratio monitor, optimisers, the TBPTT train step, the host loop;
- `cdrl.evaluation`: held-out next-frame scores, playing policies;
- `cdrl.learners`: the learners that play the game, one module each behind one interface,
  and their registry;
- `cdrl.runs`: run configs, run directories, checkpoints, offline/online runs, sweeps;
- `cdrl.analysis`: reading finished runs back: tables and the thesis's figures;
- `cdrl.cli`: the `cdrl` command (`cdrl.cli_report`: its `eval` and `plot`).
"""
