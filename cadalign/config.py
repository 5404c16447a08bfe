"""Strict, typed configs: frozen dataclasses loaded from TOML/YAML/JSON.

A config class is a frozen dataclass whose fields carry a docstring and a
default. Loading merges a preset (or the defaults) with the keys of a file and
is strict: an unknown key, a value of the wrong type, a value outside a
``Literal`` or outside the bounds declared in the field's metadata
(``ge``/``gt``/``le``/``lt``) raises :class:`~cadalign.errors.ConfigError`
naming the file, the key path and what is allowed.

Example:
    >>> from dataclasses import dataclass
    >>> @dataclass(frozen=True)
    ... class ICP:
    ...     max_iters: int = 50
    >>> from_dict(ICP, {"max_iters": 10}).max_iters
    10
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import math
import tomllib
import types
import typing
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal, TypeVar, get_args, get_origin

import numpy as np
import yaml

from cadalign.errors import ConfigError

T = TypeVar("T")

_BOUND_CHECKS = {
    "ge": (lambda v, b: v >= b, ">="),
    "gt": (lambda v, b: v > b, ">"),
    "le": (lambda v, b: v <= b, "<="),
    "lt": (lambda v, b: v < b, "<"),
}


def bounded(default: Any, **bounds: float) -> Any:
    """A dataclass field with numeric bounds checked on load, e.g. ``bounded(0.1, gt=0)``."""
    unknown = set(bounds) - set(_BOUND_CHECKS)
    if unknown:
        raise TypeError(f"unknown bound(s) {sorted(unknown)}; use ge/gt/le/lt")
    if isinstance(default, (list, dict, set)):
        raise TypeError("mutable defaults are not allowed; use a tuple")
    return dataclasses.field(default=default, metadata=bounds)


def merge_mappings(a: Mapping[str, Any], b: Mapping[str, Any]) -> dict[str, Any]:
    """``a`` with ``b``'s keys over it; tables present in both merge key by key (override dicts of a config)."""
    out = dict(a)
    for k, v in b.items():
        out[k] = merge_mappings(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), Mapping) else v
    return out


def read_mapping(path: Path) -> dict[str, Any]:
    """Read a TOML, YAML or JSON file into a dict, with errors naming the file."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file not found: {path}; check the path")
    suffix = path.suffix.lower()
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not a UTF-8 text file ({exc.reason} at byte {exc.start}); save it as UTF-8 "
                          "text") from exc
    try:
        if suffix == ".toml":
            data = tomllib.loads(text)
        elif suffix in (".yaml", ".yml"):
            data = yaml.safe_load(text) or {}
        elif suffix == ".json":
            data = json.loads(text)
        else:
            raise ConfigError(f"{path}: unsupported config format {suffix!r}; use .toml, .yaml or .json")
    except ConfigError:
        raise
    except Exception as exc:  # parser errors differ per format (and RecursionError); report them uniformly
        raise ConfigError(f"{path}: could not parse: {str(exc)[:300]}; fix the syntax at the place named") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: top level must be a table/mapping, got {type(data).__name__}")
    return data


def from_dict(cls: type[T], data: Mapping[str, Any], *, source: str = "<config>", base: T | None = None) -> T:
    """Build ``cls`` from ``data`` strictly, starting from ``base`` (or the defaults).

    Args:
        cls: a dataclass type.
        data: the keys to set; nested dataclass fields take nested mappings.
        source: the name used in error messages (usually the file path).
        base: an instance whose values are the starting point (a preset).
    """
    return _build(cls, data, source, "", base)


def _build(cls: type[T], data: Any, source: str, prefix: str, base: Any) -> T:
    if not isinstance(data, Mapping):
        raise ConfigError(f"{source}: '{prefix.rstrip('.') or '<root>'}' must be a table, got {data!r}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    for key in data:
        if key not in fields:
            close = difflib.get_close_matches(str(key), list(fields), n=1)
            hint = f" (did you mean '{prefix}{close[0]}'?)" if close else ""
            raise ConfigError(
                f"{source}: unknown key '{prefix}{key}'{hint}; allowed keys: {', '.join(sorted(fields))}"
            )
    kwargs: dict[str, Any] = {}
    for name, f in fields.items():
        key = prefix + name
        current = getattr(base, name) if base is not None else _MISSING
        if name in data:
            value = data[name]
            if dataclasses.is_dataclass(_strip_optional(hints[name])) and isinstance(value, Mapping):
                nested_base = current if current is not _MISSING and current is not None else None
                kwargs[name] = _build(_strip_optional(hints[name]), value, source, key + ".", nested_base)
            else:
                kwargs[name] = _coerce(value, hints[name], source, key)
            _check_bounds(kwargs[name], f.metadata, source, key)
        elif current is not _MISSING:
            kwargs[name] = current
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ConfigError(f"{source}: missing required key '{key}'")
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (ValueError, TypeError) as exc:
        where = prefix.rstrip(".") or cls.__name__
        raise ConfigError(f"{source}: invalid '{where}': {exc}") from exc


class _Missing:
    pass


_MISSING = _Missing()


def _strip_optional(tp: Any) -> Any:
    if get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in get_args(tp) if a is not type(None)]
        if len(args) == 1:
            return args[0]
    return tp


def _check_bounds(value: Any, metadata: Mapping[str, Any], source: str, key: str) -> None:
    """Check numeric bounds; tuples/lists (e.g. per-channel coefficients) are checked element by element."""
    if value is None or not any(b in metadata for b in _BOUND_CHECKS):
        return
    if isinstance(value, (tuple, list)):
        for i, v in enumerate(value):
            _check_bounds(v, metadata, source, f"{key}[{i}]")
        return
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return
    for bound_name, (ok, symbol) in _BOUND_CHECKS.items():
        if bound_name in metadata and not ok(value, metadata[bound_name]):
            raise ConfigError(
                f"{source}: '{key}' = {value!r} is out of range; it must be {symbol} {metadata[bound_name]}"
            )


def _type_error(source: str, key: str, value: Any, expected: str) -> ConfigError:
    return ConfigError(f"{source}: '{key}' = {value!r} has the wrong type; expected {expected}")


def _coerce(value: Any, tp: Any, source: str, key: str) -> Any:  # noqa: C901 - a type switch
    origin = get_origin(tp)
    if tp is Any:
        return value
    if origin is Literal:
        allowed = get_args(tp)
        if value not in allowed:
            raise ConfigError(
                f"{source}: '{key}' = {value!r} is not allowed; allowed values: {', '.join(map(repr, allowed))}"
            )
        return value
    if origin in (typing.Union, types.UnionType):
        args = get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in (a for a in args if a is not type(None)):
            try:
                return _coerce(value, arg, source, key)
            except ConfigError as exc:
                errors.append(str(exc))
        if errors:
            raise ConfigError(errors[-1])
        raise _type_error(source, key, value, str(tp))
    if origin is tuple:
        return _coerce_tuple(value, get_args(tp), source, key)
    if origin in (dict, Mapping):
        if not isinstance(value, Mapping):
            raise _type_error(source, key, value, "a table")
        _, vt = get_args(tp) or (str, Any)
        return {str(k): _coerce(v, vt, source, f"{key}.{k}") for k, v in value.items()}
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        return _build(tp, value, source, key + ".", None)
    return _coerce_scalar(value, tp, source, key)


def _coerce_tuple(value: Any, args: tuple[Any, ...], source: str, key: str) -> tuple[Any, ...]:
    if not isinstance(value, (list, tuple)):
        raise _type_error(source, key, value, "a list")
    if len(args) == 2 and args[1] is Ellipsis:
        return tuple(_coerce(v, args[0], source, f"{key}[{i}]") for i, v in enumerate(value))
    if len(value) != len(args):
        raise ConfigError(f"{source}: '{key}' must have {len(args)} elements, got {len(value)}")
    return tuple(
        _coerce(v, a, source, f"{key}[{i}]") for i, (v, a) in enumerate(zip(value, args, strict=True))
    )


def _coerce_scalar(value: Any, tp: Any, source: str, key: str) -> Any:
    if tp is bool:
        if not isinstance(value, bool):
            raise _type_error(source, key, value, "true or false")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise _type_error(source, key, value, "an integer")
        if not -(2**63) <= value < 2**63:  # YAML/JSON integers are unbounded; numpy's are not
            raise ConfigError(f"{source}: '{key}' = {value} is out of the 64-bit integer range")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise _type_error(source, key, value, "a number")
        try:
            number = float(value)
        except OverflowError:  # an integer beyond float range
            number = math.inf
        if not math.isfinite(number):  # TOML and YAML accept nan and inf; no setting means them
            raise ConfigError(f"{source}: '{key}' = {value!r:.40} is not a finite number; give a finite value")
        return number
    if tp is str:
        if not isinstance(value, str):
            raise _type_error(source, key, value, "a string")
        return value
    if tp is np.ndarray:
        arr = np.asarray(value, dtype=np.float64) if isinstance(value, (list, tuple, np.ndarray)) else None
        if arr is None or arr.dtype == object:
            raise _type_error(source, key, value, "a list of numbers")
        return arr
    if tp is Path:
        if not isinstance(value, (str, Path)):
            raise _type_error(source, key, value, "a path string")
        return Path(value)
    raise _type_error(source, key, value, getattr(tp, "__name__", str(tp)))


def to_dict(cfg: Any) -> Any:
    """A JSON-serialisable view of a config (paths as strings, tuples as lists)."""
    if dataclasses.is_dataclass(cfg) and not isinstance(cfg, type):
        return {f.name: to_dict(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)}
    if isinstance(cfg, (list, tuple)):
        return [to_dict(v) for v in cfg]
    if isinstance(cfg, Mapping):
        return {str(k): to_dict(v) for k, v in cfg.items()}
    if isinstance(cfg, Path):
        return str(cfg)
    return cfg


def config_fingerprint_dict(cfg: Any) -> Any:
    """The part of a config that decides whether two runs are the same: :func:`to_dict` (JSON types only)
    without the dataclass fields whose value equals the field's default, recursively for nested configs.

    Adding a field with a default thus leaves the view, and the fingerprint, of every existing config
    unchanged, so results and checkpoints made before the field existed stay valid, while a non-default
    value still counts. Plain mappings and sequences are walked (their dataclass members reduced); other
    values pass through. Stage manifests and training checkpoints compare configs through this one view.

    Example:
        >>> from dataclasses import dataclass
        >>> @dataclass(frozen=True)
        ... class ICP:
        ...     max_iters: int = 50
        ...     tol: float = 1e-6
        >>> config_fingerprint_dict({"icp": ICP(max_iters=10), "source": "a.ply"})
        {'icp': {'max_iters': 10}, 'source': 'a.ply'}
    """
    return stored_fingerprint_dict(to_dict(cfg), cfg)


def stored_fingerprint_dict(stored: Any, like: Any) -> Any:
    """:func:`config_fingerprint_dict` of a config read back from disk.

    ``stored`` is the :func:`to_dict` form written by a run, possibly by an older version that lacked some
    fields; ``like`` is the config it is compared with, which says which keys are dataclass fields and what
    their defaults are. A stored key that is no longer a field is kept (it counts as a difference), and a
    nested config whose fields are all at their defaults is dropped when its default is that same config.
    """
    return _plain(_reduce(stored, like, _MISSING))


def config_differences(stored: Any, cfg: Any) -> list[str]:
    """Dotted key paths where a stored config (to_dict form) and ``cfg`` differ, fields at defaults aside.

    Empty when a run made with ``stored`` may be reused or resumed under ``cfg``.
    """
    a, b = _flatten(stored_fingerprint_dict(stored, cfg)), _flatten(config_fingerprint_dict(cfg))
    keys = {k for k in set(a) | set(b) if a.get(k, _MISSING) != b.get(k, _MISSING)}
    return sorted(k for k in keys if not any(o.startswith(k + ".") for o in keys))  # the deepest keys only


def _reduce(stored: Any, like: Any, ref: Any) -> Any:
    """``stored`` without its default-valued dataclass fields; ``ref`` is the default instance of ``like``
    (a nested config's defaults come from its parent's default), or ``_MISSING`` for the class defaults."""
    if dataclasses.is_dataclass(like) and not isinstance(like, type) and isinstance(stored, Mapping):
        fields = {f.name: f for f in dataclasses.fields(like)}
        same_ref = ref is not _MISSING and type(ref) is type(like)
        out: dict[str, Any] = {}
        for key, value in stored.items():
            f = fields.get(key)
            if f is None:  # a field this version does not have: it counts
                out[key] = value
                continue
            default = getattr(ref, key) if same_ref else _field_default(f)
            sub = getattr(like, key)
            if dataclasses.is_dataclass(sub) and isinstance(value, Mapping):
                reduced = _reduce(value, sub, default)
                if reduced or type(default) is not type(sub):  # {} differs from a None default
                    out[key] = reduced
            elif default is _MISSING or _plain(value) != _plain(to_dict(default)):
                out[key] = _reduce(value, sub, _MISSING)
        return out
    if isinstance(like, Mapping) and isinstance(stored, Mapping):
        return {k: _reduce(v, like[k], _MISSING) if k in like else v for k, v in stored.items()}
    if isinstance(like, (list, tuple)) and isinstance(stored, (list, tuple)) and len(like) == len(stored):
        return [_reduce(s, x, _MISSING) for s, x in zip(stored, like, strict=True)]
    return stored


def _field_default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return _MISSING


def _plain(obj: Any) -> Any:
    """JSON types only (tuples as lists, arrays as lists, paths as strings), so stored and live values compare."""
    return json.loads(json.dumps(to_dict(obj), sort_keys=True, default=_json_value))


def _json_value(obj: Any) -> Any:
    if isinstance(obj, (np.ndarray, np.generic)):
        return obj.tolist()
    return repr(obj)


def _flatten(obj: Any, prefix: str = "") -> dict[str, Any]:
    """Leaves of nested mappings by dotted key path; an empty mapping is a leaf (except at the top)."""
    if isinstance(obj, Mapping) and (obj or not prefix):
        out: dict[str, Any] = {}
        for k, v in obj.items():
            out.update(_flatten(v, f"{prefix}.{k}" if prefix else str(k)))
        return out
    return {prefix: obj}


def resolve(
    cls: type[T],
    presets: Mapping[str, T] | None = None,
    preset: str | None = None,
    path: Path | None = None,
    overrides: Mapping[str, Any] | None = None,
) -> T:
    """The config a stage runs with: preset, then file keys, then explicit overrides.

    Raises:
        ConfigError: unknown preset (listing the allowed ones) or any strict-load error.
    """
    base: T | None = None
    if preset is not None:
        if not presets or preset not in presets:
            allowed = ", ".join(sorted(presets or {}))
            raise ConfigError(f"unknown preset {preset!r} for {cls.__name__}; allowed presets: {allowed}")
        base = presets[preset]
    cfg = from_dict(cls, {}, base=base) if base is not None else cls()
    if path is not None:
        cfg = from_dict(cls, read_mapping(Path(path)), source=str(path), base=cfg)
    if overrides:
        cfg = from_dict(cls, dict(overrides), source="command line", base=cfg)
    return cfg
