"""gearbench inside an OpenHTF station (optional extra: ``pip install gearbench[openhtf]``).

    from gearbench.openhtf import build_test
    from openhtf.output.callbacks import json_factory

    test = build_test("profiles/cvt.yaml", sim=True)
    test.add_output_callbacks(json_factory.OutputToJSON("records/{dut_id}.json", indent=2))
    test.execute(test_start=lambda: "SN-1")

- ``build_test(profile_path, sim=False, out_root=...)`` -> ``openhtf.Test``: one phase
  per profile step (calibrate_<motor>, load, efficiency) and a final ``gearbench_result``.
- ``phases(profile_path)``: the same phases with the generic ``BenchPlug`` placeholder,
  for your own ``Test`` and your own plug: ``.with_plugs(bench=MyPlug.for_profile(path))``.
- ``BenchPlug`` (the profile's drives on its bus) and ``SimBenchPlug`` (the same
  drives stack against the emulated bench): ``auto_placeholder = True``.

Nothing here is imported by ``import gearbench``; this package itself imports OpenHTF
only when one of its names is first used, and neutralises OpenHTF's import-time
quirks (reading ``sys.argv``, installing a SIGINT handler), see ``_compat``.
"""
from __future__ import annotations

__all__ = ["build_test", "phases", "BenchPlug", "SimBenchPlug", "UserInputOperator", "GearbenchTest"]

_WHERE = {"build_test": "steps", "phases": "steps", "GearbenchTest": "steps",
          "BenchPlug": "plugs", "SimBenchPlug": "plugs", "UserInputOperator": "plugs"}


def __getattr__(name: str):
    # lazy: importing gearbench.openhtf costs nothing until a name is used
    if name in _WHERE:
        import importlib

        return getattr(importlib.import_module(f"{__name__}.{_WHERE[name]}"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
