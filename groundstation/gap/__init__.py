"""Sim-to-real gap diagnosis: locate, attribute and shrink the model's departures from flight data (pure)."""
