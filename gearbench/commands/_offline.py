"""Helpers shared by the offline analysis commands (calibrate, identify, efficiency)."""
from __future__ import annotations

import json
import math
from pathlib import Path

from ..errors import GearbenchError, TraceError
from ..trace import Trace


def read_trace(path: str, required: tuple[str, ...], *, min_samples: int = 50) -> Trace:
    """Read and validate a trace; every problem becomes a one-line TraceError."""
    p = Path(path)
    if p.is_dir():
        raise TraceError(f"{p}: is a folder, not a trace file; pass a .csv or .parquet file")
    tr = Trace.read(p)
    tr.validate(required, min_samples=min_samples)
    return tr


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
