"""A small JSON Schema validator for the schemas cascal ships (no third-party dependency).

It implements the subset of JSON Schema (draft 2020-12) that ``io/schemas/*/*.json`` use
and refuses any other keyword, so a schema cannot silently ask for a check that is not
made: ``$ref`` (local), ``type``, ``const``, ``enum``, ``required``, ``properties``,
``additionalProperties``, ``items``, ``minItems``, ``maxItems``, ``minimum``,
``exclusiveMinimum``, ``minLength``, ``pattern`` and ``oneOf``.
"""

from __future__ import annotations

import json
import re
from functools import cache
from importlib import resources
from typing import Any

__all__ = ["SchemaError", "load_schema", "validate"]

_ANNOTATIONS = {"$schema", "$id", "$defs", "$comment", "title", "description", "default"}
_CHECKS = {
    "$ref",
    "type",
    "const",
    "enum",
    "required",
    "properties",
    "additionalProperties",
    "items",
    "minItems",
    "maxItems",
    "minimum",
    "exclusiveMinimum",
    "minLength",
    "pattern",
    "oneOf",
}
_TYPES = {
    "object": lambda v: isinstance(v, dict),
    "array": lambda v: isinstance(v, list),
    "string": lambda v: isinstance(v, str),
    "boolean": lambda v: isinstance(v, bool),
    "null": lambda v: v is None,
    "number": lambda v: type(v) in (int, float),
    "integer": lambda v: type(v) is int or (type(v) is float and v.is_integer()),
}


class SchemaError(ValueError):
    """An instance does not match its schema; ``path`` says where (``$.stages[1].x``)."""

    def __init__(self, path: str, message: str, *, of_type: bool = False) -> None:
        self.path = path
        self.detail = message
        self.of_type = of_type  # the instance is of another JSON type than expected
        super().__init__(f"{path}: {message}")


def load_schema(name: str, version: int) -> dict:
    """The shipped schema ``io/schemas/<version>/<name>.json``, parsed: a new dict each
    call, so a caller's edits reach no other."""
    return json.loads(_schema_text(name, version))


@cache
def _schema_text(name: str, version: int) -> str:
    return resources.files("cascal.io").joinpath(f"schemas/{version}/{name}.json").read_text()


def validate(instance: Any, schema: dict, *, root: dict | None = None, path: str = "$") -> None:
    """Raise :class:`SchemaError` at the first place ``instance`` breaks ``schema``."""
    root = schema if root is None else root
    for key, rule in schema.items():
        if key in _ANNOTATIONS:
            continue
        if key not in _CHECKS:
            raise ValueError(f"schema keyword {key!r} is not supported by cascal's validator")
        if key == "$ref":
            validate(instance, _resolve(root, rule), root=root, path=path)
        elif key == "oneOf":
            _one_of(instance, rule, root, path)
        elif key == "type":
            names = [rule] if isinstance(rule, str) else rule
            if not any(_TYPES[t](instance) for t in names):
                got = _kind(instance)
                raise SchemaError(path, f"expected {' or '.join(names)}, got {got}", of_type=True)
        elif key == "const" and not _same(instance, rule):
            raise SchemaError(path, f"expected {rule!r}, got {_short(instance)}")
        elif key == "enum" and not any(_same(instance, r) for r in rule):
            raise SchemaError(path, f"expected one of {rule}, got {_short(instance)}")
        elif isinstance(instance, dict):
            _object(instance, key, rule, schema, root, path)
        elif isinstance(instance, list):
            _array(instance, key, rule, root, path)
        elif key in ("minimum", "exclusiveMinimum") and type(instance) in (int, float):
            if instance < rule or (key == "exclusiveMinimum" and instance == rule):
                op = ">" if key == "exclusiveMinimum" else ">="
                raise SchemaError(path, f"expected a number {op} {rule}, got {instance!r}")
        elif key in ("minLength", "pattern") and isinstance(instance, str):
            if key == "minLength" and len(instance) < rule:
                raise SchemaError(path, f"expected at least {rule} characters")
            if key == "pattern" and not re.search(rule, instance):
                raise SchemaError(path, f"expected text matching {rule!r}, got {instance!r}")


def _object(inst: dict, key: str, rule: Any, schema: dict, root: dict, path: str) -> None:
    if key == "required":
        missing = [k for k in rule if k not in inst]
        if missing:
            raise SchemaError(path, f"missing {', '.join(map(repr, missing))}")
    elif key == "properties":
        for k, sub in rule.items():
            if k in inst:
                validate(inst[k], sub, root=root, path=f"{path}.{k}")
    elif key == "additionalProperties":
        extra = [k for k in inst if k not in schema.get("properties", {})]
        if rule is False and extra:
            raise SchemaError(path, f"unexpected {', '.join(map(repr, extra))}")
        if isinstance(rule, dict):
            for k in extra:
                validate(inst[k], rule, root=root, path=f"{path}.{k}")


def _array(inst: list, key: str, rule: Any, root: dict, path: str) -> None:
    if key == "items":
        sub = _resolve(root, rule["$ref"]) if set(rule) == {"$ref"} else rule
        if sub == {"type": "number"}:  # fast path for long numeric arrays
            for i, v in enumerate(inst):
                if type(v) not in (int, float):
                    raise SchemaError(f"{path}[{i}]", f"expected number, got {_kind(v)}")
            return
        for i, v in enumerate(inst):
            validate(v, sub, root=root, path=f"{path}[{i}]")
    elif key == "minItems" and len(inst) < rule:
        raise SchemaError(path, f"expected at least {rule} items, got {len(inst)}")
    elif key == "maxItems" and len(inst) > rule:
        raise SchemaError(path, f"expected at most {rule} items, got {len(inst)}")


def _one_of(inst: Any, options: list, root: dict, path: str) -> None:
    errors = []
    for option in options:
        try:
            validate(inst, option, root=root, path=path)
        except SchemaError as exc:
            errors.append(exc)
    if len(errors) == len(options):  # the option that matched furthest: of the right type
        raise max(errors, key=lambda e: (len(e.path), not e.of_type))
    if len(errors) < len(options) - 1:
        raise SchemaError(path, "matches more than one of the allowed forms")


def _resolve(root: dict, ref: str) -> dict:
    if not ref.startswith("#/"):
        raise ValueError(f"only local $ref are supported, got {ref!r}")
    node: Any = root
    for part in ref[2:].split("/"):
        node = node[part]
    return node


def _same(a: Any, b: Any) -> bool:
    if _TYPES["number"](a) and _TYPES["number"](b):
        return a == b
    return type(a) is type(b) and a == b


def _kind(v: Any) -> str:
    for name in ("null", "boolean", "integer", "number", "string", "array", "object"):
        if _TYPES[name](v):
            return name
    return type(v).__name__


def _short(v: Any) -> str:
    text = json.dumps(v) if not isinstance(v, float) or v == v else repr(v)
    return text if len(text) <= 40 else text[:37] + "..."
