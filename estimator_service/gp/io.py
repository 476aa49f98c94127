"""Save and load fitted GPs as single ``.npz`` files (no pickle).

Layout: ``__format__`` (int, :data:`FORMAT_VERSION`), ``__kind__`` (``exact``, ``sparse``,
``hetero``, ``enhanced`` or ``circular``) and the model's arrays; nested models (hetero:
``main/``, ``noise/``; enhanced: ``residual/``; circular: ``inner/``) use key prefixes.
Files are written to a temporary name in the same folder and renamed, so a crash never
leaves a half-written model. An enhanced GP's parametric mean function is code, not data:
pass it to :func:`load_gp`. An exact GP's Cholesky factors (``P n^2`` numbers, most of the
file) are not saved but factored again on load (:func:`~estimator_service.gp.exact.cholesky_factors`,
the same bits as the fit's); files that hold them (``chol_t``) still load.
"""

from __future__ import annotations

import os
import zipfile
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from estimator_service.files import MAX_ARRAY_BYTES, atomic_savez, npz_oversized, npz_unreadable
from estimator_service.gp.base import GPModel, Scaler
from estimator_service.gp.circular import CircularGP
from estimator_service.gp.enhanced import EnhancedGP, JacobianFunction, MeanFunction
from estimator_service.gp.exact import ExactGP, cholesky_factors
from estimator_service.gp.hetero import HeteroscedasticGP
from estimator_service.gp.sparse import SparseGP

__all__ = ["FORMAT_VERSION", "ModelFileError", "load_gp", "load_innermost_gp", "save_gp"]

FORMAT_VERSION = 1
Arrays = dict[str, NDArray]


class ModelFileError(ValueError):
    """A model file is unreadable, truncated, of another version or inconsistent."""


def _scaler_arrays(prefix: str, xs: Scaler, ys: Scaler) -> Arrays:
    return {
        f"{prefix}x_mean": xs.mean,
        f"{prefix}x_std": xs.std,
        f"{prefix}y_mean": ys.mean,
        f"{prefix}y_std": ys.std,
    }


def _to_arrays(model: GPModel, prefix: str = "") -> Arrays:
    out: Arrays = {f"{prefix}__kind__": np.array(model.kind)}
    if isinstance(model, ExactGP):
        out |= _scaler_arrays(prefix, model.x_scaler, model.y_scaler)
        out |= {f"{prefix}{k}": getattr(model, k) for k in ("theta", "x_train", "alpha")}
        if model.noise_profile is not None:
            out[f"{prefix}noise_profile"] = model.noise_profile
    elif isinstance(model, SparseGP):
        out |= _scaler_arrays(prefix, model.x_scaler, model.y_scaler)
        keys = ("theta", "pseudo_inputs", "beta", "chol_mm_t", "chol_b_t")
        out |= {f"{prefix}{k}": getattr(model, k) for k in keys}
    elif isinstance(model, HeteroscedasticGP):
        out |= _to_arrays(model.main, f"{prefix}main/") | _to_arrays(model.noise, f"{prefix}noise/")
    elif isinstance(model, EnhancedGP):
        out |= _to_arrays(model.residual, f"{prefix}residual/")
    elif isinstance(model, CircularGP):
        out[f"{prefix}angle_inputs"] = np.asarray(model.angle_inputs, dtype=np.float64)
        out[f"{prefix}angle_output"] = np.array([model.angle_output, model.period], dtype=np.float64)
        out |= _to_arrays(model.inner, f"{prefix}inner/")
    else:
        raise TypeError(f"cannot save a {type(model).__name__}")
    return out


def save_gp(model: GPModel, path: str | os.PathLike[str]) -> Path:
    """Write ``model`` to ``path`` (``.npz``) atomically; returns the path."""
    return atomic_savez(path, __format__=np.array(FORMAT_VERSION), **_to_arrays(model))


def _get(data: Arrays, key: str, ndim: int, where: str) -> NDArray:
    if key not in data:
        raise ModelFileError(f"{where}: missing array '{key}'")
    arr = data[key]
    if arr.ndim != ndim or not np.issubdtype(arr.dtype, np.floating):
        raise ModelFileError(
            f"{where}: array '{key}' must be a {ndim}-D float array, got {arr.dtype} {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        raise ModelFileError(f"{where}: array '{key}' holds NaN or infinite values")
    return np.array(arr, dtype=np.float64)


def _expect(cond: bool, where: str, msg: str) -> None:
    if not cond:
        raise ModelFileError(f"{where}: inconsistent shapes: {msg}")


def _scalers(data: Arrays, prefix: str, where: str, d: int, p: int) -> tuple[Scaler, Scaler]:
    xm, xsd = _get(data, f"{prefix}x_mean", 1, where), _get(data, f"{prefix}x_std", 1, where)
    ym, ysd = _get(data, f"{prefix}y_mean", 1, where), _get(data, f"{prefix}y_std", 1, where)
    _expect(xm.shape == xsd.shape == (d,), where, f"x scaler must have {d} entries, got {xm.shape}")
    _expect(ym.shape == ysd.shape == (p,), where, f"y scaler must have {p} entries, got {ym.shape}")
    return Scaler(xm, xsd), Scaler(ym, ysd)


class _Code(NamedTuple):
    """The code an enhanced GP needs to load: its mean and mean Jacobian functions."""

    mean: MeanFunction | None = None
    jacobian: JacobianFunction | None = None


_NO_CODE = _Code()


def _from_arrays(data: Arrays, prefix: str, where: str, code: _Code = _NO_CODE) -> GPModel:
    kind_key = f"{prefix}__kind__"
    if kind_key not in data:
        raise ModelFileError(f"{where}: missing '{kind_key}' (not a gpbf GP file?)")
    kind = str(data[kind_key])
    if kind == "exact":
        return _exact(data, prefix, where)
    if kind == "sparse":
        theta = _get(data, f"{prefix}theta", 2, where)
        z = _get(data, f"{prefix}pseudo_inputs", 3, where)
        beta = _get(data, f"{prefix}beta", 2, where)
        lm, lb = (
            _get(data, f"{prefix}chol_mm_t", 3, where),
            _get(data, f"{prefix}chol_b_t", 3, where),
        )
        p, m, d = z.shape
        _expect(theta.shape == (p, d + 2), where, f"theta {theta.shape} vs pseudo_inputs {z.shape}")
        _expect(beta.shape == (p, m), where, f"beta {beta.shape}, expected {(p, m)}")
        _expect(lm.shape == lb.shape == (p, m, m), where, f"Cholesky factors {lm.shape}, {lb.shape}")
        xs, ys = _scalers(data, prefix, where, d, p)
        return SparseGP(xs, ys, theta, z, beta, lm, lb)
    if kind == "hetero":
        main = _from_arrays(data, f"{prefix}main/", where)
        noise = _from_arrays(data, f"{prefix}noise/", where)
        if not isinstance(main, ExactGP) or not isinstance(noise, ExactGP):
            raise ModelFileError(f"{where}: heteroscedastic parts must be exact GPs")
        _expect(main.output_dim == noise.output_dim, where, "main and noise GPs differ in outputs")
        return HeteroscedasticGP(main, noise)
    if kind == "enhanced":
        return _enhanced(data, prefix, where, code)
    if kind == "circular":
        return _circular(data, prefix, where, code)
    raise ModelFileError(f"{where}: unknown model kind {kind!r}")


def _exact(data: Arrays, prefix: str, where: str) -> ExactGP:
    theta = _get(data, f"{prefix}theta", 2, where)
    x = _get(data, f"{prefix}x_train", 2, where)
    alpha = _get(data, f"{prefix}alpha", 2, where)
    p, n, d = theta.shape[0], x.shape[0], x.shape[1]
    _expect(theta.shape == (p, d + 2), where, f"theta {theta.shape} vs x_train {x.shape}")
    _expect(alpha.shape == (p, n), where, f"alpha {alpha.shape}, expected {(p, n)}")
    prof = None
    if f"{prefix}noise_profile" in data:
        prof = _get(data, f"{prefix}noise_profile", 2, where)
        _expect(prof.shape == (p, n), where, f"noise_profile {prof.shape}, expected {(p, n)}")
    xs, ys = _scalers(data, prefix, where, d, p)
    if f"{prefix}chol_t" in data:  # files written before the factors were left out
        chol = _get(data, f"{prefix}chol_t", 3, where)
        _expect(chol.shape == (p, n, n), where, f"chol_t {chol.shape}, expected {(p, n, n)}")
    else:
        chol = _factored(x, theta, prof, where)
    return ExactGP(xs, ys, theta, x, chol, alpha, prof)


def _factored(x: NDArray, theta: NDArray, prof: NDArray | None, where: str) -> NDArray:
    """An exact GP's factors (:func:`cholesky_factors`), refused when they would be larger
    than any array a file may hold or when the hyperparameters are ones no fit gives."""
    (p, _), n = theta.shape, x.shape[0]
    need = p * n * n * np.dtype(np.float64).itemsize
    if need > MAX_ARRAY_BYTES:
        raise ModelFileError(
            f"{where}: {p} outputs of {n} training points need {need} bytes of Cholesky factors, "
            f"more than {MAX_ARRAY_BYTES} (a damaged or hostile file)"
        )
    with np.errstate(all="ignore"):
        try:
            chol = cholesky_factors(x, theta, prof)
        except np.linalg.LinAlgError as exc:
            raise ModelFileError(f"{where}: its kernel matrix cannot be factored: {exc}") from None
    if not np.all(np.isfinite(chol)):
        raise ModelFileError(f"{where}: its kernel matrix cannot be factored: theta gives NaN or inf")
    return chol


def _enhanced(data: Arrays, prefix: str, where: str, code: _Code) -> EnhancedGP:
    if code.mean is None:
        raise ModelFileError(f"{where}: an enhanced GP needs its parametric mean_function to load")
    return EnhancedGP(code.mean, _from_arrays(data, f"{prefix}residual/", where), code.jacobian)


def _circular(data: Arrays, prefix: str, where: str, code: _Code) -> CircularGP:
    angles = _get(data, f"{prefix}angle_inputs", 1, where)
    meta = _get(data, f"{prefix}angle_output", 1, where)
    _expect(meta.shape == (2,), where, f"angle_output must hold (column, period), got {meta.shape}")
    out, period = meta
    inner = _from_arrays(data, f"{prefix}inner/", where, code)
    a = tuple(int(v) for v in angles)
    d, p = inner.input_dim - len(a), inner.output_dim - (1 if out >= 0 else 0)
    _expect(all(0 <= i < d for i in a) and len(set(a)) == len(a), where, f"angle_inputs {a} with d = {d}")
    _expect(-1 <= out < p and period > 0, where, f"angle_output {out} (P = {p}), period {period}")
    return CircularGP(inner, a, int(out), float(period))


def load_gp(
    path: str | os.PathLike[str],
    *,
    mean_function: MeanFunction | None = None,
    mean_jacobian: JacobianFunction | None = None,
) -> GPModel:
    """Load a model written by :func:`save_gp` (an enhanced GP with its functions, see
    :class:`~estimator_service.gp.enhanced.EnhancedGP`).

    Raises
    ------
    ModelFileError
        Truncated or unreadable file, wrong format version, missing or inconsistent arrays.
    """
    data, where = _read(path)
    return _from_arrays(data, "", where, _Code(mean_function, mean_jacobian))


def load_innermost_gp(path: str | os.PathLike[str]) -> GPModel:
    """The innermost GP of a model :func:`save_gp` wrote (an enhanced GP's residual, a
    circular GP's inner GP), which needs no code to load: what a refit on other data keeps."""
    data, where = _read(path)
    prefix = ""
    while str(data.get(f"{prefix}__kind__")) in ("enhanced", "circular"):
        prefix += "residual/" if str(data[f"{prefix}__kind__"]) == "enhanced" else "inner/"
    return _from_arrays(data, prefix, where)


def _read(path: str | os.PathLike[str]) -> tuple[Arrays, str]:
    """A model file's arrays (checked for size and format version) and its name for errors."""
    where = f"model file {os.fspath(path)!r}"
    try:
        with np.load(path, allow_pickle=False) as npz:
            oversized = npz_oversized(npz)
            if oversized:
                raise ModelFileError(f"{where}: {oversized} (a damaged or hostile file)")
            data = {k: npz[k] for k in npz.files}
    except FileNotFoundError:
        raise
    except (zipfile.BadZipFile, EOFError, OSError, ValueError) as exc:
        raise ModelFileError(f"{where}: {npz_unreadable(exc)}") from exc
    if "__format__" not in data:
        raise ModelFileError(f"{where}: no '__format__' entry (not a gpbf GP file?)")
    fmt = data["__format__"]
    if fmt.shape != () or not np.issubdtype(fmt.dtype, np.integer):
        raise ModelFileError(f"{where}: '__format__' must be one integer, got {fmt.dtype} {fmt.shape}")
    version = int(fmt)
    if version != FORMAT_VERSION:
        raise ModelFileError(f"{where}: format version {version}, this build reads {FORMAT_VERSION}")
    return data, where
