"""The one way a frozen dataclass brings its own inputs to their normal form.

Derived values are properties and caches are :func:`functools.cached_property`; what is
left is normalisation: a field given as a list, a string or a NumPy integer stored as the
tuple, array or ``int`` the class documents. :func:`normalise` does that inside
``__post_init__`` only, before the instance is seen by anyone else; after construction a
frozen dataclass is never written to.
"""

from __future__ import annotations

__all__ = ["normalise"]


def normalise(obj: object, **fields: object) -> None:
    """Set ``obj``'s fields to their normal form (call from its ``__post_init__`` only).

    Parameters
    ----------
    obj
        A frozen dataclass under construction.
    **fields
        Field name -> its value in normal form.
    """
    for name, value in fields.items():
        object.__setattr__(obj, name, value)
