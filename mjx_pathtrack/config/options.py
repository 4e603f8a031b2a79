"""Nested, typed configurations with flat option names.

A configuration is a frozen dataclass whose fields may be frozen dataclasses themselves
(``TrainConfig(env=EnvConfig(reward=RewardWeights(...)), ppo=PPOConfig(...))``). Each leaf
option has a dotted path (``"env.reward.distance"``); the :class:`Options` mixin adds *flat
names* on top (``FLAT_NAMES``: ``"alpha" -> ("env.reward.distance",)``), the names the command
line (``--alpha``), sweep files and old flat ``config.json`` files use. One flat name may set
several paths (``beta`` sets both deviation weights).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import types
import typing
from typing import Any, ClassVar


class ConfigError(ValueError):
    """An option that cannot work; the message names the option (as its command-line flag) and
    what is allowed."""


class Options:
    """Mixin for a frozen dataclass config: ``get``/``replace`` by flat name or dotted path, the
    flat view, JSON. Subclasses set ``FLAT_NAMES`` (flat name -> dotted paths) and may override
    :meth:`upgrade_flat` (old flat ``config.json`` contents -> today's flat names)."""

    FLAT_NAMES: ClassVar[dict[str, tuple[str, ...]]] = {}

    @classmethod
    def paths(cls, name: str) -> tuple[str, ...]:
        """The dotted paths option ``name`` (a flat name or a dotted path) sets."""
        if name in cls.FLAT_NAMES:
            return cls.FLAT_NAMES[name]
        if "." in name:
            return (name,)
        raise ConfigError(f"unknown option {name!r}; options: {', '.join(cls.FLAT_NAMES)} (or a dotted path "
                         f"such as env.substeps)")

    def get(self, name: str) -> Any:
        """The value of option ``name`` (a flat name: the value at its first path)."""
        value: Any = self
        for part in self.paths(name)[0].split("."):
            if not dataclasses.is_dataclass(value) or part not in {f.name for f in dataclasses.fields(value)}:
                raise ConfigError(f"unknown option {name!r}")
            value = getattr(value, part)
        return value

    def replace(self, **changes: Any):
        """A copy with options changed; keys are flat names or dotted paths
        (``**{"env.substeps": 48}``). Lists become tuples and integers floats where the field
        wants them; dicts of a nested block become that block."""
        config = self
        for name, value in changes.items():
            for path in self.paths(name):
                try:
                    config = _set(config, path.split("."), value, path)
                except ConfigError:
                    raise
                except ValueError as e:  # a block's own check (e.g. EnvConfig's), named by the flag
                    text = str(e)
                    leaf = path.rsplit(".", 1)[-1]
                    text = text[len(leaf) + 1:] if text.startswith(leaf + " ") else text
                    raise ConfigError(f"--{name.replace('_', '-')}: {text}") from None
        return config

    def flat(self) -> dict[str, Any]:
        """Every flat option name with its value (the command line's view of the config)."""
        return {name: self.get(name) for name in self.FLAT_NAMES}

    @classmethod
    def from_flat(cls, values: dict[str, Any]):
        """The default config with ``values`` (flat names or dotted paths) applied."""
        return cls().replace(**values)

    def to_json(self) -> str:
        """``config.json`` text, nested like the dataclasses."""
        return json.dumps(dataclasses.asdict(self), indent=2) + "\n"

    @classmethod
    def upgrade_flat(cls, data: dict[str, Any]) -> dict[str, Any]:
        """The flat contents of an old ``config.json`` in today's flat names (default: as they are)."""
        return data

    @classmethod
    def from_json(cls, text: str):
        """The config of a ``config.json``: the nested format, or the flat one written before the
        configs were nested (:meth:`upgrade_flat`). Unknown keys raise ``ValueError`` naming them."""
        data = json.loads(text)
        if not isinstance(data, dict):
            raise ValueError("config.json must hold a JSON object")
        nested = {f.name for f in dataclasses.fields(cls) if dataclasses.is_dataclass(_hints(cls)[f.name])}
        if any(isinstance(data.get(k), dict) for k in nested):
            return from_dict(cls, data)
        data = cls.upgrade_flat(dict(data))
        unknown = sorted(set(data) - set(cls.FLAT_NAMES))
        if unknown:
            raise ValueError(f"unknown config keys: {unknown}")
        return cls.from_flat(data)


def _hints(cls) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _options(hint) -> tuple:
    return typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, types.UnionType) else (hint,)


def _coerce(hint, value: Any, where: str) -> Any:
    """``value`` as the field type ``hint`` wants it: dicts become dataclasses, lists tuples,
    integers floats (JSON and the command line do not keep these apart)."""
    options = _options(hint)
    for option in options:
        if dataclasses.is_dataclass(option) and isinstance(value, dict):
            return from_dict(option, value, where)
    if isinstance(value, list) and any(typing.get_origin(o) is tuple for o in options):
        return tuple(value)
    if isinstance(value, int) and not isinstance(value, bool) and float in options and int not in options:
        return float(value)
    return value


def from_dict(cls, data: dict[str, Any], where: str = ""):
    """``cls(**data)`` with nested dataclasses built from their dicts; unknown keys are errors."""
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"unknown config keys: {[where + k for k in unknown]}")
    hints = _hints(cls)
    return cls(**{k: _coerce(hints[k], v, f"{where}{k}.") for k, v in data.items()})


def _set(obj, parts: list[str], value: Any, path: str):
    """``obj`` with the field at ``parts`` (a dotted path split) set to ``value``."""
    if not dataclasses.is_dataclass(obj) or parts[0] not in {f.name for f in dataclasses.fields(obj)}:
        raise ConfigError(f"unknown option {path!r}")
    head = parts[0]
    if len(parts) == 1:
        new = _coerce(_hints(type(obj))[head], value, path + ".")
    else:
        new = _set(getattr(obj, head), parts[1:], value, path)
    return dataclasses.replace(obj, **{head: new})


def leaves(obj, prefix: str = "") -> dict[str, Any]:
    """``{dotted path: value}`` of every non-dataclass field of a (nested) dataclass."""
    out = {}
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            out.update(leaves(value, f"{prefix}{f.name}."))
        else:
            out[prefix + f.name] = value
    return out


def differences(a, b) -> list[str]:
    """The dotted paths whose values differ between two configs of one class."""
    la, lb = leaves(a), leaves(b)
    return [k for k in la if la[k] != lb[k]]


def _optional(kind):
    """argparse type of an optional option: 'none' is None, anything else ``kind(text)``."""
    def parse(text: str):
        return None if text.lower() == "none" else kind(text)

    parse.__name__ = kind.__name__  # argparse names the type in its error messages
    return parse


def leaf_type(cls, path: str):
    """The annotated type of the field at dotted ``path`` of dataclass ``cls``."""
    *head, last = path.split(".")
    for part in head:
        cls = _hints(cls)[part]
    return _hints(cls)[last]


def add_flags(parser: argparse.ArgumentParser, cls, choices: dict[str, tuple] | None = None,
              skip: tuple[str, ...] = ()) -> None:
    """One ``--flat-name`` flag per flat option of config class ``cls`` (defaults: ``cls()``'s
    values): booleans ``--x/--no-x``, tuples ``nargs='+'`` (``'*'`` where empty by default), optional values accept
    ``none``; ``choices``: allowed values per flat name."""
    choices = choices or {}
    defaults = cls().flat()
    for name, value in defaults.items():
        if name in skip:
            continue
        hint = leaf_type(cls, cls.FLAT_NAMES[name][0])
        options = _options(hint)
        flag = "--" + name.replace("_", "-")
        if isinstance(value, bool):
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=value)
        elif typing.get_origin(hint) is tuple:  # tuple[int, ...] or tuple[str, ...]
            parser.add_argument(flag, type=typing.get_args(hint)[0], nargs="*" if not value else "+",
                                default=list(value))
        elif type(None) in options:  # optional: a number or a path
            kind = float if float in options else str
            parser.add_argument(flag, type=_optional(kind), default=value,
                                help="'none' to unset" if value is not None else None)
        else:
            parser.add_argument(flag, type=type(value), default=value, choices=choices.get(name))


def from_flags(args: argparse.Namespace, cls, skip: tuple[str, ...] = ()):
    """The config of parsed :func:`add_flags` flags."""
    return cls.from_flat({name: getattr(args, name) for name in cls.FLAT_NAMES if name not in skip})
