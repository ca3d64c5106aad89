"""A stand-in for NVIDIA's ``nvidia-cuda-mps-control`` that records how it was called (tests/test_gpu_sharing.py,
tests/test_generate.py)."""

from __future__ import annotations

from pathlib import Path

from transtac_sim.gpu_sharing import CONTROL


def stand_in(bin_dir: Path, log: Path, start_output: str = "", start_exit: int = 0) -> None:
    """A ``nvidia-cuda-mps-control`` in ``bin_dir`` that appends its arguments and standard input to ``log``."""
    bin_dir.mkdir(exist_ok=True)
    script = bin_dir / CONTROL
    script.write_text(f"""#!/bin/sh
if [ "$1" = "-d" ]; then echo "start" >> {log}; echo "{start_output}"; exit {start_exit}; fi
while read -r line; do echo "command $line" >> {log}; done
""")
    script.chmod(0o755)
