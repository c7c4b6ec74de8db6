"""The paper's numbers, copied from its LaTeX (Tables 1–4): mean KL divergence per (row, column).

Table 1: vehicle (fixed step), forward, conditional NF vs sequential Monte Carlo; Table 2:
vehicle with dropout, the three encoders, forward and backward; Tables 3/4: SIR with fixed
(single) and random (multi) parameters, the three encoders × S, I, R, forward and backward.
"""
from __future__ import annotations

from pipeline.paper.config import ENCODER_LABEL, ENCODERS
from pipeline.names import COMPARTMENTS

Cells = dict[tuple[str, str], float]

PAPER_T1: Cells = {("Before-bifurcation (fw)", "Conditional NF"): 0.843,
                   ("Before-bifurcation (fw)", "Sequential MC"): 7.554,
                   ("At-bifurcation (fw)", "Conditional NF"): 3.268,
                   ("At-bifurcation (fw)", "Sequential MC"): 8.856,
                   ("After-bifurcation (fw)", "Conditional NF"): 0.777,
                   ("After-bifurcation (fw)", "Sequential MC"): 9.069}
_T2_ROWS = {"Before-bifurcation (fw)": (5.062, 4.989, 4.988),
            "Before-bifurcation (bw)": (4.955, 4.893, 4.621),
            "At-bifurcation (fw)": (4.503, 4.484, 4.572),
            "At-bifurcation (bw)": (4.844, 4.827, 4.681),
            "After-bifurcation (fw)": (3.719, 3.791, 3.753),
            "After-bifurcation (bw)": (4.502, 4.463, 4.157)}
PAPER_T2: Cells = {(row, ENCODER_LABEL[e]): v for row, values in _T2_ROWS.items()
                   for e, v in zip(ENCODERS, values, strict=True)}
_T3 = {"fw": (2.245, 2.211, 2.304, 2.243, 2.375, 2.467, 2.192, 2.209, 2.264),
       "bw": (2.110, 1.984, 2.232, 2.143, 2.098, 2.320, 2.053, 1.975, 2.157)}
_T4 = {"fw": (2.847, 2.456, 2.642, 2.816, 2.440, 2.616, 2.729, 2.478, 2.418),
       "bw": (2.838, 2.097, 2.828, 2.634, 2.138, 2.765, 2.765, 2.051, 2.662)}
SIR_COLUMNS: list[str] = [f"{ENCODER_LABEL[e]} / {c}" for e in ENCODERS for c in COMPARTMENTS]
PAPER_T3: Cells = {(row, col): v for row, vals in _T3.items()
                   for col, v in zip(SIR_COLUMNS, vals, strict=True)}
PAPER_T4: Cells = {(row, col): v for row, vals in _T4.items()
                   for col, v in zip(SIR_COLUMNS, vals, strict=True)}
PAPER: dict[str, Cells] = {"Table 1": PAPER_T1, "Table 2": PAPER_T2, "Table 3": PAPER_T3,
                           "Table 4": PAPER_T4}
