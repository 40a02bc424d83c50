"""The bench's digital twin: replay a recorded run through gearbench.sim, measure the gap, fit."""
