"""Sim-to-real gap diagnosis (issue 6): where the paper's model misses, which unmodelled
effect explains it, and how far adding it closes the gap on held-out data.

    from gearbench.analysis.diagnose import diagnose
    result = diagnose(trace)            # or diagnose(trace, load_model("model.json"))
    result.verdict.effect, result.candidates[0].shrink, result.as_dict()
"""
from .effects import LIBRARY, NAMES
from .nominal import GivenModel, load_model
from .chain import Diagnosis, diagnose

__all__ = ["Diagnosis", "GivenModel", "LIBRARY", "NAMES", "diagnose", "load_model"]
