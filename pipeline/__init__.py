"""flowcast: conditional normalizing flows for forward/backward state and parameter estimation.

The library is plain Python (no Prefect); ``flows/`` orchestrates it.
"""
import os
from importlib.metadata import PackageNotFoundError, version

# OpenMP's default spin-waiting makes torch's 2-thread CPU ops ~30x slower whenever the other
# core is busy (measured here: vehicle simulation 1.3 s -> 38.8 s). Passive waiting costs nothing
# on an idle machine. It must be set before torch loads its OpenMP runtime.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

try:
    __version__ = version("flowcast")
except PackageNotFoundError:  # running from a source tree without install
    __version__ = "0.0.0+local"
