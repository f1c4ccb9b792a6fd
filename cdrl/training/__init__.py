"""Training: the norm-ratio monitor (`monitor`), optimisers and traced hyper-parameters
(`optim`), the pure TBPTT train step (`step`), the host loop (`loop`) and online training
of the controllers against the game (`online`)."""
