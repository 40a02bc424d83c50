"""Drive families by name, python-can style: a table plus an entry-point group.

Adding a family is adding a module and a row here, or, for a third party,
declaring ``[project.entry-points."gearbench.drives"] myfamily = "pkg.mod:MyNetwork"``.
"""
from __future__ import annotations

import importlib
from importlib.metadata import entry_points

from ..errors import DriveError
from .base import DriveNetwork

BACKENDS: dict[str, str] = {
    "cia402": "gearbench.drives.cia402:CiA402Network",
    "modbus": "gearbench.drives.modbus:ModbusNetwork",
}


def available() -> dict[str, str]:
    table = dict(BACKENDS)
    for ep in entry_points(group="gearbench.drives"):
        table.setdefault(ep.name, ep.value)
    return table


def network_class(family: str) -> type[DriveNetwork]:
    table = available()
    if family not in table:
        raise DriveError(f"unknown drive family '{family}' (known: {', '.join(sorted(table))}); "
                         f"fix the profile's bus.family or install the plugin that provides it")
    module, _, cls = table[family].partition(":")
    return getattr(importlib.import_module(module), cls)
