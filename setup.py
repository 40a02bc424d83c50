"""Ships the top-level ``drivers/`` and ``profiles/`` folders inside the wheel.

They stay at the repository top level (the Quick start runs ``profiles/cvt.yaml``)
and are mapped to the data-only packages ``gearbench._data.drivers`` and
``gearbench._data.profiles``; every file in them is package data, so a file
dropped into either folder is shipped without listing it anywhere.
Everything else is in pyproject.toml.
"""
from setuptools import find_packages, setup

DATA = {"gearbench._data.drivers": "drivers", "gearbench._data.profiles": "profiles"}

setup(packages=find_packages(include=["gearbench", "gearbench.*"]) + list(DATA),
      package_dir=DATA,
      package_data={name: ["*", "**/*"] for name in DATA},
      exclude_package_data={name: ["__pycache__/*", "**/__pycache__/*"] for name in DATA})
