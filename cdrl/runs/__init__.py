"""Runs: a `RunConfig` (`config`), the run directory and its logs (`rundir`), orbax
checkpoints (`checkpoint`), a run's data and game (`sources`), offline and online training
runs (`offline`, `online`), `train_run` choosing between them (`train`), and sweeps of
configurations as one vmapped program (`sweep`)."""
