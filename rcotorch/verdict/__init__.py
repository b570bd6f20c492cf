"""How far an answer can be trusted: member health, confidence intervals and residual checks, and
held-out validation.
"""
