"""Benchmarks run by ``groundstation bench NAME``; each module exposes ``add_arguments`` and ``run``."""
