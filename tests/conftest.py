"""Suite-wide set-up.

A shell starts background jobs with SIGINT ignored, and an ignored signal stays ignored across
exec: a suite launched that way (``.ci/run &``) would give every CLI it starts a Ctrl-C that does
nothing, and the tests that press Ctrl-C would hang. Python's own handler is put back here, so
children start with the default disposition, as from a terminal.
"""

import signal

if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)
