"""Short ``repr``s for models, filters and beliefs: the structure, not the factors.

A fitted GP holds megabytes of Cholesky factors; ``print(filter)`` shows the filter kind,
its models and settings, with arrays summarised by shape (small ones in full).
"""

from __future__ import annotations

from dataclasses import fields, is_dataclass
from typing import Any

import numpy as np

__all__ = ["short_repr"]

MAX_DEPTH = 3
SMALL = 6  # arrays with at most this many values are shown in full


def _value(v: Any, depth: int) -> str:
    if isinstance(v, np.ndarray):
        if v.size <= SMALL:
            return np.array2string(v, precision=4, separator=", ")
        return f"<array {'x'.join(map(str, v.shape))} {v.dtype}>"
    if is_dataclass(v) and not isinstance(v, type):
        return short_repr(v, depth + 1) if depth < MAX_DEPTH else f"{type(v).__name__}(...)"
    if isinstance(v, (tuple, list)):
        if len(v) > SMALL:
            return f"<{len(v)} items>"
        inner = ", ".join(_value(x, depth) for x in v)
        return f"({inner}{',' if len(v) == 1 else ''})" if isinstance(v, tuple) else f"[{inner}]"
    if callable(v) and not isinstance(v, type):
        return f"<function {getattr(v, '__qualname__', type(v).__name__)}>"
    text = repr(v)
    return text if len(text) <= 60 else f"<{type(v).__name__}>"


def short_repr(obj: Any, depth: int = 0) -> str:
    """``Name(field=value, ...)`` of a dataclass, with large arrays and nested models summarised."""
    parts = [f"{f.name}={_value(getattr(obj, f.name), depth)}" for f in fields(obj) if f.repr and f.init]
    return f"{type(obj).__name__}({', '.join(parts)})"
