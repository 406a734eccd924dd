"""CABC identification of the paper's hover state-space model (pure numpy/scipy, no IO)."""
