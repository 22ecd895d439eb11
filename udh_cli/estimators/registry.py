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
    takes ``KEY`` (the command's method; under ``udh bench`` each method compared). ``KEY`` may name an option
    of a record the method composes, ``network.search`` (:func:`option_path`), and a bare ``search`` reaches it
    there when the method has no ``search`` of its own. Values are read as JSON when they parse (numbers,
    true/false, null), else kept as text (paths). Returns ``{method: options}`` for the methods that got
    options, nested as :func:`nest_options` makes them. Raises :class:`UdhError` for a malformed item, a METHOD
    not in ``methods``, or a KEY that none of them takes (naming the keys they take).
    """
    options: dict[str, dict[str, Any]] = {}
    for item in items or []:
        parsed = parse_key_value(item)
        if parsed is None:
            shown = item if len(item) <= 60 else item[:57] + "..."
            raise UdhError(f"option '{shown}': write {OPTION_SYNTAX.removeprefix('-O ')}, e.g. model=my.onnx or sift.ratio=0.8")
        key, value = parsed
        head, dot, rest = key.partition(".")
        if dot and head in ESTIMATORS:
            if head not in methods:
                raise UdhError(f"option {key!r}: {head!r} is not a method of this command ({', '.join(methods)})")
            targets, name = [head], rest.strip()
            if option_path(head, name) is None:
                raise UdhError(f"option {key!r}: {_takes(head, name)}")
        else:
            targets, name = [m for m in methods if option_path(m, key) is not None], key
            if not targets:
                raise UdhError(f"option {key!r}: no method here takes {key!r} ({', '.join(methods)}); {_takes(methods[0], key)}")
        for target in targets:
            options[target] = nest_options(target, {name: value}, options.get(target, {}))
    return options


def _takes(name: str, key: str) -> str:
    """What method ``name`` takes, for an error about ``key``: its composed record's keys when ``key`` names one."""
    head, dot, _ = key.partition(".")
    nested = _nested_fields(name)
    if dot and head in nested:
        return f"{name}'s {head} takes: {', '.join(nested[head])}"
    listed = [f"{key}.{{{', '.join(nested[key])}}}" if key in nested else key for key in _own_options(name)]
    return f"{name} takes: {', '.join(listed) or 'no options'}"


def estimator_names() -> list[str]:
    """The registered method names, in registry order."""
    return list(ESTIMATORS)


def _estimator_class(name: str) -> type:
    if name not in ESTIMATORS:
        raise UdhError(f"unknown method '{name}'; choose one of: {', '.join(ESTIMATORS)}")
    module_name, class_name, _ = ESTIMATORS[name]
    return getattr(importlib.import_module(module_name), class_name)


def _own_options(name: str) -> list[str]:
    """The dataclass fields of the class registered as ``name`` that its constructor takes."""
    cls = _estimator_class(name)
    return [f.name for f in dataclasses.fields(cls) if f.init] if dataclasses.is_dataclass(cls) else []


def _nested_fields(name: str) -> dict[str, list[str]]:
    """The fields of ``name``'s record that hold another method's options (metadata ``options_of``), with the keys
    each takes: that method's options less those the record sets itself (metadata ``set_here``)."""
    cls = _estimator_class(name)
    if not dataclasses.is_dataclass(cls):
        return {}
    return {f.name: [key for key in _own_options(f.metadata["options_of"]) if key not in f.metadata.get("set_here", ())]
            for f in dataclasses.fields(cls) if f.init and "options_of" in f.metadata}


def estimator_options(name: str) -> list[str]:
    """The options the method registered as ``name`` takes: its dataclass fields, and for a record it composes
    (``auto``'s ``network``) that record's keys, dotted (``network.search``)."""
    nested = _nested_fields(name)
    return [key for field_name in _own_options(name)
            for key in ([f"{field_name}.{inner}" for inner in nested[field_name]] if field_name in nested else [field_name])]


def option_path(name: str, key: str) -> tuple[str, ...] | None:
    """Where method ``name`` takes ``key``: ``(key,)`` for a field of its own, ``(record, key)`` for a key of a
    record it composes (``"network.search"``, or a bare ``"search"`` when it has no ``search`` of its own); None
    when it does not take it."""
    head, dot, rest = key.partition(".")
    nested = _nested_fields(name)
    if dot:
        return (head, rest) if rest in nested.get(head, ()) else None
    if key in _own_options(name):
        return (key,)
    return next(((record, key) for record, keys in nested.items() if key in keys), None)


def nest_options(name: str, options: dict[str, Any], into: dict[str, Any] | None = None) -> dict[str, Any]:
    """``options`` for method ``name`` (bare, dotted or nested keys) as its constructor takes them, merged into a
    copy of ``into``: each key of a composed record inside that record's dict (``{"network": {"search": 2}}``).

    Raises :class:`UdhError` for a key the method does not take, naming those it takes.
    """
    nested = _nested_fields(name)
    out = {key: dict(value) if key in nested and isinstance(value, dict) else value for key, value in (into or {}).items()}
    for key, value in options.items():
        path = option_path(name, key)
        if path is None:
            raise UdhError(f"method '{name}' does not take {key}; {_takes(name, key).replace(f'{name} takes', 'it takes')}")
        if len(path) == 2:
            out[path[0]] = {**out.get(path[0], {}), path[1]: value}
        elif key in nested and isinstance(value, dict):  # a record given whole, e.g. network={"search": 2}
            for inner, inner_value in value.items():
                out = nest_options(name, {f"{key}.{inner}": inner_value}, out)
            out.setdefault(key, {})
        else:
            out[key] = value
    return out


def merge_flag_options(name: str, flags: dict[str, Any], options: dict[str, Any]) -> dict[str, Any]:
    """A command's flags (``{"search": 2}``) and its ``-O`` options of method ``name`` (nested, as
    :func:`parse_method_options` returns them) as one nested dict; raises :class:`UdhError` when a flag and an
    option set the same setting to different values, so that neither silently wins."""
    for key, value in flags.items():
        path = option_path(name, key)
        holder = options if path is None or len(path) == 1 else options.get(path[0], {})
        if path is not None and path[-1] in holder and holder[path[-1]] != value:
            raise UdhError(f"method '{name}': {'.'.join(path)} is given twice, as --{key.replace('_', '-')} {value} and "
                           f"-O {'.'.join(path)}={holder[path[-1]]}; give it once")
    return nest_options(name, flags, options)


def with_option_default(name: str, options: dict[str, Any], key: str, value: Any, none_is_unset: bool = False) -> dict[str, Any]:
    """``options`` of method ``name`` nested (:func:`nest_options`), with ``key`` set to ``value`` where the method
    takes it and ``options`` do not give it (or give None, with ``none_is_unset``); unchanged where it does not."""
    nested = nest_options(name, options)
    path = option_path(name, key)
    if path is None:
        return nested
    holder = nested if len(path) == 1 else nested.setdefault(path[0], {})
    if path[-1] not in holder or (none_is_unset and holder[path[-1]] is None):
        holder[path[-1]] = value
    return nested


def create_estimator(name: str, **options: Any) -> Estimator:
    """Build the estimator registered as ``name`` with keyword ``options`` (its dataclass fields; the keys of a
    record it composes dotted, bare or nested, as :func:`nest_options` reads them).

    Raises :class:`UdhError` for an unknown name or option, or an option value of the wrong type.
    """
    cls = _estimator_class(name)
    options = nest_options(name, options)
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
