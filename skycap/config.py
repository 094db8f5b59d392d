"""Typed configuration: dataclasses loaded from TOML, overridden from the command line, saved beside outputs.

Every job has one top-level config dataclass (nested dataclasses for its parts, defaults for every
field). The same three steps serve every job:

    cfg = load_config(DemoConfig, path=args.config, overrides=args.set)   # TOML file + ``--set a.b=1``
    ...
    save_config(cfg, out_dir / "config.toml")                            # beside what it produced

Values are validated against the field types by msgspec; a wrong key or type raises
:class:`ConfigError` naming the offending key, the source and how to fix it.
"""

from __future__ import annotations

import argparse
import dataclasses
import enum
import tomllib
from pathlib import Path
from typing import Any, TypeVar

import msgspec
import tomli_w

from skycap.errors import SkycapError

T = TypeVar("T")

__all__ = [
    "ConfigError",
    "add_config_args",
    "config_from_args",
    "config_to_dict",
    "load_config",
    "parse_override",
    "save_config",
]


class ConfigError(SkycapError, ValueError):
    """A configuration file or override that does not fit the config's types."""


def parse_override(text: str) -> tuple[list[str], Any]:
    """Parse ``a.b.c=value`` into (["a", "b", "c"], value); the value is read as TOML, else a string."""
    if "=" not in text:
        raise ConfigError(f"override {text!r} is not of the form key.sub=value (example: --set orbit.radius_m=8)")
    key, raw = text.split("=", 1)
    key = key.strip()
    if not key:
        raise ConfigError(f"override {text!r} has an empty key")
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw
    return key.split("."), value


def _deep_merge(base: dict, update: dict) -> dict:
    out = dict(base)
    for k, v in update.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = v
    return out


def config_to_dict(cfg: Any) -> dict:
    """A config dataclass as plain TOML-able data (None fields left out, Paths and enums as strings)."""

    def clean(x: Any) -> Any:
        if dataclasses.is_dataclass(x) and not isinstance(x, type):
            return {f.name: clean(getattr(x, f.name)) for f in dataclasses.fields(x) if getattr(x, f.name) is not None}
        if isinstance(x, dict):
            return {str(k): clean(v) for k, v in x.items() if v is not None}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        if isinstance(x, Path):
            return str(x)
        if isinstance(x, enum.Enum):
            return x.value
        return x

    return clean(cfg)


def _convert(cls: type[T], data: dict, source: str) -> T:
    try:
        return msgspec.convert(data, type=cls, strict=False, dec_hook=_dec_hook)
    except msgspec.ValidationError as e:
        raise ConfigError(
            f"invalid configuration from {source}: {e}. "
            f"Fix the value in the file or override it with --set KEY=VALUE."
        ) from e


def _dec_hook(tp: type, obj: Any) -> Any:
    if tp is Path and isinstance(obj, str):
        return Path(obj)
    raise NotImplementedError


def load_config(cls: type[T], path: str | Path | None = None, overrides: list[str] | None = None) -> T:
    """Build ``cls`` from its defaults, then the TOML file at ``path`` (if any), then ``overrides``.

    Unknown keys are errors (a typo must not be silently ignored).
    """
    data = config_to_dict(cls())
    source = "defaults"
    if path is not None:
        p = Path(path)
        if not p.is_file():
            raise ConfigError(f"config file {p} does not exist; pass an existing TOML file to --config or leave it out")
        try:
            file_data = tomllib.loads(p.read_text())
        except tomllib.TOMLDecodeError as e:
            raise ConfigError(f"config file {p} is not valid TOML: {e}") from e
        _check_keys(cls, file_data, str(p))
        data = _deep_merge(data, file_data)
        source = str(p)
    for ov in overrides or []:
        keys, value = parse_override(ov)
        upd: dict = {}
        cur = upd
        for k in keys[:-1]:
            cur = cur.setdefault(k, {})
        cur[keys[-1]] = value
        _check_keys(cls, upd, f"--set {ov}")
        data = _deep_merge(data, upd)
        source += f" + --set {ov}"
    return _convert(cls, data, source)


def _check_keys(cls: type, data: dict, source: str, prefix: str = "") -> None:
    if not dataclasses.is_dataclass(cls):
        return
    hints = {f.name: f for f in dataclasses.fields(cls)}
    import typing

    types = typing.get_type_hints(cls)
    for k, v in data.items():
        if k not in hints:
            known = ", ".join(sorted(hints))
            raise ConfigError(f"unknown config key '{prefix}{k}' in {source}; known keys here: {known}")
        sub = types[k]
        if isinstance(v, dict) and dataclasses.is_dataclass(sub):
            _check_keys(sub, v, source, prefix=f"{prefix}{k}.")


def save_config(cfg: Any, path: str | Path) -> Path:
    """Write ``cfg`` as TOML; the file loads back to an equal config with :func:`load_config`."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(tomli_w.dumps(config_to_dict(cfg)))
    return p


def add_config_args(parser: argparse.ArgumentParser) -> None:
    """Add ``--config FILE`` and repeatable ``--set key.sub=value`` to a subcommand's parser."""
    parser.add_argument("--config", type=Path, default=None, help="TOML config file (defaults apply for missing keys)")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override one config value, e.g. --set orbit.radius_m=8 (repeatable; values are TOML)",
    )


def config_from_args(cls: type[T], args: argparse.Namespace, extra: dict[str, Any] | None = None) -> T:
    """Load ``cls`` from ``--config``/``--set`` and then apply ``extra`` (dotted key -> value, None skipped).

    ``extra`` carries a subcommand's convenience flags (``--drones 3`` -> {"fleet.drones": 3}).
    """
    overrides = list(getattr(args, "set", []) or [])
    cfg = load_config(cls, getattr(args, "config", None), overrides)
    if extra:
        data = config_to_dict(cfg)
        for dotted, value in extra.items():
            if value is None:
                continue
            cur = data
            keys = dotted.split(".")
            for k in keys[:-1]:
                cur = cur.setdefault(k, {})
            cur[keys[-1]] = value.as_posix() if isinstance(value, Path) else value
        cfg = _convert(cls, data, "command-line flags")
    return cfg
