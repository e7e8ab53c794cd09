"""Counting and pacing a sample stream that crosses processes (ROS-free).

Between two processes of the separate-node pipeline a sample can be lost: a reliable topic
with a keep-last queue of ``depth`` drops the oldest message when its reader falls more than
``depth`` behind. Nothing in the message says so; the publisher's sequence number does: the
middleware numbers every message a publisher writes 1, 2, 3... and hands the number to the
subscriber with the message (``publication_sequence_number`` of rclpy's message info).

- :class:`SequenceCounter`: one subscription's received messages and the messages lost before
  them (the jumps of the sequence number), in all and since a mark.
- :class:`StageProgress`: what a stage reports about its per-sample topics: per input topic
  the last sequence number it took and what it received and lost since the current run began,
  per output topic what it published (in all and in the run); it travels on
  ``pipeline/progress``.
- :class:`StampPairing`: rows of two topics of one stream (``bar_lengths`` and ``thermal``) put
  back together by stamp, whatever the order in which the two topics arrive.
- :class:`FlowControl`: a replay's view of the stages downstream: how many messages each one
  still has to take (published upstream minus taken), whether to wait before sending more, and
  the summary of what arrived where.

A run is named by the replay (``pipeline/run``); each stage marks its counters when it hears
the name, before the first sample of the run is sent, so the summary is about that run only.
A sample can still be lost after the last message a subscriber received (nothing follows to
show the gap): the summary counts those as published minus received and lost.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

__all__ = ['FlowControl', 'InputProgress', 'SequenceCounter', 'StageProgress', 'StageState',
           'StampPairing']


class SequenceCounter:
    """Messages received on one subscription and those lost before them.

    ``note(seq)`` for every message in arrival order, ``seq`` the publisher's sequence number
    (1, 2, 3... per publisher; None when the middleware does not provide it). A jump of k + 1
    counts k lost messages. A number that does not increase starts a new publisher session
    (the publisher restarted): nothing is counted lost across it. With more than one publisher
    on the topic their numbers interleave; the caller then sets ``ambiguous`` and jumps are no
    longer counted. :meth:`mark` starts the counts ``run_received`` and ``run_lost``.
    """

    def __init__(self) -> None:
        self.received = 0
        self.lost = 0
        self.gaps = 0
        self.sessions = 0
        self.supported = True
        self.ambiguous = False
        self.last = 0
        self._mark = (0, 0)

    def note(self, seq: int | None) -> int:
        """Count one message; returns how many were lost just before it."""
        self.received += 1
        if seq is None or seq <= 0:
            self.supported = False
            return 0
        last, self.last = self.last, seq
        if self.sessions == 0 or seq <= last:
            self.sessions += 1
            return 0
        missing = seq - last - 1
        if missing and not self.ambiguous:
            self.lost += missing
            self.gaps += 1
            return missing
        return 0

    def mark(self) -> None:
        self._mark = (self.received, self.lost)

    @property
    def run_received(self) -> int:
        return self.received - self._mark[0]

    @property
    def run_lost(self) -> int:
        return self.lost - self._mark[1]


class StampPairing:
    """Rows of two per-sample topics of one stream, paired by stamp.

    Each topic comes from one publisher in stamp order, but the two topics reach a subscriber
    independently: after a busy spell one of them may arrive thousands of rows ahead of the
    other. A row waits for its partner for as long as the partner can still come, that is
    until the other topic has delivered a later stamp (the partner was lost on the way; when a
    topic's stamps go back, how far each topic has come starts again), or until more than
    ``max_pending`` rows of one topic wait (a bound on memory: set it to at least the
    subscriptions' queue depth, the most one topic can run ahead). Either way the row is
    counted in :attr:`unpaired`.
    """

    def __init__(self, max_pending: int) -> None:
        self.max_pending = int(max_pending)
        self._pending: tuple[OrderedDict[int, NDArray[np.float64]], ...] = (OrderedDict(), OrderedDict())
        self._newest: list[int | None] = [None, None]
        self.unpaired = 0

    def add(self, side: int, stamps_ns: NDArray[np.int64], rows: NDArray[np.float64]) -> None:
        """Rows (n, k) of topic ``side`` (0 or 1) stamped ``stamps_ns`` (n,), in arrival order."""
        pending = self._pending[side]
        for stamp, row in zip(stamps_ns.tolist(), rows):
            pending[stamp] = row
        if len(stamps_ns):
            newest = self._newest[side]
            if newest is not None and int(stamps_ns.min()) < newest:
                # this topic's stamps went back (a log played again without a new run): how far
                # each topic has come starts again
                self._newest = [None, None]
                newest = None
            top = int(stamps_ns.max())
            if newest is None or top > newest:
                self._newest[side] = top

    def take(self) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]] | None:
        """The rows paired so far, in stamp order: (stamps (n,), rows of topic 0, rows of topic
        1), or None; then gives up the rows whose partner can no longer come."""
        a, b = self._pending
        out = None
        if a and b:
            small, large = (a, b) if len(a) <= len(b) else (b, a)
            both = sorted(s for s in small if s in large)
            if both:
                out = (np.array(both, dtype=np.int64), np.array([a.pop(s) for s in both]),
                       np.array([b.pop(s) for s in both]))
        for side, pending in enumerate(self._pending):
            other = self._newest[1 - side]
            while pending and other is not None and next(iter(pending)) < other:
                pending.popitem(last=False)
                self.unpaired += 1
            while len(pending) > self.max_pending:
                pending.popitem(last=False)
                self.unpaired += 1
        return out

    def clear(self) -> None:
        """A new run (its stamps start again): give up every waiting row."""
        self.unpaired += len(self)
        for pending in self._pending:
            pending.clear()
        self._newest = [None, None]

    def __len__(self) -> int:
        return sum(len(p) for p in self._pending)


@dataclass(frozen=True)
class InputProgress:
    """One input topic of a stage: ``last`` the publisher's sequence number of the last message
    taken, ``received`` and ``lost`` since the run began, ``publishers`` the publishers the
    stage's subscription is matched with (-1 unknown)."""

    last: int = 0
    received: int = 0
    lost: int = 0
    publishers: int = -1

    @classmethod
    def of(cls, counter: SequenceCounter, publishers: int = -1) -> InputProgress:
        return cls(counter.last, counter.run_received, counter.run_lost, publishers)


@dataclass(frozen=True)
class StageProgress:
    """One report of a stage: its name, the run it counts for ('' none yet), the queue depth of
    its inputs (0 unknown), an :class:`InputProgress` per input topic (fully qualified), and per
    output topic the messages it published in all (its publisher's last sequence number) and
    since the run began (``published_run``)."""

    stage: str
    inputs: dict[str, InputProgress] = field(default_factory=dict)
    published: dict[str, int] = field(default_factory=dict)
    depth: int = 0
    run: str = ''
    published_run: dict[str, int] = field(default_factory=dict)

    _FIELDS = ('last', 'received', 'lost', 'publishers')

    def to_pairs(self) -> list[tuple[str, str]]:
        """Key/value pairs: ``run``, ``depth``, ``<topic> last|received|lost|publishers`` per input and
        ``<topic> published|published_run`` per output."""
        out = [('run', self.run), ('depth', str(self.depth))]
        out += [(f'{t} {k}', str(getattr(p, k))) for t, p in self.inputs.items() for k in self._FIELDS]
        out += [(f'{t} published', str(n)) for t, n in self.published.items()]
        out += [(f'{t} published_run', str(n)) for t, n in self.published_run.items()]
        return out

    @classmethod
    def from_pairs(cls, stage: str, pairs: Iterable[tuple[str, str]]) -> StageProgress:
        """The inverse of :meth:`to_pairs`; keys it does not know are ignored."""
        inputs: dict[str, dict[str, int]] = {}
        published: dict[str, int] = {}
        published_run: dict[str, int] = {}
        depth, run = 0, ''
        for key, value in pairs:
            if key == 'run':
                run = value
                continue
            try:
                n = int(value)
            except ValueError:
                continue
            topic, _, what = key.rpartition(' ')
            if key == 'depth':
                depth = n
            elif topic and what == 'published':
                published[topic] = n
            elif topic and what == 'published_run':
                published_run[topic] = n
            elif topic and what in cls._FIELDS:
                inputs.setdefault(topic, {})[what] = n
        return cls(stage, {t: InputProgress(**v) for t, v in inputs.items()}, published, depth, run,
                   published_run)


@dataclass
class StageState:
    """The last report of one stage, when it last changed (``progressed_at``) and when the
    last report came (``heard_at``: a stage repeats an unchanged report while it is idle).
    ``stalled``: it stopped taking messages while behind and is no longer waited for; ``late``:
    first heard after the publisher began (its counts may miss the start of the run)."""

    progress: StageProgress
    progressed_at: float
    stalled: bool = False
    late: bool = False
    heard_at: float = 0.0


class FlowControl:
    """A publisher's view of the stages downstream (see the module docstring).

    run : the name of this run (the stages count from the moment they hear it)
    window : most messages a stage may still have to take before the publisher waits (at most
        half the stage's own queue depth, when it reports one)
    timeout_s : a stage that takes nothing for this long while it is behind is given up (no
        longer waited for; the summary says so)
    clock : monotonic time [s]

    Use: :meth:`note_progress` for every report; :meth:`ready` until every stage counts for
    this run; :meth:`begin` just before the first message; :meth:`note_sent` as messages go
    out; :meth:`waiting_for` before each batch; :meth:`drained` at the end; :meth:`summary`.
    """

    def __init__(self, run: str, window: int, timeout_s: float = 10.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.run = run
        self.window = int(window)
        self.timeout_s = float(timeout_s)
        self.clock = clock
        self.sent: dict[str, int] = {}
        self.stages: dict[str, StageState] = {}
        self.begun = False

    def ready(self, topics: Iterable[str] = ()) -> bool:
        """Every stage heard from counts for this run, and each one that takes one of
        ``topics`` (this publisher's) is matched with a publisher of it."""
        topics = set(topics)
        return all(st.progress.run == self.run and all(
            p.publishers != 0 for t, p in st.progress.inputs.items() if t in topics)
            for st in self.stages.values())

    def readers(self, topic: str) -> int:
        """Stages counting for this run that take ``topic`` and are matched with a publisher."""
        return sum(1 for st in self.counting()
                   if st.progress.inputs.get(topic, InputProgress(publishers=0)).publishers != 0)

    def begin(self, topics: Iterable[str]) -> None:
        """This publisher is about to send its first message on ``topics``."""
        for topic in topics:
            self.sent[topic] = 0
        self.begun = True

    def note_sent(self, topic: str, n: int) -> None:
        """This publisher has sent ``n`` messages on ``topic`` in all."""
        self.sent[topic] = int(n)

    def note_progress(self, progress: StageProgress) -> None:
        now = self.clock()
        old = self.stages.get(progress.stage)
        if old is None:
            self.stages[progress.stage] = StageState(progress, now, late=self.begun, heard_at=now)
            return
        old.heard_at = now
        if old.progress != progress:  # a heartbeat without news is no progress
            old.progress, old.progressed_at = progress, now

    def counting(self) -> list[StageState]:
        """The stages that count for this run."""
        return [st for st in self.stages.values() if st.progress.run == self.run]

    def _upstream(self, topic: str, run: bool) -> int | None:
        """Messages published on ``topic`` by this publisher and the stages (in all, or in
        this run), or None when no one we know of publishes it."""
        counts = [self.sent[topic]] if topic in self.sent else []
        for st in self.counting():
            table = st.progress.published_run if run else st.progress.published
            if topic in table:
                counts.append(table[topic])
        return sum(counts) if counts else None

    def backlog(self, st: StageState, _hops: int = 0) -> int:
        """Messages still to reach the stage, largest over its inputs: those published to it
        that it has not taken yet (by sequence numbers: a stage that took none of this
        publisher's yet is behind by all it sent), plus, for an input another stage publishes,
        that stage's own backlog (they will come too)."""
        worst = 0
        for topic, p in st.progress.inputs.items():
            upstream = self._upstream(topic, run=False)
            if upstream is None:
                continue
            last = p.last if topic not in self.sent or p.received or p.lost else 0
            behind = upstream - last
            if topic not in self.sent and _hops < 8:
                behind += max((self.backlog(q, _hops + 1) for q in self.counting()
                               if topic in q.progress.published), default=0)
            worst = max(worst, behind)
        return worst

    def window_for(self, st: StageState) -> int:
        """Messages the stage may have to take: ``window``, at most half its queue depth."""
        return self.window if not st.progress.depth else min(self.window, st.progress.depth // 2)

    def batch(self, largest: int = 64) -> int:
        """Messages to send at a time: at most half the smallest window."""
        windows = [self.window_for(st) for st in self.counting()] or [self.window]
        return max(1, min(largest, min(windows) // 2))

    def waiting_for(self, batch: int = 0) -> list[str]:
        """Stages that would be more than their window behind after ``batch`` more messages
        (those that took nothing for ``timeout_s`` are given up)."""
        now = self.clock()
        behind = []
        for st in self.counting():
            if st.stalled or self.backlog(st) <= max(0, self.window_for(st) - batch):
                continue
            if now - st.progressed_at > self.timeout_s:
                st.stalled = True
                continue
            behind.append(st.progress.stage)
        return behind

    def drained(self, quiet_s: float = 2.0) -> bool:
        """Every stage has taken everything published to it and said so twice (an unchanged
        report: it is idle, so what it published is final too — a report taken between its
        last input and its last output would make the summary's counts disagree); or it lacks
        some but, idle, kept reporting no progress for ``quiet_s`` (they were lost after its
        last message: the summary counts them as missing); or it has said nothing for
        ``timeout_s`` (a busy stage may not report for a while: it is waited for)."""
        now = self.clock()
        return all(st.stalled or (self.backlog(st) <= 0 and st.heard_at > st.progressed_at)
                   or st.heard_at - st.progressed_at > quiet_s
                   or now - st.heard_at > self.timeout_s for st in self.counting())

    def summary(self) -> list[dict[str, object]]:
        """Per stage and input topic, in this run: published upstream, received, lost
        (sequence jumps), and missing (published but neither received nor seen lost: after the
        stage's last message, or still on the way when it stopped taking them). received +
        lost + missing = published."""
        out: list[dict[str, object]] = []
        for st in sorted(self.counting(), key=lambda s: s.progress.stage):
            for topic, p in sorted(st.progress.inputs.items()):
                upstream = self._upstream(topic, run=True)
                if upstream is None and not p.received:
                    continue  # no one publishes it
                missing = max(0, upstream - p.received - p.lost) if upstream is not None else 0
                out.append({'stage': st.progress.stage, 'topic': topic, 'published': upstream,
                            'received': p.received, 'lost': p.lost, 'missing': missing,
                            'stalled': st.stalled, 'late': st.late})
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
            if r.get('late'):
                text += ' (heard from only after the replay began: counted from then)'
            parts.append(text)
        return '; '.join(parts)
