"""The ``sim_command`` parameter: an operator and a fault injector for the simulated terminal.

Simulation only (``device:=sim``). Set it with ``ros2 param set /mmd/pose_node sim_command
"place bar3 dr5"``; several commands may be joined with ``;``. The answer (or the reason a
command was refused) is the parameter service's reason text.

World (the digital twin, :class:`mmd_ros.hardware.twin_source.TwinSource`):

- ``place <bar> <pair>``: put a bar (``bar1``..``bar6``, ``ref1``) on a reference socket pair
- ``remove <bar>``: take a bar off and lay it in its case
- ``hold <bar> <length_mm>``: hold a bar at a centre distance (e.g. outside its calibrated range)
- ``mount``: the six measuring bars between the plates (reference bars back on their pairs)
- ``move <bar> [seconds] [amplitude_um]``: the bar is bumped and oscillates (3 s, 20 µm)

Terminal faults (:class:`mmd_ros.hardware.sim_backend.SimTerminal`):

- ``unplug`` / ``plug``: pull the USB cable and put it back
- ``corrupt <n>``: the next n frames on the wire get a bad checksum
- ``drop <n>``: the next n samples are never sent (a sequence gap)
- ``reset_counters``: the terminal's counters restart (power loss of its counter section)
- ``stall`` / ``resume``: the terminal's USB side hangs / recovers
- ``signal_lost <channel>`` / ``signal_ok <channel>``: a channel's encoder signal is lost (its
  readhead unplugged or dirty: the terminal flags every sample) / good again
"""

from __future__ import annotations

import shlex

from mmd_ros.hardware.sim_backend import SimTerminal
from mmd_ros.hardware.twin_source import TwinSource
from mmd_ros.twin import TwinError

__all__ = ['COMMANDS', 'SimCommandError', 'run_commands']

COMMANDS = ('place', 'remove', 'hold', 'mount', 'move', 'unplug', 'plug', 'corrupt', 'drop',
            'reset_counters', 'stall', 'resume', 'signal_lost', 'signal_ok')


class SimCommandError(ValueError):
    """A ``sim_command`` that cannot be carried out."""


def _int(text: str, what: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise SimCommandError(f'{what} must be an integer, got {text!r}') from None
    if value < 1:
        raise SimCommandError(f'{what} must be >= 1, got {value}')
    return value


def _float(text: str, what: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise SimCommandError(f'{what} must be a number, got {text!r}') from None


def run_command(words: list[str], source: TwinSource, terminal: SimTerminal) -> str:
    """Carry out one command; returns what was done."""
    if not words:
        return ''
    cmd, args = words[0], words[1:]
    need = {'place': 2, 'remove': 1, 'hold': 2, 'mount': 0, 'unplug': 0, 'plug': 0,
            'corrupt': 1, 'drop': 1, 'reset_counters': 0, 'stall': 0, 'resume': 0,
            'signal_lost': 1, 'signal_ok': 1}
    if cmd not in COMMANDS:
        raise SimCommandError(f'unknown command {cmd!r}; commands: {", ".join(COMMANDS)}')
    if cmd == 'move':
        if not 1 <= len(args) <= 3:
            raise SimCommandError('usage: move <bar> [seconds] [amplitude_um]')
    elif cmd == 'place':
        if len(args) not in (2, 3):
            raise SimCommandError(f'place takes 2 arguments, <bar> <pair>, and optionally short or '
                                  f'long; got {args}')
    elif len(args) != need[cmd]:
        raise SimCommandError(f'{cmd} takes {need[cmd]} argument(s), got {args}')
    try:
        if cmd == 'place':
            source.place(args[0], args[1], args[2] if len(args) > 2 else '')
            return f'{args[0]} placed on {args[1]}' + (f' from {args[2]}' if len(args) > 2 else '')
        if cmd == 'remove':
            source.remove(args[0])
            return f'{args[0]} removed'
        if cmd == 'hold':
            source.hold(args[0], _float(args[1], 'length_mm') * 1e-3)
            return f'{args[0]} held at {args[1]} mm'
        if cmd == 'mount':
            source.mount()
            return 'measuring bars mounted'
        if cmd == 'move':
            seconds = _float(args[1], 'seconds') if len(args) > 1 else 3.0
            amp = _float(args[2], 'amplitude_um') * 1e-6 if len(args) > 2 else 20e-6
            source.disturb(args[0], seconds, amp)
            return f'{args[0]} moving for {seconds:g} s'
    except (TwinError, KeyError) as exc:
        raise SimCommandError(str(exc).strip('"')) from None
    if cmd == 'unplug':
        terminal.unplug()
        return 'cable pulled'
    if cmd == 'plug':
        terminal.plug()
        return 'cable plugged in'
    if cmd == 'corrupt':
        n = _int(args[0], 'corrupt n')
        terminal.corrupt_frames(n)
        return f'{n} frame(s) will be corrupted'
    if cmd == 'drop':
        n = _int(args[0], 'drop n')
        terminal.drop_frames(n)
        return f'{n} sample(s) will be dropped'
    if cmd == 'reset_counters':
        # one step for the terminal and the world: the reset and the world's note of the clock
        # restart happen under the terminal's lock (see TwinSource.note_counter_reset)
        with terminal._cond:  # noqa: SLF001 - the simulated terminal offers no other hook
            terminal.reset_counters()
            source.note_counter_reset()
        return 'counters reset'
    if cmd == 'stall':
        terminal.stall()
        return 'terminal stalled'
    if cmd in ('signal_lost', 'signal_ok'):
        if args[0] not in source.names:
            raise SimCommandError(f'no channel {args[0]!r}; channels are {list(source.names)}')
        k = list(source.names).index(args[0])
        lost = cmd == 'signal_lost'
        terminal.set_signal_lost(k, lost)
        if not lost:
            terminal.set_quadrature_error(k, False)
        return f'{args[0]}: encoder signal ' + ('lost' if lost else 'good')
    terminal.resume()
    return 'terminal resumed'


def run_commands(text: str, source: TwinSource, terminal: SimTerminal) -> str:
    """Carry out ``;``-separated commands; raises :class:`SimCommandError` on the first bad one."""
    done = []
    for part in text.split(';'):
        try:
            words = shlex.split(part)
        except ValueError as exc:
            raise SimCommandError(f'cannot parse {part!r}: {exc}') from None
        if words:
            done.append(run_command(words, source, terminal))
    return '; '.join(d for d in done if d) or 'nothing to do'
