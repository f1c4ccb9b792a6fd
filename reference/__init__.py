"""Independent implementations that cdrl's programs are checked and timed against: the eager
PyTorch model (`torch_model`). Not part of the installed library; import it from the
repository root (pytest's `pythonpath`, or a script that puts the root on `sys.path`)."""
