"""Sinks: zenoh publisher and Rerun stream (IO lives here, not in dsp/sysid/gap)."""
