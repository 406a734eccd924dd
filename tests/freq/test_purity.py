"""groundstation.freq is pure numerics: importing every module pulls in no IO, plotting or clock package."""

from __future__ import annotations

import subprocess
import sys


def test_freq_imports_no_io_packages():
    code = ("import sys, groundstation.freq.spectra, groundstation.freq.model_response, groundstation.freq.cost, "
            "groundstation.freq.metrics, groundstation.freq.verify, groundstation.freq.identify\n"
            "bad = [m for m in ('matplotlib', 'rerun', 'zenoh', 'asyncio', 'serial', 'rich') if m in sys.modules]\n"
            "print(','.join(bad))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "", f"groundstation.freq imports {out}"
