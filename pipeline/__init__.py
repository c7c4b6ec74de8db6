"""flowcast: conditional normalizing flows for forward/backward state and parameter estimation.

The library is plain Python (no Prefect); ``flows/`` orchestrates it.
"""
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("flowcast")
except PackageNotFoundError:  # running from a source tree without install
    __version__ = "0.0.0+local"
