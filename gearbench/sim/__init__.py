"""Simulated physics: motors, drive loops, reducer bench. Deterministic for a seed."""
