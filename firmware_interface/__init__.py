"""The link to the flight controller: sans-IO MAVLink session, transports, .tlog recording and log readers."""
