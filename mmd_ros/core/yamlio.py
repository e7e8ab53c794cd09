"""Reading and writing the YAML files of the core (device, calibration, model, ambient profile),
in one place: errors name the file, sizes are bounded, and writes are atomic.

Reading. A file is read only up to :data:`MAX_YAML_BYTES` (a wrong path to a disk image or to
``/dev/zero`` is refused, not read without end), must be UTF-8 text, and its YAML must not
expand to more than :data:`MAX_YAML_NODES` nodes. PyYAML shares the node of an alias instead of
copying it, so a ten-line file of nested aliases (a "billion laughs") loads in microseconds but
is a tree of 10^9 nodes to anything that walks it — our validators, ``yaml.safe_dump`` when the
model is written into a processed log, ``json.dump`` of ``--json``. We count the nodes of the
tree as it would be expanded (shared nodes counted each time they are used, computed once),
and refuse beyond the limit; a recursive alias (``&a [*a]``) is refused too. Aliases themselves
stay allowed: a user may well write the same joint table once and refer to it (``<<: *base``),
and none of our files comes anywhere near the limit (the largest, a model with knot tables, is
a few thousand nodes).

Writing. :func:`atomic_write_text` writes a temporary file beside the target, fsyncs it, keeps
the previous file as ``.bak`` by a hard link (or a copy where links are not possible) — never by
moving the only good copy away — then renames the new file over the target and fsyncs the
folder. Killed at any moment, the target holds the old content or the new one, complete. The
file mode of the file replaced is kept. :func:`interrupted_saves` finds what an interrupted
save can leave beside a file (its ``.bak``, temporaries), so that a loader that finds no file
can say so.
"""

from __future__ import annotations

import contextlib
import errno
import os
import secrets
import shutil
import stat
from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml

from mmd_ros.core.errors import ConfigError

__all__ = [
    'MAX_YAML_BYTES', 'MAX_YAML_NODES', 'WRITE_STEPS', 'atomic_write_text', 'interrupted_saves',
    'parse_yaml', 'read_text_file', 'read_yaml',
]

#: Largest YAML file or text read [bytes]: 8 MiB, a thousand times our largest file.
MAX_YAML_BYTES = 8 * 1024 * 1024
#: Most nodes a YAML document may expand to (aliases counted as copies).
MAX_YAML_NODES = 200_000
#: The steps of :func:`atomic_write_text`, in order; :data:`fault_hook` is called after each.
WRITE_STEPS = ('temp_created', 'temp_written', 'backup_linked', 'backup_done', 'replaced',
               'folder_synced')

#: Called with each step's name as :func:`atomic_write_text` passes it (tests crash the writer
#: there); None in normal use.
fault_hook: Callable[[str], None] | None = None


#: libyaml's parser when PyYAML was built with it (its wheels are): the same nodes and data,
#: 5–50 times faster than the pure-Python one, which took about 0.1 s of every ``mmd process``
#: on the device description and calibration it reads from the log.
_Loader = getattr(yaml, 'CSafeLoader', yaml.SafeLoader)


class _TooLarge(Exception):
    pass


def _expanded_nodes(root: yaml.Node) -> int:
    """Nodes of the document with every alias expanded (each shared node computed once)."""
    memo: dict[int, int] = {}
    active: set[int] = set()

    def size(node: yaml.Node) -> int:
        key = id(node)
        if key in memo:
            return memo[key]
        if key in active:
            raise _TooLarge('an alias refers to the node that contains it (endless recursion)')
        active.add(key)
        if isinstance(node, yaml.MappingNode):
            n = 1 + sum(size(k) + size(v) for k, v in node.value)
        elif isinstance(node, yaml.SequenceNode):
            n = 1 + sum(size(v) for v in node.value)
        else:
            n = 1
        active.discard(key)
        memo[key] = n
        return n

    return size(root)


def parse_yaml(text: str, source: str) -> Any:
    """YAML text to data; invalid YAML, or YAML beyond the size limits, raises
    :class:`ConfigError` naming ``source``."""
    if len(text) > MAX_YAML_BYTES:
        raise ConfigError(source, '(file)', f'is {len(text)} characters long; at most '
                          f'{MAX_YAML_BYTES} are read (is it the right file?)')
    loader = _Loader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        nodes = _expanded_nodes(node)
        if nodes > MAX_YAML_NODES:
            raise _TooLarge(f'expands to {nodes:.3g} nodes (aliases counted as copies); at most '
                            f'{MAX_YAML_NODES} are allowed')
        return loader.construct_document(node)
    except yaml.YAMLError as exc:  # its text spans lines (with a caret under the column): one line here
        raise ConfigError(source, '(file)', f'is not valid YAML: {" ".join(str(exc).split())}') from None
    except _TooLarge as exc:
        raise ConfigError(source, '(file)', f'is refused: its YAML {exc}') from None
    except RecursionError:
        raise ConfigError(source, '(file)', 'is refused: its YAML is nested too deeply') from None
    finally:
        loader.dispose()


def interrupted_saves(path: str | os.PathLike[str]) -> list[Path]:
    """What an interrupted :func:`atomic_write_text` may have left beside ``path``: the backup
    (``<name>.bak``) and temporary files (``.<name>.*.tmp``, and ``<name>.*.tmp`` of older
    versions), newest first."""
    p = Path(path)
    if not p.parent.is_dir():
        return []
    found = [q for q in (p.with_name(p.name + '.bak'),) if q.is_file()]
    found += [q for pattern in (f'.{p.name}.*.tmp', f'{p.name}.*.tmp') for q in p.parent.glob(pattern)
              if q.is_file()]
    return sorted(set(found), key=lambda q: q.stat().st_mtime, reverse=True)


def read_text_file(path: str | os.PathLike[str], what: str = 'file') -> str:
    """The UTF-8 text of a small file; a missing, unreadable, binary or oversized file raises
    :class:`ConfigError` naming it (and, for a missing one, what an interrupted save left)."""
    p = Path(path)
    try:
        with open(p, 'rb') as handle:
            raw = handle.read(MAX_YAML_BYTES + 1)
    except FileNotFoundError:
        left = interrupted_saves(p)
        hint = ''
        if left:
            hint = ('; an interrupted save left ' + ', '.join(str(q) for q in left)
                    + f': check it and copy it to {p.name} to use it')
        raise ConfigError(str(p), '(file)', f'cannot be read: No such file or directory{hint}') from None
    except OSError as exc:
        raise ConfigError(str(p), '(file)', f'cannot be read: {exc.strerror or exc}') from None
    if len(raw) > MAX_YAML_BYTES:
        raise ConfigError(str(p), '(file)', f'is larger than {MAX_YAML_BYTES} bytes: not a {what} '
                          '(is it the right file?)')
    try:
        return raw.decode('utf-8')
    except UnicodeDecodeError as exc:
        raise ConfigError(str(p), '(file)', f'is not a text file (byte {exc.start} is not UTF-8): '
                          f'not a {what} (is it the right file?)') from None


def read_yaml(path: str | os.PathLike[str]) -> Any:
    """Read and parse a YAML file; a missing, unreadable, binary, oversized or invalid file
    raises :class:`ConfigError` naming it."""
    return parse_yaml(read_text_file(path, 'YAML file'), str(path))


def _step(name: str) -> None:
    if fault_hook is not None:
        fault_hook(name)


def _temp_beside(target: Path) -> Path:
    return target.with_name(f'.{target.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp')


def _fsync_folder(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY | getattr(os, 'O_DIRECTORY', 0))
    except OSError:
        return  # a folder that cannot be opened cannot be synced either (some network file systems)
    try:
        os.fsync(fd)
    except OSError as exc:
        if exc.errno not in (errno.EINVAL, errno.ENOTSUP, errno.EBADF):
            raise
    finally:
        os.close(fd)


def _backup(target: Path) -> Path:
    """A second name for the current ``target`` under a temporary name: a hard link, or a
    synced copy where the file system has none."""
    link = _temp_beside(target.with_name(target.name + '.bak'))
    try:
        os.link(target, link)
    except OSError:
        shutil.copy2(target, link)
        with open(link, 'rb') as handle:
            os.fsync(handle.fileno())
    return link


def atomic_write_text(path: str | os.PathLike[str], text: str, *, backup: bool = False) -> Path:
    """Write ``text`` to ``path`` atomically: killed at any moment, ``path`` holds the old
    content or the new one, complete (see the module docstring for the steps).

    backup : keep the previous file as ``<name>.bak`` (a hard link or a copy of it, made before
        the new file replaces it)
    A symlink at ``path`` is written through (the link stays); the mode of the file replaced is
    kept, a new file gets the usual mode (0666 less the umask). Returns the path written.
    """
    target = Path(os.path.realpath(path))
    folder = target.parent
    folder.mkdir(parents=True, exist_ok=True)
    try:
        old_mode: int | None = stat.S_IMODE(os.stat(target).st_mode)
    except FileNotFoundError:
        old_mode = None
    tmp = _temp_beside(target)
    link: Path | None = None
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, 'w', encoding='utf-8') as handle:
            _step('temp_created')
            handle.write(text)
            handle.flush()
            if old_mode is not None:
                os.fchmod(handle.fileno(), old_mode)
            os.fsync(handle.fileno())
        _step('temp_written')
        if backup and old_mode is not None:
            link = _backup(target)
            _step('backup_linked')
            os.replace(link, target.with_name(target.name + '.bak'))
            link = None
            _step('backup_done')
        os.replace(tmp, target)
        _step('replaced')
        _fsync_folder(folder)
        _step('folder_synced')
    except BaseException:
        for leftover in (tmp, link):
            if leftover is not None:
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(leftover)
        raise
    return target
