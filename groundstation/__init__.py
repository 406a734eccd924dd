"""Helicopter flight-test ground station: live service, DSP, CABC identification, gap diagnosis, sinks."""
__version__ = "0.1.0"
