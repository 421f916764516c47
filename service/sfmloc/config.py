"""Configuration as pydantic models, read from files and ``SFMLOC_...`` environment variables.

Precedence, lowest to highest: model defaults < config file < environment < explicit
overrides (command-line flags). Environment variables are ``<PREFIX><FIELD>`` in upper case;
nested models use ``__`` (``SFMLOC_ENGINE__K=50``). Values are parsed as JSON when they look
like JSON (numbers, lists, objects, booleans) and as plain strings otherwise, then validated by
the model, so a typo fails loudly with the variable's name.
"""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ConfigDict, ValidationError

from .errors import ConfigError

ENV_PREFIX = "SFMLOC_"

M = TypeVar("M", bound=BaseModel)


class StrictModel(BaseModel):
    """Base for every configuration model: unknown keys are errors, not silently ignored."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)


def read_config_file(path: str | Path) -> dict[str, Any]:
    """A JSON or TOML file as a dict."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"cannot read config file {path}: {exc}") from None
    try:
        if path.suffix.lower() == ".toml":
            if sys.version_info >= (3, 11):
                import tomllib

                return tomllib.loads(text)
            raise ConfigError(f"{path}: TOML config files need Python 3.11+; use JSON")
        return json.loads(text)
    except ConfigError:
        raise
    except Exception as exc:  # noqa: BLE001 - any parse error is a config error naming the file
        raise ConfigError(f"cannot parse config file {path}: {exc}") from None


def _parse_env_value(raw: str) -> Any:
    s = raw.strip()
    if s[:1] in '[{"' or s in ("true", "false", "null") or _looks_numeric(s):
        try:
            return json.loads(s)
        except json.JSONDecodeError:
            return raw
    return raw


def _looks_numeric(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def env_overrides(
    model: type[BaseModel], prefix: str, environ: Mapping[str, str]
) -> dict[str, Any]:
    """The nested dict of values that ``environ`` sets for ``model`` under ``prefix``."""
    out: dict[str, Any] = {}
    for name, field in model.model_fields.items():
        key = f"{prefix}{name}".upper()
        sub = field.annotation
        if isinstance(sub, type) and issubclass(sub, BaseModel):
            nested = env_overrides(sub, key + "__", environ)
            if nested:
                out[name] = nested
        if key in environ:
            out[name] = _parse_env_value(environ[key])
    return out


def _deep_merge(base: dict[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, Mapping) and isinstance(out.get(k), Mapping):
            out[k] = _deep_merge(dict(out[k]), v)
        else:
            out[k] = v
    return out


def load_config(
    model: type[M],
    file: str | Path | None = None,
    *,
    prefix: str = ENV_PREFIX,
    environ: Mapping[str, str] | None = None,
    overrides: Mapping[str, Any] | None = None,
) -> M:
    """Build ``model`` from defaults, a config file, the environment and explicit overrides."""
    data: dict[str, Any] = {}
    if file is not None:
        data = _deep_merge(data, read_config_file(file))
    data = _deep_merge(
        data, env_overrides(model, prefix, os.environ if environ is None else environ)
    )
    if overrides:
        data = _deep_merge(data, {k: v for k, v in overrides.items() if v is not None})
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        where = f" (file {file}, environment {prefix}*)" if file else f" (environment {prefix}*)"
        raise ConfigError(f"invalid {model.__name__}{where}:\n{exc}") from None


def merge_presets(defaults: M, **changes: Any) -> M:
    """hloc-style: a named preset is a dict of changes merged over the defaults."""
    return type(defaults).model_validate(_deep_merge(defaults.model_dump(), changes))
