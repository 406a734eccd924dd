"""Trends across flights: per-parameter and per-effect series over a campaign and a change test.

:mod:`groundstation.trends.change` is pure numpy (no IO): series in flight order with their
standard errors in, a verdict per series out. Reading the campaign table and drawing the trends are
the ``campaign`` command's (:mod:`groundstation.campaign`).
"""
