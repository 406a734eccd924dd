"""Hardware in the loop without hardware: virtual serial ports replaying recorded links, and a simulated
helicopter flight controller with injectable unmodelled effects, and the scenario sets of the diagnosis's
blind test (``scenarios``). Never imports groundstation.sysid/gap."""
