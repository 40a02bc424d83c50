"""Helpers shared by the offline analysis commands (calibrate, identify, efficiency)."""
from __future__ import annotations

import json
import math
from pathlib import Path

from ..errors import GearbenchError, TraceError
from ..trace import Trace


MOTORS = ("in", "out")


def read_trace(path: str, required: tuple[str, ...], *, min_samples: int = 50,
               motor: str | None = None) -> Trace:
    """Read and validate a trace; every problem becomes a one-line TraceError.

    gearbench's own run traces (``trace-<step>.parquet``, columns ``in.position_rad`` ...)
    are read directly: for a single-motor analysis ``motor`` picks one motor's columns
    (``in.position_rad`` -> ``position_rad``); for a bench analysis (required columns
    ``in_position_rad`` ...) the dotted names are mapped to those."""
    p = Path(path)
    if p.is_dir():
        raise TraceError(f"{p}: is a folder, not a trace file; pass a .csv or .parquet file "
                         f"(a run folder's trace-<step>.parquet)")
    tr = Trace.read(p)
    dotted = [c for c in tr.columns if "." in c and c.split(".", 1)[0] in MOTORS]
    if dotted:
        tr = _from_run_trace(tr, required, motor, dotted)
    elif motor is not None:
        raise TraceError(f"{p}: --motor {motor} is for a gearbench run trace (columns "
                         f"{motor}.position_rad ...); this trace has {', '.join(tr.columns)}: "
                         f"leave --motor out")
    tr.validate(required, min_samples=min_samples)
    return tr


def _from_run_trace(tr: Trace, required, motor, dotted) -> Trace:
    present = sorted({c.split(".", 1)[0] for c in dotted})
    if all("_" in r and r.split("_", 1)[0] in MOTORS for r in required):   # a bench analysis
        names = [c for c in dotted]
        return tr.select(names, {c: c.replace(".", "_", 1) for c in names})
    if motor is None:
        if len(present) != 1:
            raise TraceError(f"{tr.source}: a gearbench run trace with motors {', '.join(present)}; "
                             f"pass --motor {' or --motor '.join(present)} to pick one")
        motor = present[0]
    if motor not in present:
        raise TraceError(f"{tr.source}: no motor '{motor}' in this run trace (it has "
                         f"{', '.join(present)}); pass --motor {' or --motor '.join(present)}")
    names = [c for c in dotted if c.startswith(f"{motor}.")]
    return tr.select(names, {c: c.split(".", 1)[1] for c in names})


def read_json(path: str) -> dict:
    p = Path(path)
    try:
        return json.loads(p.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise GearbenchError(f"{p}: file not found; check the path") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise GearbenchError(f"{p}: cannot read file ({exc.__class__.__name__}); check the path") from None
    except json.JSONDecodeError as exc:
        raise GearbenchError(f"{p}: not valid JSON (line {exc.lineno}: {exc.msg}); use the output "
                             f"of 'gearbench calibrate --json'") from None


def jsonable(o):
    """Recursively make floats JSON-safe (NaN/inf → None) and numpy types plain."""
    import numpy as np

    if isinstance(o, dict):
        return {str(k): jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        return jsonable(o.tolist())
    if isinstance(o, np.generic):
        o = o.item()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return o


def dump(obj) -> None:
    print(json.dumps(jsonable(obj)))
