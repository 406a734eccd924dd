"""Hardware in the loop without hardware: virtual serial ports replaying recorded links, and a simulated
helicopter flight controller with injectable unmodelled effects. Never imports groundstation.sysid/gap."""
