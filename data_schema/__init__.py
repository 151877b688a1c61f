"""Episode file format (HDF5): the field declaration, the Episode type, its atomic writer, reader and validator."""
from importlib import import_module

_EXPORTS = {  # name -> submodule; imported on first use so that `python -m data_schema.<module>` runs cleanly
    "FIELDS": "fields", "Field": "fields", "SCHEMA_VERSION": "fields",
    "EpisodeError": "checks",
    "EPISODE_SUFFIX": "episode", "Episode": "episode", "read_episode": "episode", "write_episode": "episode",
    "check": "validate", "validate_episode": "validate",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module 'data_schema' has no attribute {name!r}")
    return getattr(import_module(f"data_schema.{_EXPORTS[name]}"), name)
