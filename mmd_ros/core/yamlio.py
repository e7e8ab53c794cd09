"""Reading and writing the YAML files of the core (device, calibration, model), in one place:
errors name the file, and writes are atomic."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import yaml

from mmd_ros.core.errors import ConfigError

__all__ = ['atomic_write_text', 'parse_yaml', 'read_yaml']


def parse_yaml(text: str, source: str) -> Any:
    """YAML text to data; invalid YAML raises :class:`ConfigError` naming ``source``."""
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise ConfigError(source, '(file)', f'is not valid YAML: {exc}') from None


def read_yaml(path: str | os.PathLike[str]) -> Any:
    """Read and parse a YAML file; a missing, unreadable or invalid file raises
    :class:`ConfigError` naming it."""
    p = Path(path)
    try:
        text = p.read_text(encoding='utf-8')
    except OSError as exc:
        raise ConfigError(str(p), '(file)', f'cannot be read: {exc.strerror}') from None
    return parse_yaml(text, str(p))


def atomic_write_text(path: str | os.PathLike[str], text: str, *, backup: bool = False) -> Path:
    """Write ``text`` to ``path`` atomically (temporary file, fsync, rename), so a crash leaves
    the old file or the new one, never half of one. ``backup`` keeps the old file as ``.bak``."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=target.name + '.', suffix='.tmp', dir=target.parent)
    try:
        with os.fdopen(fd, 'w', encoding='utf-8') as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
        if backup and target.exists():
            os.replace(target, target.with_name(target.name + '.bak'))
        os.replace(tmp, target)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return target
