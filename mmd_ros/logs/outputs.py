"""Where a command may write: never over a file it reads, never over a raw log unless asked.

Every command of ``mmd`` that writes (``process --out/--csv``, ``analyze --out``, ``iso230-2
--out``, ``simulate --out``, the design tools' ``--out``) checks its outputs here first, against
the files it reads, before it reads or computes anything:

- an output that is one of the inputs is refused, with or without ``--force``: paths are
  compared as files (``os.path.samefile``: a relative path, a symlink or a hard link to the
  log is the log);
- an output that is an existing raw log (an MCAP file with ``/mmd/raw_counts``: a recording, a
  simulated run) is refused unless ``force`` is set — a raw log cannot be made again;
- two outputs may not be the same file, and a folder output may not be an existing file.

:func:`replacing` then writes a file under a temporary name beside it and renames it into place
only when the command succeeded: a refused or failed command leaves nothing behind, and an
older output stays whole until the new one is complete.
"""

from __future__ import annotations

import contextlib
import fnmatch
import mmap
import os
import secrets
from collections.abc import Iterable, Iterator
from pathlib import Path

from mmd_ros.logs.errors import LogError

__all__ = ['OutputError', 'check_output_folder', 'check_outputs', 'is_raw_log', 'replacing']

RAW_TOPIC = b'/mmd/raw_counts'
MCAP_MAGIC = b'\x89MCAP0\r\n'
FOOTER_SIZE = 1 + 8 + 8 + 8 + 4  # opcode, length, summary start, summary offset start, CRC


class OutputError(LogError):
    """A command was asked to write where it must not."""


PathLike = str | os.PathLike[str]


def _same(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist (yet): compare the resolved names
        return os.path.realpath(a) == os.path.realpath(b)


def is_raw_log(path: PathLike) -> bool:
    """Whether ``path`` is an MCAP log holding ``/mmd/raw_counts``.

    The topic name is looked for in the file's bytes (channel records are stored uncompressed
    before the chunks and again in the summary). A log without a summary (a recording cut by a
    crash) may hold its channels only inside compressed chunks: it is read to be sure."""
    p = Path(path)
    try:
        with open(p, 'rb') as handle:
            if handle.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
                return False
            size = os.fstat(handle.fileno()).st_size
            with mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ) as data:
                if data.find(RAW_TOPIC) >= 0:
                    return True
                complete = size >= 2 * len(MCAP_MAGIC) + FOOTER_SIZE and data[-len(MCAP_MAGIC):] == MCAP_MAGIC
    except (OSError, ValueError):
        return False
    if complete:
        return False
    from mmd_ros.logs.reader import LogReader
    try:
        return LogReader(p).has_topic(RAW_TOPIC.decode())
    except LogError:
        return False


def check_outputs(outputs: Iterable[tuple[str, PathLike | None]], inputs: Iterable[PathLike | None],
                  *, force: bool = False) -> None:
    """Refuse outputs that are inputs, existing raw logs (unless ``force``) or each other.

    outputs : (option, path) pairs, e.g. ('--out', 'run.processed.mcap'); None is skipped
    inputs : every file the command reads; None is skipped
    """
    ins = [Path(p) for p in inputs if p is not None]
    seen: list[tuple[str, Path]] = []
    for option, raw in outputs:
        if raw is None:
            continue
        out = Path(raw)
        for src in ins:
            if _same(out, src):
                raise OutputError(f'{option} {out}: that is {src}, which this command reads; '
                                  'write the output elsewhere (nothing was written)')
        for other, path in seen:
            if _same(out, path):
                raise OutputError(f'{option} {out}: {other} writes that file too (nothing was written)')
        if out.is_dir():
            raise OutputError(f'{option} {out}: is a folder, not a file (nothing was written)')
        if not force and out.exists() and is_raw_log(out):
            raise OutputError(f'{option} {out}: is a raw log (it holds /mmd/raw_counts) and would '
                              'be overwritten; choose another name, or pass --force if you really '
                              'mean to replace it (nothing was written)')
        seen.append((option, out))


def check_output_folder(option: str, folder: PathLike | None, inputs: Iterable[PathLike | None],
                        patterns: Iterable[str]) -> None:
    """Refuse a folder output that is an existing file, or in which the command would write
    (file names matching ``patterns``) over one of its inputs."""
    if folder is None:
        return
    out = Path(folder)
    if out.exists() and not out.is_dir():
        raise OutputError(f'{option} {out}: is a file, not a folder (nothing was written)')
    pats = list(patterns)
    for raw in inputs:
        if raw is None:
            continue
        src = Path(raw)
        if not src.exists():
            continue
        for pattern in pats:
            if fnmatch.fnmatch(src.name, pattern) and _same(out / src.name, src):
                raise OutputError(f'{option} {out}: this command writes {src.name} there, over '
                                  f'{src}, which it reads; choose another folder (nothing was written)')


@contextlib.contextmanager
def replacing(path: PathLike) -> Iterator[Path]:
    """A temporary path beside ``path`` to write to; renamed onto ``path`` (through a symlink,
    which stays) when the block ends without an error, removed when it raises."""
    target = Path(os.path.realpath(path))
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f'.{target.name}.{os.getpid()}.{secrets.token_hex(4)}.part')
    try:
        yield tmp
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
