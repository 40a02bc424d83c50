"""The analysis docstrings' examples run as written (doctest)."""
import doctest
import importlib
import pkgutil

import pytest

import gearbench.analysis

MODULES = sorted(m.name for m in pkgutil.walk_packages(gearbench.analysis.__path__, "gearbench.analysis."))


@pytest.mark.parametrize("name", MODULES)
def test_examples_run(name):
    result = doctest.testmod(importlib.import_module(name), optionflags=doctest.ELLIPSIS)
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed in {name}"
