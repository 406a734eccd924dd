"""Frequency-domain identification and verification of the hover model, the way rotorcraft
flight-test engineers work (CIFER-style).

* :mod:`.spectra` - frequency responses from flight data: overlapped tapered windows of several
  lengths combined into one composite estimate, conditioned (multi-input) responses, coherence and
  random error per frequency;
* :mod:`.model_response` - the eq.-8 model's responses (with input delays) on the same frequencies;
* :mod:`.cost` - Tischler's cost J per input-output pair, pass/fail against the usual guidelines;
* :mod:`.metrics` - equivalent time delay from the phase slope, ADS-33 bandwidth and phase delay;
* :mod:`.verify` - everything above for one model and one flight, as one result with its JSON;
* :mod:`.identify` - the eq.-8 parameters (and optional input delays) fitted by minimising J.

Pure numpy/scipy: no files, no plots, no clocks (plots and Rerun output live in
:mod:`groundstation.sinks.bode`, commands in :mod:`groundstation.commands`).
"""


from groundstation.errors import FreqError

__all__ = ["FreqError"]
