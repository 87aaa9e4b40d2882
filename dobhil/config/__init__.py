"""Configuration: the key table (``schema``) and loading/validation (``load``)."""

from dobhil.config.load import build_config, load_config, parse_override, resolve_config, to_yaml
from dobhil.config.schema import Config, key_fields

__all__ = ["Config", "build_config", "key_fields", "load_config", "parse_override", "resolve_config",
           "to_yaml"]
