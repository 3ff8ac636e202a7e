"""The generic part of the configuration: declare, validate, load and print frozen dataclasses.

A schema is a frozen dataclass of sections, each a frozen dataclass of keys. A key declares its
constraints next to it with :func:`setting` (``rate_hz: float = setting(100.0, positive)``) and
its documentation as the string literal after it; a section declares constraints between its
keys in ``RULES``. :func:`load_config` builds the schema from defaults, a TOML file and
``SECTION.KEY=VALUE`` overrides, checks every key's type and constraints, and raises
:class:`ConfigError` naming the first bad key (``imu.rate_hz: must be > 0, not 0``). A key
that moved is declared in the schema's ``RENAMED`` (``{"old.key": "new.key"}``): its old name
is still read, as the new one, with a one-line warning (:func:`renamed_notice`).
:func:`dump_toml` prints a config with each key's documentation and constraints as comments.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import inspect
import ipaddress
import itertools
import logging
import math
import os
import tomllib
import typing
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar
from urllib.parse import urlsplit

from brasidas.files import FileReadError, read_regular_file

C = TypeVar("C")
T = TypeVar("T")

_LOGGER = logging.getLogger(__name__)
_CHECKS = "brasidas.checks"
MAX_CONFIG_BYTES = 1024 * 1024
"""A config file is a few kilobytes; a larger one is refused, not read."""


class ConfigError(Exception):
    """A configuration problem: ``[SOURCE: ]SECTION.KEY: reason`` on one line."""

    def __init__(self, key: str, reason: str, source: str = "") -> None:
        self.key, self.reason, self.source = key, reason, source
        where = f"{key}: " if key else ""
        super().__init__(f"{source}: {where}{reason}" if source else f"{where}{reason}")


# --------------------------------------------------------------------------- constraints


@dataclass(frozen=True)
class Check:
    """One constraint on a value: ``ok(value)`` holds, else "must be {rule}"."""

    rule: str
    """What a valid value is, as in "must be {rule}" (also printed by ``dump_toml``)."""
    ok: Callable[[Any], bool]


@dataclass(frozen=True)
class Rule:
    """A constraint between keys of one section; ``key`` is the one named when it fails."""

    key: str
    rule: str
    """As in "{key} must be {rule}"; formatted with ``section`` (the section's name) and the
    section's keys, e.g. ``"> {section}.low ({low})"``."""
    ok: Callable[[Any], bool]
    """Called with the section."""
    others: tuple[str, ...] = ()
    """The other keys it reads: the error names the file of whichever of them was set there."""


def setting(default: T, *checks: Check) -> T:
    """A key's default and its constraints (a dataclass field; read back by :func:`checks_of`)."""
    value: T = dataclasses.field(default=default, metadata={_CHECKS: checks})
    return value


def checks_of(item: dataclasses.Field[Any]) -> tuple[Check, ...]:
    checks: tuple[Check, ...] = item.metadata.get(_CHECKS, ())
    return checks


def at_least(low: float, *, most: float | None = None) -> Check:
    """``low <= value`` (``<= most`` when given)."""
    if most is None:
        return Check(f">= {_number(low)}", lambda value: value >= low)
    return Check(f"between {_number(low)} and {_number(most)}", lambda value: low <= value <= most)


def above(low: float, *, most: float | None = None) -> Check:
    """``low < value`` (``<= most`` when given)."""
    if most is None:
        return Check(f"> {_number(low)}", lambda value: value > low)
    return Check(f"> {_number(low)} and <= {_number(most)}", lambda value: low < value <= most)


def _number(value: float) -> str:
    return str(int(value)) if float(value).is_integer() else repr(value)


positive = above(0)
non_negative = at_least(0)
fraction = above(0, most=1)
"""A share of full scale: 0 < value <= 1."""
bind_port = Check("a port number (0-65535; 0: any free port)", lambda value: 0 <= value <= 65535)
"""A port to bind: 0 lets the kernel choose."""
remote_port = Check("a port number (1-65535)", lambda value: 1 <= value <= 65535)
"""A port to send to."""
non_empty = Check("non-empty", lambda value: len(value) > 0)


def one_of(*choices: object) -> Check:
    return Check("one of " + ", ".join(map(_toml_value, choices)), lambda value: value in choices)


def each(check: Check) -> Check:
    """Every item of a list satisfies ``check``."""
    return Check(
        f"a list of items each {check.rule}", lambda value: all(check.ok(item) for item in value)
    )


def empty_or(check: Check) -> Check:
    """The empty string (the key's "not set") or a value satisfying ``check``."""
    return Check(f"empty or {check.rule}", lambda value: value == "" or check.ok(value))


def _is_ip(value: str) -> bool:
    try:
        ipaddress.ip_address(value)
    except ValueError:
        return False
    return True


def _is_host(value: str) -> bool:
    if _is_ip(value):
        return True
    labels = value.rstrip(".").split(".")
    return all(
        0 < len(label) <= 63
        and label.replace("-", "").isalnum()
        and label.isascii()
        and not label.startswith("-")
        and not label.endswith("-")
        for label in labels
    )


def _is_multicast(value: str) -> bool:
    return _is_ip(value) and ipaddress.ip_address(value).is_multicast


ip_address = Check("an IP address", _is_ip)


def _is_network(value: str) -> bool:
    try:
        ipaddress.ip_network(value, strict=False)
    except ValueError:
        return False
    return True


ip_network = Check("an IP address or network (address/prefix)", _is_network)
multicast_address = Check("a multicast IP address", _is_multicast)
host_name = Check("an IP address or a host name", _is_host)


def url(*schemes: str) -> Check:
    def ok(value: str) -> bool:
        parts = urlsplit(value)
        return parts.scheme in schemes and bool(parts.hostname)

    return Check(f"a {'/'.join(schemes)} URL", ok)


def ordered_across(low: str, high: str, why: str) -> Rule:
    """Key ``low`` (``section.key``) is less than key ``high`` of another section; ``why``
    says what goes wrong otherwise. A rule of the config class's own ``RULES``."""
    low_section, _, low_key = low.partition(".")
    high_section, _, high_key = high.partition(".")

    def ok(config: Any) -> bool:
        low_value: float = getattr(getattr(config, low_section), low_key)
        high_value: float = getattr(getattr(config, high_section), high_key)
        return low_value < high_value

    return Rule(high, f"> {low} ({{{low}}}): {why}", ok, (low,))


def ordered(low: str, high: str, *, strict: bool = True) -> Rule:
    """Key ``low`` is less than (or, not ``strict``, at most) key ``high``."""
    text = f"{{section}}.{low} ({{{low}}})"
    if strict:
        return Rule(high, f"> {text}", lambda s: getattr(s, low) < getattr(s, high), (low,))
    return Rule(high, f">= {text}", lambda s: getattr(s, low) <= getattr(s, high), (low,))


# --------------------------------------------------------------------------- loading


def load_config(
    cls: type[C],
    path: str | Path | None = None,
    overrides: Iterable[str] = (),
    notices: list[str] | None = None,
) -> C:
    """Build ``cls`` from defaults, then the TOML file at ``path``, then ``overrides``.

    Each override is ``SECTION.KEY=VALUE``, VALUE a TOML value or a bare string. A renamed
    key given by its old name is logged as a warning and appended to ``notices``.
    """
    values: dict[str, dict[str, tuple[Any, str]]] = {}
    found: list[str] = []
    if path is not None:
        source = str(path)
        if not os.path.lexists(path):
            raise ConfigError("", "file not found", source)
        try:
            raw = read_regular_file(path, "config", MAX_CONFIG_BYTES)
        except FileReadError as err:
            raise ConfigError("", str(err).removeprefix(f"{source}: "), source) from None
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as err:
            line = raw[: err.start].count(b"\n") + 1
            raise ConfigError(
                "", f"not UTF-8 text (byte 0x{raw[err.start]:02x} on line {line})", source
            ) from None
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as err:
            raise ConfigError("", f"invalid TOML: {err}", source) from None
        _collect(cls, _renamed(cls, data, source, found), source, values)
    for item in overrides:
        _collect(cls, _renamed(cls, _parse_override(item), "", found), "", values)
    config = _build(cls, values)
    for notice in found:
        _LOGGER.warning("%s", notice)
    if notices is not None:
        notices.extend(found)
    return config


def renamed_notice(old: str, new: str, source: str) -> str:
    """The one line said when a key is given by its old name."""
    where = f" in {source}" if source else " on the command line"
    return f"deprecated key {old}{where}: it is now {new} (read as such); rename it"


def _renamed(cls: type, data: dict[str, Any], source: str, found: list[str]) -> dict[str, Any]:
    """``data`` with the keys of the schema's ``RENAMED`` under their new names; a key given
    by both names in one place is an error (which one was meant?)."""
    renamed: Mapping[str, str] = getattr(cls, "RENAMED", {})
    if not renamed:
        return data
    result = {
        name: dict(table) if isinstance(table, dict) else table for name, table in data.items()
    }
    for name, table in data.items():
        if not isinstance(table, dict):
            continue
        for key in table:
            new = renamed.get(f"{name}.{key}")
            if new is None:
                continue
            new_section, _, new_key = new.partition(".")
            target = result.setdefault(new_section, {})
            if not isinstance(target, dict):
                continue  # "must be a table" is said by _collect
            if new_key in target:
                raise ConfigError(
                    f"{name}.{key}", f"renamed {new}, which is also set: keep only {new}", source
                )
            target[new_key] = result[name].pop(key)
            found.append(renamed_notice(f"{name}.{key}", new, source))
    return result


def _parse_override(item: str) -> dict[str, Any]:
    dotted, sep, raw = item.partition("=")
    parts = dotted.strip().split(".")
    if not sep or len(parts) != 2 or not all(parts):
        raise ConfigError("", f"--set {item}: expected SECTION.KEY=VALUE")
    try:
        value: Any = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw  # bare strings need no quotes on the command line
    return {parts[0]: {parts[1]: value}}


def _collect(
    cls: type, data: dict[str, Any], source: str, values: dict[str, dict[str, tuple[Any, str]]]
) -> None:
    """Check names and tables of ``data`` against the schema; record each value and its source."""
    sections = {item.name: item for item in dataclasses.fields(cls)}
    for name, table in data.items():
        if name not in sections:
            raise ConfigError(name, "unknown section" + _suggest(name, sections), source)
        if not isinstance(table, dict):
            raise ConfigError(name, "must be a table ([section])", source)
        keys = {item.name for item in dataclasses.fields(_section_type(cls, name))}
        for key, value in table.items():
            if key not in keys:
                raise ConfigError(f"{name}.{key}", "unknown key" + _suggest(key, keys), source)
            values.setdefault(name, {})[key] = (value, source)


def _build(cls: type[C], values: dict[str, dict[str, tuple[Any, str]]], base: C | None = None) -> C:
    sections: dict[str, Any] = {}
    for item in dataclasses.fields(cls):  # type: ignore[arg-type]
        section_type = _section_type(cls, item.name)
        hints = _hints(section_type)
        current = (
            getattr(base, item.name) if base is not None else _default_section(item, section_type)
        )
        given = values.get(item.name, {})
        changes = {
            key: _coerce(value, hints[key], f"{item.name}.{key}", source)
            for key, (value, source) in given.items()
        }
        section = dataclasses.replace(current, **changes)
        _validate_section(item.name, section, {key: source for key, (_, source) in given.items()})
        sections[item.name] = section
    config = cls(**sections)
    _validate_across(config, values)
    return config


def _validate_across(config: Any, values: dict[str, dict[str, tuple[Any, str]]]) -> None:
    """The config's own ``RULES``: constraints between keys of different sections, named
    ``section.key`` (and formatted with the sections, e.g. ``"{failsafe.hold_after}"``)."""
    for rule in getattr(config, "RULES", ()):
        if rule.ok(config):
            continue
        section, _, key = rule.key.partition(".")
        sources = []
        for dotted in (rule.key, *rule.others):
            name, _, field_name = dotted.partition(".")
            sources.append(values.get(name, {}).get(field_name, (None, ""))[1])
        sections = {item.name: getattr(config, item.name) for item in dataclasses.fields(config)}
        raise ConfigError(
            rule.key,
            f"must be {rule.rule.format(**sections)}, "
            f"not {_toml_value(getattr(getattr(config, section), key))}",
            next((source for source in sources if source), ""),
        )


def _validate_section(name: str, section: Any, sources: Mapping[str, str]) -> None:
    for item in dataclasses.fields(section):
        value = getattr(section, item.name)
        for check in checks_of(item):
            if not check.ok(value):
                raise ConfigError(
                    f"{name}.{item.name}",
                    f"must be {check.rule}, not {_toml_value(value)}",
                    sources.get(item.name, ""),
                )
    for rule in getattr(section, "RULES", ()):
        if not rule.ok(section):
            value = getattr(section, rule.key)
            raise ConfigError(
                f"{name}.{rule.key}",
                f"must be {_describe(rule, name, section)}, not {_toml_value(value)}",
                next((sources[k] for k in (rule.key, *rule.others) if sources.get(k)), ""),
            )


def _describe(rule: Rule, name: str, section: Any) -> str:
    keys = {item.name: getattr(section, item.name) for item in dataclasses.fields(section)}
    return rule.rule.format(section=name, **keys)


def _default_section(item: dataclasses.Field[Any], section_type: type) -> Any:
    """A section's defaults: its field's (a daemon may set other defaults for the keys of a
    section it shares), else the section type's own."""
    if item.default_factory is not dataclasses.MISSING:
        return item.default_factory()
    if item.default is not dataclasses.MISSING:
        return item.default
    return section_type()


def _section_type(cls: type, name: str) -> type:
    section: type = _hints(cls)[name]
    return section


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    """The class's resolved annotations, once: resolving them (string annotations, compiled
    each time) was most of loading a config."""
    return typing.get_type_hints(cls)


def _suggest(name: str, known: Iterable[str]) -> str:
    close = difflib.get_close_matches(name, list(known), n=1)
    return f" (did you mean '{close[0]}'?)" if close else ""


def _coerce(value: Any, expected: Any, dotted: str, source: str) -> Any:
    if typing.get_origin(expected) is tuple:
        item_type = typing.get_args(expected)[0]
        if not isinstance(value, list):
            raise ConfigError(dotted, f"must be a list of {_type_name(item_type)}", source)
        return tuple(_coerce(item, item_type, dotted, source) for item in value)
    if expected is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if expected is float and isinstance(value, float) and not math.isfinite(value):
        raise ConfigError(dotted, f"must be a finite number, not {value!r}", source)
    if (expected is int and isinstance(value, bool)) or not isinstance(value, expected):
        raise ConfigError(dotted, f"must be {_type_name(expected)}, not {value!r}", source)
    return value


def _type_name(expected: Any) -> str:
    names = {str: "a string", int: "an integer", float: "a number", bool: "true or false"}
    return names.get(expected, str(expected))


# --------------------------------------------------------------------------- dumping


def dump_toml(config: object) -> str:
    """The configuration as TOML, every key included, each with its docstring and constraints."""
    lines: list[str] = []
    for section in dataclasses.fields(config):  # type: ignore[arg-type]
        value = getattr(config, section.name)
        lines.append(f"[{section.name}]")
        lines.extend(
            f"# {rule.key} must be {_describe(rule, section.name, value)}."
            for rule in getattr(value, "RULES", ())
        )
        docs = _field_docs(type(value))
        for item in dataclasses.fields(value):
            doc = docs.get(item.name)
            if doc:
                lines.extend(f"# {line}" for line in doc.splitlines())
            checks = checks_of(item)
            if checks:
                lines.append("# Must be " + "; ".join(check.rule for check in checks) + ".")
            lines.append(f"{item.name} = {_toml_value(getattr(value, item.name))}")
        lines.append("")
    return "\n".join(lines)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        escaped = value.replace("\\", "\\\\").replace('"', '\\"')
        return f'"{escaped}"'
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(item) for item in value) + "]"
    raise TypeError(f"cannot write {value!r} as TOML")


def _field_docs(cls: type) -> dict[str, str]:
    """Attribute docstrings (the string literal after a field), read from the source of the
    class and of the classes it extends."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if dataclasses.is_dataclass(klass):
            docs.update(_own_field_docs(klass))
    return docs


def _own_field_docs(cls: type) -> dict[str, str]:
    import ast
    import textwrap

    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    except (OSError, TypeError):
        return {}
    docs: dict[str, str] = {}
    body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
    for node, following in itertools.pairwise(body):
        if (
            isinstance(node, ast.AnnAssign)
            and isinstance(node.target, ast.Name)
            and isinstance(following, ast.Expr)
            and isinstance(following.value, ast.Constant)
            and isinstance(following.value.value, str)
        ):
            docs[node.target.id] = inspect.cleandoc(following.value.value)
    return docs
