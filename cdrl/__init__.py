from cdrl import controller, variants  # noqa: F401  (registers every variant)
