"""Counting and pacing a sample stream that crosses processes (ROS-free).

Between two processes of the separate-node pipeline a sample can be lost: a reliable topic
with a keep-last queue of ``depth`` drops the oldest message when its reader falls more than
``depth`` behind. Nothing in the message says so; the publisher's sequence number does: the
middleware numbers every message a publisher writes 1, 2, 3... and hands the number to the
subscriber with the message (``publication_sequence_number`` of rclpy's message info).

- :class:`SequenceCounter`: one subscription's received messages and the messages lost before
  them (the jumps of the sequence number), per publisher session.
- :class:`StageProgress`: what a stage reports about its per-sample topics (messages taken and
  lost per input topic, published per output topic); it travels on ``pipeline/progress``.
- :class:`FlowControl`: a replay's view of the stages downstream: how many messages each one
  still has to take (published upstream minus taken and lost), whether to wait before sending
  more, and the summary of what arrived where.

A sample can still be lost after the last message a subscriber received (nothing follows to
show the gap): :class:`FlowControl` counts those too, as published upstream minus taken by the
stage, once the stream has ended.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

__all__ = ['FlowControl', 'InputProgress', 'SequenceCounter', 'StageProgress', 'StageState']


class SequenceCounter:
    """Messages received on one subscription and those lost before them.

    ``note(seq)`` for every message in arrival order, ``seq`` the publisher's sequence number
    (1, 2, 3... per publisher; None when the middleware does not provide it). A jump of k + 1
    counts k lost messages. A number that does not increase starts a new publisher session
    (the publisher restarted): nothing is counted lost across it, and the session's figures
    start again (``first``, ``last``, ``session_received``, ``session_lost``). With more than
    one publisher on the topic their numbers interleave; the caller then sets ``ambiguous`` and
    jumps are no longer counted.
    """

    def __init__(self) -> None:
        self.received = 0
        self.lost = 0
        self.gaps = 0
        self.sessions = 0
        self.supported = True
        self.ambiguous = False
        self.first = 0
        self.last = 0
        self.session_received = 0
        self.session_lost = 0

    def note(self, seq: int | None) -> int:
        """Count one message; returns how many were lost just before it."""
        self.received += 1
        self.session_received += 1
        if seq is None or seq <= 0:
            self.supported = False
            return 0
        last, self.last = self.last, seq
        if self.sessions == 0 or seq <= last:
            self.sessions += 1
            self.first = seq
            self.session_received = 1
            self.session_lost = 0
            return 0
        missing = seq - last - 1
        if missing and not self.ambiguous:
            self.lost += missing
            self.session_lost += missing
            self.gaps += 1
            return missing
        return 0


@dataclass(frozen=True)
class InputProgress:
    """One input topic of a stage, in the current publisher session (``sessions`` counts them):
    the first and last sequence numbers taken, the messages received and those seen lost
    (jumps) between them."""

    sessions: int = 0
    first: int = 0
    last: int = 0
    received: int = 0
    lost: int = 0

    @classmethod
    def of(cls, counter: SequenceCounter) -> InputProgress:
        return cls(counter.sessions, counter.first, counter.last, counter.session_received,
                   counter.session_lost)


@dataclass(frozen=True)
class StageProgress:
    """One report of a stage: its name, the queue depth of its inputs (0 unknown), per input
    topic (fully qualified) an :class:`InputProgress`, per output topic the messages it
    published in all (which is its publisher's last sequence number)."""

    stage: str
    inputs: dict[str, InputProgress] = field(default_factory=dict)
    published: dict[str, int] = field(default_factory=dict)
    depth: int = 0

    _FIELDS = ('sessions', 'first', 'last', 'received', 'lost')

    def to_pairs(self) -> list[tuple[str, str]]:
        """Key/value pairs: ``depth``, ``<topic> sessions|first|last|received|lost`` per
        input and ``<topic> published`` per output."""
        out = [('depth', str(self.depth))]
        out += [(f'{t} {k}', str(getattr(p, k))) for t, p in self.inputs.items() for k in self._FIELDS]
        out += [(f'{t} published', str(n)) for t, n in self.published.items()]
        return out

    @classmethod
    def from_pairs(cls, stage: str, pairs: Iterable[tuple[str, str]]) -> StageProgress:
        """The inverse of :meth:`to_pairs`; keys it does not know are ignored."""
        inputs: dict[str, dict[str, int]] = {}
        published: dict[str, int] = {}
        depth = 0
        for key, value in pairs:
            try:
                n = int(value)
            except ValueError:
                continue
            topic, _, what = key.rpartition(' ')
            if key == 'depth':
                depth = n
            elif topic and what == 'published':
                published[topic] = n
            elif topic and what in cls._FIELDS:
                inputs.setdefault(topic, {})[what] = n
        return cls(stage, {t: InputProgress(**v) for t, v in inputs.items()}, published, depth)


@dataclass
class StageState:
    """The last report of one stage, when it last changed (``progressed_at``), and what it had
    counted before this publisher began (``before``: the summary is about this run only).
    ``stalled``: it stopped taking messages while behind and is no longer waited for."""

    progress: StageProgress
    progressed_at: float
    before: StageProgress
    stalled: bool = False


class FlowControl:
    """A publisher's view of the stages downstream (see the module docstring).

    window : most messages a stage may still have to take before the publisher waits (at most
        half the stage's own queue depth, when it reports one)
    timeout_s : a stage that takes nothing for this long while it is behind is given up (no
        longer waited for; the summary says so)
    clock : monotonic time [s]

    Use: :meth:`note_progress` for every report, :meth:`begin` just before the first message,
    :meth:`note_sent` as messages go out, :meth:`waiting_for` before each batch,
    :meth:`drained` at the end, then :meth:`summary`.
    """

    def __init__(self, window: int, timeout_s: float = 10.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.window = int(window)
        self.timeout_s = float(timeout_s)
        self.clock = clock
        self.sent: dict[str, int] = {}
        self.stages: dict[str, StageState] = {}
        self.begun = False

    def begin(self, topics: Iterable[str]) -> None:
        """This publisher is about to send its first message on ``topics`` (zero sent so far):
        what the stages counted until now came from earlier publishers."""
        for topic in topics:
            self.sent[topic] = 0
        for st in self.stages.values():
            st.before = st.progress
        self.begun = True

    def note_sent(self, topic: str, n: int) -> None:
        """This publisher has sent ``n`` messages on ``topic`` in all."""
        self.sent[topic] = int(n)

    def note_progress(self, progress: StageProgress) -> None:
        old = self.stages.get(progress.stage)
        if old is None:
            # first heard after we began: its sessions on our topics are ours, unless their
            # numbers run past what we sent (an earlier publisher's)
            before = StageProgress(progress.stage) if not self.begun else StageProgress(
                progress.stage, {t: InputProgress(sessions=p.sessions - 1)
                                 if p.last <= self.sent.get(t, -1) else p
                                 for t, p in progress.inputs.items()})
            self.stages[progress.stage] = StageState(progress, self.clock(), before)
        elif old.progress != progress:  # a heartbeat without news is no progress
            old.progress, old.progressed_at = progress, self.clock()

    def _input(self, st: StageState, topic: str) -> tuple[InputProgress, int | None]:
        """The stage's progress on ``topic`` in this run and the messages published to it in
        this run (None when no one we know of publishes it)."""
        p = st.progress.inputs[topic]
        old = st.before.inputs.get(topic, InputProgress())
        if topic in self.sent:  # ours: a new session at the stage, numbered from 1
            if p.sessions <= old.sessions:
                p = InputProgress()
            return p, self.sent[topic]
        publishers = [s for s in self.stages.values() if topic in s.progress.published]
        if not publishers:
            return p, None
        upstream = sum(s.progress.published[topic] - s.before.published.get(topic, 0)
                       for s in publishers)
        if p.sessions == old.sessions:  # numbered since before this run: count from there
            base = sum(s.before.published.get(topic, 0) for s in publishers)
            p = InputProgress(p.sessions, max(1, p.first - base), p.last - base,
                              p.received - old.received, p.lost - old.lost)
        return p, upstream

    def backlog(self, st: StageState) -> int:
        """Messages published to the stage in this run that it has not taken yet, largest over
        its inputs."""
        worst = 0
        for topic in st.progress.inputs:
            p, upstream = self._input(st, topic)
            if upstream is not None:
                worst = max(worst, upstream - p.last)
        return worst

    def _behind(self, batch: int) -> list[str]:
        now = self.clock()
        behind = []
        for name, st in self.stages.items():
            if st.stalled or self.backlog(st) <= max(0, self.window_for(st) - batch):
                continue
            if now - st.progressed_at > self.timeout_s:
                st.stalled = True
                continue
            behind.append(name)
        return behind

    def window_for(self, st: StageState) -> int:
        """Messages the stage may have to take: ``window``, at most half its queue depth."""
        return self.window if not st.progress.depth else min(self.window, st.progress.depth // 2)

    def batch(self, largest: int = 64) -> int:
        """Messages to send at a time: at most half the smallest window."""
        windows = [self.window_for(st) for st in self.stages.values()] or [self.window]
        return max(1, min(largest, min(windows) // 2))

    def waiting_for(self, batch: int = 0) -> list[str]:
        """Stages that would be more than their window behind after ``batch`` more messages
        (those silent for ``timeout_s`` are given up)."""
        return self._behind(batch)

    def drained(self, quiet_s: float = 2.0) -> bool:
        """Every stage has taken everything published to it, or has taken nothing for
        ``quiet_s`` (what it still lacks was lost after its last message: the summary counts
        it as missing)."""
        now = self.clock()
        return all(st.stalled or self.backlog(st) <= 0 or now - st.progressed_at > quiet_s
                   for st in self.stages.values())

    def summary(self) -> list[dict[str, object]]:
        """Per stage and input topic, in this run: published upstream, received, lost
        (sequence jumps), and missing (published but neither received nor seen lost: before
        the stage's first message, after its last, or still on the way when it stopped
        answering). received + lost + missing = published."""
        out: list[dict[str, object]] = []
        for name, st in sorted(self.stages.items()):
            for topic in sorted(st.progress.inputs):
                p, upstream = self._input(st, topic)
                if upstream is None and not p.received:
                    continue  # no one publishes it
                missing = 0
                if upstream is not None:
                    missing = max(0, upstream - p.received - p.lost)
                out.append({'stage': name, 'topic': topic, 'published': upstream,
                            'received': p.received, 'lost': p.lost, 'missing': missing,
                            'stalled': st.stalled})
        return out

    @staticmethod
    def describe(rows: list[dict[str, object]]) -> str:
        """One clause per stage input: "<stage>: <topic> 5000 of 5000 received, none lost"."""
        parts = []
        for r in rows:
            total = r['published'] if r['published'] is not None else '?'
            text = f'{r["stage"]}: {r["topic"]} {r["received"]} of {total} received'
            lost = int(r['lost']) + int(r['missing'])  # type: ignore[call-overload]
            text += f', {lost} lost' if lost else ', none lost'
            if r['stalled']:
                text += ' (it stopped taking messages)'
            parts.append(text)
        return '; '.join(parts)
