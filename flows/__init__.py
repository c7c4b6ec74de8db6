"""Prefect flows and deployments: thin orchestration over the ``pipeline`` library."""
import os

# Before torch is imported anywhere in a flow run: see pipeline/__init__.py (OpenMP spin-waiting).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
