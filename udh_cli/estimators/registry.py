"""Create estimators by name. The names here are the ``--method`` choices of every command."""

from __future__ import annotations

import dataclasses
import importlib
import json
import numbers
import os
import types
import typing
from typing import Any, Sequence

from udh_cli.errors import UdhError

if typing.TYPE_CHECKING:
    from udh_cli.estimators.base import Estimator

# name -> (module, class, one-line description). Modules are imported on demand, so that choosing
# "sift" never loads onnxruntime. The class is an Estimator, or an options record whose build() composes one
# (the cascades of udh_cli.estimators.refined): either way its dataclass fields are the method's options.
ESTIMATORS: dict[str, tuple[str, str, str]] = {
    "sift": ("udh_cli.estimators.features", "SiftRansac", "SIFT + ratio test + RANSAC (5 px)"),
    "orb": ("udh_cli.estimators.features", "OrbRansac", "ORB + ratio test + RANSAC (5 px)"),
    "ecc": ("udh_cli.estimators.ecc", "EccEstimator", "ECC, MOTION_HOMOGRAPHY, from the identity"),
    "identity": ("udh_cli.estimators.identity", "IdentityEstimator", "no motion; the baseline"),
    "unsupervised": ("udh_cli.estimators.deep", "UnsupervisedEstimator", "the unsupervised deep network (onnxruntime)"),
    "supervised": ("udh_cli.estimators.deep", "SupervisedEstimator", "supervised HomographyNet (onnxruntime)"),
    "matcher": ("udh_cli.estimators.matched", "MatcherEstimator", "the learned matcher alone: dense descriptors, mutual nearest cells, MAGSAC++"),
    "unsupervised+ecc": ("udh_cli.estimators.refined", "UnsupervisedEccOptions", "unsupervised network, then coarse-to-fine ECC"),
    "auto": ("udh_cli.estimators.refined", "AutoOptions", "unsupervised+ecc, verified; SIFT+ECC, the full cascade, then mirrored/flipped/swapped views while it does not verify"),
}

# The method of `udh estimate` and `udh mosaic` when none is given: the verified combination, which measured
# best on the synthetic benchmark, graf1/graf3 and the example flight, and at least as well as SIFT on the real
# flights (docs/benchmarks.md).
DEFAULT_METHOD = "auto"


def parse_key_value(item: str) -> tuple[str, Any] | None:
    """``"KEY=VALUE"`` from a command line -> ``(KEY, value)``, the value read as JSON when it parses
    (numbers, true/false, null) and kept as text otherwise (paths, names); ``None`` if it is not KEY=VALUE."""
    key, sep, text = item.partition("=")
    if not sep or not key.strip():
        return None
    try:
        return key.strip(), json.loads(text)
    except (ValueError, RecursionError):  # not JSON, or absurdly nested: kept as text
        return key.strip(), text


OPTION_SYNTAX = "-O [METHOD.]KEY=VALUE"  # how every command takes estimator options


def parse_method_options(items: Sequence[str] | None, methods: Sequence[str]) -> dict[str, dict[str, Any]]:
    """Estimator options from a command line, one syntax for every command: ``[METHOD.]KEY=VALUE``.

    ``METHOD.KEY=VALUE`` goes to that method; a bare ``KEY=VALUE`` goes to every method of ``methods`` that
    takes ``KEY`` (the command's method; under ``udh bench`` each method compared). Values are read as JSON
    when they parse (numbers, true/false, null), else kept as text (paths). Returns ``{method: {key: value}}``
    for the methods that got options. Raises :class:`UdhError` for a malformed item, a METHOD not in
    ``methods``, or a bare KEY that none of them takes.
    """
    options: dict[str, dict[str, Any]] = {}
    for item in items or []:
        parsed = parse_key_value(item)
        if parsed is None:
            shown = item if len(item) <= 60 else item[:57] + "..."
            raise UdhError(f"option '{shown}': write {OPTION_SYNTAX.removeprefix('-O ')}, e.g. model=my.onnx or sift.ratio=0.8")
        key, value = parsed
        method, dot, name = key.rpartition(".")
        if dot:
            if method not in methods:
                raise UdhError(f"option {key!r}: {method!r} is not a method of this command ({', '.join(methods)})")
            targets = [method]
        else:
            targets = [m for m in methods if name in estimator_options(m)]
            if not targets:
                raise UdhError(f"option {key!r}: no method here takes {name!r} ({', '.join(methods)}); "
                               f"{methods[0]} takes: {', '.join(estimator_options(methods[0])) or 'no options'}")
        for target in targets:
            options.setdefault(target, {})[name.strip()] = value
    return options


def estimator_names() -> list[str]:
    """The registered method names, in registry order."""
    return list(ESTIMATORS)


def _estimator_class(name: str) -> type:
    if name not in ESTIMATORS:
        raise UdhError(f"unknown method '{name}'; choose one of: {', '.join(ESTIMATORS)}")
    module_name, class_name, _ = ESTIMATORS[name]
    return getattr(importlib.import_module(module_name), class_name)


def estimator_options(name: str) -> list[str]:
    """The option names (dataclass fields) that the estimator registered as ``name`` takes."""
    cls = _estimator_class(name)
    return [f.name for f in dataclasses.fields(cls) if f.init] if dataclasses.is_dataclass(cls) else []


def create_estimator(name: str, **options: Any) -> Estimator:
    """Build the estimator registered as ``name`` with keyword ``options`` (its dataclass fields).

    Raises :class:`UdhError` for an unknown name or option, or an option value of the wrong type.
    """
    cls = _estimator_class(name)
    accepted = estimator_options(name)
    unknown = sorted(set(options) - set(accepted))
    if unknown:
        raise UdhError(f"method '{name}' does not take {', '.join(unknown)}; it takes: {', '.join(accepted) or 'no options'}")
    _check_option_types(name, cls, options)
    from udh_cli.estimators.base import Estimator  # NumPy, once an estimator is made: the names alone need none

    made = cls(**options)
    return made if isinstance(made, Estimator) else made.build()  # an options record composes its estimator


_SIMPLE_TYPES = (bool, int, float, str, type(None))


def _check_option_types(name: str, cls: type, options: dict[str, Any]) -> None:
    """Raise :class:`UdhError` when an option of a plain type (number, flag, text) gets a value of another.

    Options arrive from the command line as parsed JSON or text, e.g. ``ratio=abc``; a wrong type would
    otherwise fail every pair later, one by one. Options of other types (arrays, nested settings) are left
    to the estimator.
    """
    if not options or not dataclasses.is_dataclass(cls):
        return
    hints = typing.get_type_hints(cls)
    for key, value in options.items():
        hint = hints.get(key)
        union = isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union
        allowed = typing.get_args(hint) if union else (hint,)
        if not all(t in _SIMPLE_TYPES for t in allowed):
            continue
        if not any(_fits(value, t) for t in allowed):
            wanted = " or ".join("none" if t is type(None) else t.__name__ for t in allowed)
            raise UdhError(f"method '{name}': option {key} takes {wanted}, not {value!r}")


def _fits(value: Any, kind: type) -> bool:
    """Whether ``value`` can stand for a ``kind`` option: ints (numpy's too) for floats, paths for text."""
    if kind is type(None):
        return value is None
    if kind is bool or isinstance(value, bool):
        return kind is bool and isinstance(value, bool)
    if kind is int:
        return isinstance(value, numbers.Integral)
    if kind is float:
        return isinstance(value, numbers.Real)
    return isinstance(value, (str, os.PathLike))
