"""Hostile ``.npz`` files for the tests of the file readers (model and flight files)."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np


def npz_declaring(path: Path, name: str, shape: tuple[int, ...], extra: dict | None = None) -> None:
    """An ``.npz`` whose member ``name`` declares ``shape`` (float64) but stores 8 bytes;
    ``extra``'s arrays stored as they are."""
    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(head, {"descr": "<f8", "fortran_order": False, "shape": shape})
    with zipfile.ZipFile(path, "w") as z:
        z.writestr(f"{name}.npy", head.getvalue() + b"\0" * 8)
        for k, v in (extra or {}).items():
            buf = io.BytesIO()
            np.save(buf, v, allow_pickle=True)
            z.writestr(f"{k}.npy", buf.getvalue())


def load_refused(path: Path, says: str) -> str:
    """Load the GP file ``path`` expecting a :class:`ModelFileError` whose message names the
    file first (``model file '<path>': ``) and contains ``says``; returns the message."""
    from estimator_service.gp import ModelFileError, load_gp

    try:
        load_gp(path)
    except ModelFileError as err:
        message = str(err)
    else:
        raise AssertionError(f"{path} was loaded, expected a ModelFileError saying {says!r}")
    assert message.startswith(f"model file {str(path)!r}: ") and says in message, message
    return message
