"""Paper-scale benchmarks: each prints its figures and writes bench/results/<name>.json."""
import os

# Before any bench module imports torch: see pipeline/__init__.py (OpenMP spin-waiting).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
