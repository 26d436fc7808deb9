"""Typed YAML schemas: dataclasses whose fields carry unit, doc and range, validated on load.

One mechanism serves the runtime config and the per-robot calibration file, so both get the same
one-line errors ("FILE: key 'a.b': problem") and the same documented template rendering.
"""

from __future__ import annotations

import difflib
import math
import typing
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any, TypeVar

import yaml

from runtime.errors import ConfigError

T = TypeVar("T")


def setting(
    default: Any,
    doc: str,
    unit: str = "",
    *,
    min: float | None = None,
    max: float | None = None,
    min_exclusive: bool = False,
    choices: tuple[Any, ...] | None = None,
) -> Any:
    """A documented schema field. Tuples are immutable, so they are safe plain defaults."""
    meta = {
        "doc": doc,
        "unit": unit,
        "min": min,
        "max": max,
        "min_exclusive": min_exclusive,
        "choices": choices,
    }
    return field(default=default, metadata=meta)


def derived(default: Any, doc: str, source: str, unit: str = "") -> Any:
    """A field a stage reads but no one sets in its section: `Config` fills it from `source`,
    the one key that sets the value, so two stages cannot disagree on it (the footprint, the
    control period). Refused in a file or an override; not rendered."""
    return field(default=default, metadata={"doc": doc, "unit": unit, "derived": source})


def _derived_from(f: Any) -> str | None:
    return f.metadata.get("derived")


def section(cls: type[T], doc: str) -> Any:
    """A nested schema section with its own documentation line."""
    return field(default_factory=cls, metadata={"doc": doc})


@dataclass(frozen=True)
class _Where:
    source: str
    key: str

    def error(self, problem: str) -> ConfigError:
        return ConfigError(f"{self.source}: key '{self.key}': {problem}")


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is tuple:
        args = typing.get_args(tp)
        return f"a list of {len(args)} numbers"
    return {float: "a number", int: "an integer", str: "a string", bool: "true or false"}.get(
        tp, str(tp)
    )


def _coerce(tp: Any, value: Any, where: _Where) -> Any:
    """Check one scalar or tuple against its annotated type; ints widen to floats, nothing else."""
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise where.error(f"expected {_type_name(tp)}, got {value!r}")
        if not math.isfinite(value):
            raise where.error(f"must be finite, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise where.error(f"expected {_type_name(tp)}, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise where.error(f"expected {_type_name(tp)}, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise where.error(f"expected {_type_name(tp)}, got {value!r}")
        return value
    if typing.get_origin(tp) is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, (list, tuple)) or len(value) != len(args):
            raise where.error(f"expected {_type_name(tp)}, got {value!r}")
        return tuple(_coerce(a, v, where) for a, v in zip(args, value))
    raise TypeError(f"unsupported schema type {tp!r}")  # a schema bug, not a user mistake


def _check_range(meta: dict[str, Any], value: Any, where: _Where) -> None:
    unit = f" {meta['unit']}" if meta.get("unit") else ""
    if meta.get("choices") is not None and value not in meta["choices"]:
        allowed = ", ".join(repr(c) for c in meta["choices"])
        raise where.error(f"must be one of {allowed}, got {value!r}")
    lo, hi = meta.get("min"), meta.get("max")
    for v in value if isinstance(value, tuple) else (value,):
        if lo is not None and (v < lo or (meta.get("min_exclusive") and v == lo)):
            bound = f"greater than {lo}" if meta.get("min_exclusive") else f"at least {lo}"
            raise where.error(f"must be {bound}{unit}, got {v}")
        if hi is not None and v > hi:
            raise where.error(f"must be at most {hi}{unit}, got {v}")


def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def build(cls: type[T], data: Any, source: str, prefix: str = "") -> T:
    """Build a schema dataclass from parsed YAML, rejecting unknown keys, wrong types and ranges."""
    where = _Where(source, prefix.rstrip(".") or "<top level>")
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise where.error(f"expected a mapping of keys, got {type(data).__name__}")
    if not is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a schema dataclass")
    known = {f.name: f for f in fields(cls)}
    for key in data:
        if key not in known:
            hint = difflib.get_close_matches(str(key), known, n=1)
            suggestion = f" (did you mean '{prefix}{hint[0]}'?)" if hint else ""
            raise ConfigError(f"{source}: unknown key '{prefix}{key}'{suggestion}")
        if (origin := _derived_from(known[key])) is not None:
            raise ConfigError(f"{source}: key '{prefix}{key}' is not set here: it follows"
                              f" '{origin}'; set that instead")
    hints = _hints(cls)
    values: dict[str, Any] = {}
    for name, f in known.items():
        if name not in data:
            continue
        tp = hints[name]
        if isinstance(tp, type) and is_dataclass(tp):
            values[name] = build(tp, data[name], source, f"{prefix}{name}.")
            continue
        fwhere = _Where(source, f"{prefix}{name}")
        value = _coerce(tp, data[name], fwhere)
        _check_range(dict(f.metadata), value, fwhere)
        values[name] = value
    return cls(**values)


def to_plain(obj: Any) -> Any:
    """Schema dataclass → plain dicts/lists, for printing and writing."""
    if is_dataclass(obj):
        return {f.name: to_plain(getattr(obj, f.name)) for f in fields(obj)
                if _derived_from(f) is None}
    if isinstance(obj, tuple):
        return [to_plain(v) for v in obj]
    return obj


class _DuplicateKey(yaml.YAMLError):
    def __init__(self, key: str, line: int, first_line: int) -> None:
        super().__init__(f"duplicate key {key!r}")
        self.key, self.line, self.first_line = key, line, first_line


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader that refuses a mapping with a key given twice: PyYAML keeps the last value
    without a word, so a forgotten earlier line would silently lose one of two settings."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: dict[Any, int] = {}
        for key_node, _value in node.value:
            key = self.construct_object(key_node, deep=True)
            line = key_node.start_mark.line + 1
            if isinstance(key, str | int | float | bool) and key in seen:
                raise _DuplicateKey(str(key), line, seen[key])
            if isinstance(key, str | int | float | bool):
                seen[key] = line
        return super().construct_mapping(node, deep=deep)


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG,
                              _StrictLoader.construct_mapping)


def load_yaml_file(path: Path, what: str) -> Any:
    """Read a YAML file, turning every way it can fail into one line naming the file."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(f"{path}: {what} not found") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read {what}: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: {what} is not UTF-8 text") from None
    try:
        return yaml.load(text, Loader=_StrictLoader)  # a SafeLoader subclass: no code runs
    except _DuplicateKey as exc:
        raise ConfigError(f"{path}: line {exc.line}: key '{exc.key}' given twice (first on line"
                          f" {exc.first_line}); delete one") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f" line {mark.line + 1}:" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(f"{path}:{line} invalid YAML: {problem}") from None


def apply_override(data: dict[str, Any], cls: type, assignment: str) -> None:
    """Apply one `--set a.b=value` to parsed YAML data; the value is parsed as YAML."""
    key, sep, raw = assignment.partition("=")
    if not sep or not key:
        raise ConfigError(f"--set {assignment!r}: expected KEY=VALUE, e.g. base.port=/dev/ttyUSB0")
    parts = key.strip().split(".")
    node_cls: Any = cls
    node = data
    for i, part in enumerate(parts):
        known = {f.name: f for f in fields(node_cls)}
        if part not in known:
            dotted = ".".join(parts[: i + 1])
            hint = difflib.get_close_matches(part, known, n=1)
            suggestion = f" (did you mean '{'.'.join(parts[:i] + [hint[0]])}'?)" if hint else ""
            raise ConfigError(f"--set {key}: unknown key '{dotted}'{suggestion}")
        if (origin := _derived_from(known[part])) is not None:
            raise ConfigError(f"--set {key}: '{key}' follows '{origin}'; set that instead")
        tp = _hints(node_cls)[part]
        if i == len(parts) - 1:
            if is_dataclass(tp):
                raise ConfigError(f"--set {key}: '{key}' is a section; set one of its keys")
            try:
                node[part] = yaml.safe_load(raw) if raw.strip() else ""
            except yaml.YAMLError:
                raise ConfigError(f"--set {key}: cannot parse value {raw!r}") from None
            return
        if not is_dataclass(tp):
            raise ConfigError(f"--set {key}: '{'.'.join(parts[: i + 1])}' is not a section")
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            return  # the file's own section is malformed: build() reports it, naming the file
        node, node_cls = child, tp


def _yaml_scalar(value: Any) -> str:
    return yaml.safe_dump(to_plain(value), default_flow_style=True, width=1000).strip().removesuffix(
        "\n..."
    )


def render_documented(obj: Any, title: str, indent: int = 0) -> str:
    """YAML text of a schema instance with every key documented: what, unit, default, range."""
    lines: list[str] = []
    if indent == 0:
        lines += [f"# {line}" if line else "#" for line in title.splitlines()] + [""]
    pad = "  " * indent
    defaults = type(obj)()
    for f in fields(obj):
        if _derived_from(f) is not None:
            continue
        value = getattr(obj, f.name)
        meta = f.metadata
        if is_dataclass(value):
            lines.append(f"{pad}# {meta['doc']}")
            lines.append(f"{pad}{f.name}:")
            lines.append(render_documented(value, title, indent + 1).rstrip("\n"))
            lines.append("")
            continue
        unit = f" [{meta['unit']}]" if meta.get("unit") else ""
        facts = [f"default: {_yaml_scalar(getattr(defaults, f.name))}"]
        if meta.get("choices") is not None:
            facts.append("one of: " + ", ".join(_yaml_scalar(c) for c in meta["choices"]))
        if meta.get("min") is not None or meta.get("max") is not None:
            lo = meta.get("min")
            lo_txt = "-inf" if lo is None else str(lo)
            hi_txt = "inf" if meta.get("max") is None else str(meta["max"])
            bracket = "(" if meta.get("min_exclusive") else "["
            facts.append(f"range: {bracket}{lo_txt}, {hi_txt}]")
        lines.append(f"{pad}# {meta['doc']}{unit}. {'; '.join(facts)}.")
        lines.append(f"{pad}{f.name}: {_yaml_scalar(value)}")
    return "\n".join(lines) + "\n"

