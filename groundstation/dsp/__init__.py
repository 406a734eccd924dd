"""Signal processing: alignment onto the FC-clock grid, eq. 18 smoothing, body-frame velocities, windows (pure numpy)."""
