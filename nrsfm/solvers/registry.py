"""The solver registry: ``solve(seq, params) -> Reconstruction`` functions looked up by name.

Each solver is a plain function taking a :class:`~nrsfm.sequence.Sequence` and a frozen parameter dataclass
(validated in ``__post_init__``) and returning a :class:`~nrsfm.reconstruction.Reconstruction`. The CLI and the
benchmarks only look solvers up by name (:func:`get_solver`, :func:`solve`); parameters can be given as keywords
or as strings (``--set K=12``, :func:`params_from_strings`), and both are type-checked.
"""

from __future__ import annotations

import dataclasses
import math
import time
import typing
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from nrsfm._malloc import large_arrays_on_heap
from nrsfm.errors import SolverError, ValidationError
from nrsfm.reconstruction import Reconstruction
from nrsfm.sequence import Sequence


@dataclass(frozen=True)
class SolverSpec:
    """A registry entry."""

    name: str
    solve: Callable[[Sequence, Any], Reconstruction]
    params: type
    description: str
    handles_missing: bool
    handles_perspective: bool


_REGISTRY: dict[str, SolverSpec] = {}


def register(name: str, params: type, description: str, *, handles_missing: bool = False,
             handles_perspective: bool = False):
    """Decorator adding ``solve(seq, params)`` to the registry under ``name``.

    The wrapped function gets the input checks every solver shares (missing
    points, projection model) and the run time recorded.
    """

    def deco(fn: Callable[[Sequence, Any], Reconstruction]):
        def solve(seq: Sequence, params: Any = None) -> Reconstruction:
            if not isinstance(seq, Sequence):
                raise ValidationError(f"seq: expected an nrsfm.Sequence, got {type(seq).__name__}")
            params = params_cls() if params is None else params
            if not isinstance(params, params_cls):
                raise ValidationError(f"params: expected {params_cls.__name__}, got {type(params).__name__}")
            check_params(params)
            if not handles_missing and not seq.is_complete:
                raise SolverError(f"{name}: expected complete tracks, got {seq.missing_fraction:.1%} missing "
                                  f"entries in '{seq.name}'; use a solver that handles missing points "
                                  f"({', '.join(n for n, s in _REGISTRY.items() if s.handles_missing) or 'none yet'})")
            if not handles_perspective and seq.projection != "orthographic":
                raise SolverError(f"{name}: expected orthographic tracks, got {seq.projection} ones in '{seq.name}'; "
                                  "convert them to weak perspective first (seq.to_weak_perspective(), or "
                                  "'nrsfm solve FILE --weak-perspective'), or use a solver that takes them "
                                  f"({', '.join(n for n, s in _REGISTRY.items() if s.handles_perspective)})")
            if seq.n_frames < 3:
                raise SolverError(f"{name}: expected at least 3 frames, got {seq.n_frames}; two orthographic views "
                                  "of even a rigid shape leave its depths free up to a rotation about one axis")
            if seq.n_points < 4:
                raise SolverError(f"{name}: expected at least 4 points, got {seq.n_points}; 3 points always lie in "
                                  "a plane, so their depths cannot be recovered")
            if not _has_extent(seq):
                raise SolverError(f"{name}: the visible points of every frame of '{seq.name}' coincide (the tracks "
                                  "have no 2D extent); there is no shape to reconstruct")
            t0 = time.perf_counter()
            with large_arrays_on_heap():  # no mmap/munmap of large temporaries every iteration (nrsfm._malloc)
                rec = fn(seq, params)
            return dataclasses.replace(rec, runtime_s=time.perf_counter() - t0,
                                       params=dataclasses.asdict(params))

        params_cls = params
        solve.__name__ = fn.__name__
        solve.__doc__ = fn.__doc__
        solve.__wrapped__ = fn
        _REGISTRY[name] = SolverSpec(name, solve, params, description, handles_missing, handles_perspective)
        return solve

    return deco


_KINDS = {int: (int, np.integer), float: (int, float, np.integer, np.floating), bool: (bool, np.bool_), str: (str,)}


def check_params(params: Any) -> None:
    """Refuse parameter values of the wrong type (``K="12"``, ``K=2.5``, ``K=True`` failed deep inside a solver)
    and NaN or infinite numbers (the per-class checks, ``tol >= 0`` and the like, let NaN through: every
    comparison with it is false)."""
    check_param_values(type(params), {f.name: getattr(params, f.name) for f in dataclasses.fields(params)})


def _unknown_parameter(params_cls: type, name: str, who: str) -> ValidationError:
    known = sorted(f.name for f in dataclasses.fields(params_cls))
    return ValidationError(f"{who}: {params_cls.__name__} has no parameter {name!r}; known: {known}")


def check_param_values(params_cls: type, values: dict[str, Any], who: str = "params") -> None:
    """:func:`check_params` for field values before ``params_cls`` is built (its own checks compare them); an
    unknown name is an error that starts with ``who`` and lists the known ones."""
    hints = typing.get_type_hints(params_cls)
    for name, value in values.items():
        if name not in hints:
            raise _unknown_parameter(params_cls, name, who)
        kind = hints[name]
        where = f"{params_cls.__name__}.{name}"
        if kind in _KINDS and (not isinstance(value, _KINDS[kind]) or (kind is not bool and isinstance(value, bool))):
            raise ValidationError(f"{where}: expected {kind.__name__}, got {type(value).__name__} {value!r}")
        if isinstance(value, (float, np.floating)) and not math.isfinite(value):
            raise ValidationError(f"{where}: expected a finite number, got {value}")


def _has_extent(seq: Sequence) -> bool:
    """Whether some frame's visible points do not all coincide (exactly: no mean is taken, which rounds)."""
    if seq.visibility is None:
        return bool(np.ptp(seq.points_2d, axis=1).any())
    vis = seq.visibility > 0  # (F, P)
    p2 = seq.points_2d
    spread = np.where(vis[..., None], p2, -np.inf).max(axis=1) - np.where(vis[..., None], p2, np.inf).min(axis=1)
    return bool((spread[vis.any(axis=1)] > 0).any())


def available_solvers() -> list[str]:
    """Registered solver names."""
    return list(_REGISTRY)


def get_solver(name: str) -> SolverSpec:
    """Look a solver up by name; unknown names raise with the list of known ones."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise ValidationError(f"method: expected one of {available_solvers()}, got {name!r}") from None


def params_from_strings(params_cls: type, assignments: list[str] | None) -> Any:
    """Build ``params_cls`` from ``["K=12", "tol=1e-6"]`` strings, coercing to the field types."""
    fields = {f.name: f for f in dataclasses.fields(params_cls)}
    hints = typing.get_type_hints(params_cls)
    values: dict[str, Any] = {}
    for item in assignments or []:
        if "=" not in item:
            raise ValidationError(f"--set: expected NAME=VALUE, got {item!r}")
        key, raw = (s.strip() for s in item.split("=", 1))
        if key not in fields:
            raise _unknown_parameter(params_cls, key, "--set")
        values[key] = _coerce(key, raw, hints[key])
    return params_cls(**values)


def _coerce(key: str, raw: str, hint: Any) -> Any:
    args = typing.get_args(hint)
    kinds = [a for a in args if a is not type(None)] if args else [hint]
    if raw.lower() in ("none", "null", "auto") and type(None) in args:
        return None
    for kind in kinds:
        try:
            if kind is bool:
                if raw.lower() in ("1", "true", "yes", "on"):
                    return True
                if raw.lower() in ("0", "false", "no", "off"):
                    return False
                raise ValueError(raw)
            if kind in (int, float, str):
                return kind(raw)
        except ValueError:
            continue
    raise ValidationError(f"--set {key}: expected {' or '.join(getattr(k, '__name__', str(k)) for k in kinds)}, "
                          f"got {raw!r}")


def require_visible_points(seq: Sequence, method: str, minimum: int = 3) -> np.ndarray:
    """`(F, P)` visibility mask; raises a :class:`SolverError` naming the first frame with fewer than
    ``minimum`` visible points, or the first point visible in no frame (nothing constrains it)."""
    vis = seq.weights > 0
    short = vis.sum(axis=1) < minimum
    if short.any():
        f = int(np.argmax(short))
        raise SolverError(f"{method}: frame {f} has fewer than {minimum} visible points; drop it "
                          "(seq.select_frames) first")
    unseen = ~vis.any(axis=0)
    if unseen.any():
        p = int(np.argmax(unseen))
        raise SolverError(f"{method}: point {p} is visible in no frame ({int(unseen.sum())} of {vis.shape[1]} "
                          "points are); drop them (seq.select_points(seq.visibility.any(axis=0))) first")
    return vis



def solve(seq: Sequence, method: str = "rank3", params: Any = None, **overrides: Any) -> Reconstruction:
    """Solve ``seq`` with the registered ``method``; keyword overrides build its params (or replace fields of
    ``params`` when both are given)."""
    spec = get_solver(method)
    check_param_values(spec.params, overrides, method)
    if params is None:
        params = spec.params(**overrides)
    elif overrides:  # a params object and keyword overrides: the overrides win
        if not isinstance(params, spec.params):
            raise ValidationError(f"params: expected {spec.params.__name__}, got {type(params).__name__}")
        params = dataclasses.replace(params, **overrides)
    return spec.solve(seq, params)
