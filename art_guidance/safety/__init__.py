"""Passive (free-drift) safety with state uncertainty, the paper's central constraint.

- `passive`: `PassiveSafety` (ellipsoids, the drift maps, the q-sigma margin, its evaluation
  and linearisation for SCVx*);
- `drift`: the free drift in closed form and its certified continuous minimum (`DriftArcs`);
- `drift_bounds`: the lower bounds that let that search skip sample intervals;
- `drift_search`: the search itself (refinement of bracketed minima, splitting of intervals);
- `results`: what `PassiveSafety` returns (`SafetyEvaluation`, `SafetyLinearization`).
"""
from art_guidance.safety.passive import (  # noqa: F401
    PassiveSafety, SafetyEvaluation, SafetyLinearization,
)
