"""Sim-to-real gap diagnosis (issue 6)."""
