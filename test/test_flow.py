"""Counting losses from publisher sequence numbers and pacing a replay by its stages (ROS-free)."""

from __future__ import annotations

import numpy as np

from mmd_ros.core.flow import FlowControl, InputProgress, SequenceCounter, StageProgress, StampPairing

RAW, LEN = '/mmd/raw_counts', '/mmd/bar_lengths'


def test_sequence_counter_counts_every_jump_and_starts_over_with_a_new_publisher():
    rng = np.random.default_rng(1)
    c = SequenceCounter()
    sent = np.arange(1, 5001)
    kept = sent[rng.random(sent.size) > 0.1]  # 10 % dropped, the first and last kept
    kept = np.unique(np.r_[1, kept, 5000])
    lost = [c.note(int(s)) for s in kept]
    assert c.received == kept.size and c.received + c.lost == 5000
    assert sum(lost) == c.lost and c.gaps == int(np.count_nonzero(np.diff(kept) > 1))
    # a run begins; the publisher restarts: numbers from 1 again, nothing lost across it
    c.mark()
    assert c.note(1) == 0 and c.sessions == 2 and c.last == 1
    assert c.note(3) == 1 and (c.run_received, c.run_lost) == (2, 1)
    assert c.lost == 5000 - kept.size + 1
    # several publishers interleave: jumps no longer count
    c.ambiguous = True
    assert c.note(10) == 0 and c.lost == 5000 - kept.size + 1
    # a middleware without sequence numbers: received only
    d = SequenceCounter()
    d.note(None)
    assert not d.supported and d.received == 1 and d.lost == 0


def test_stage_progress_round_trips_through_key_values():
    p = StageProgress('/mmd/fk_node', {LEN: InputProgress(900, 880, 20, 1)}, {'/mmd/pose': 870},
                      depth=1000, run='/mmd/replay_node 17', published_run={'/mmd/pose': 400})
    pairs = p.to_pairs() + [('noise', 'x'), ('/mmd/pose what', '1')]
    assert StageProgress.from_pairs('/mmd/fk_node', pairs) == p


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


RUN = '/mmd/replay_node 1'


def progress(stage, inputs, published=None, depth=0, run=RUN, published_run=None):
    return StageProgress(stage, inputs, published or {}, depth, run, published_run or {})


def test_flow_control_paces_by_the_slowest_stage_and_accounts_for_every_message_of_the_run():
    clock = Clock()
    flow = FlowControl(RUN, window=100, timeout_s=5.0, clock=clock)
    comp, fk, rec = '/mmd/compensation_node', '/mmd/fk_node', '/mmd/recorder_node'
    # before the replay: the stages heard an earlier publisher and have not marked this run yet
    flow.note_progress(progress(comp, {RAW: InputProgress(7000, 6990, 10)}, {LEN: 6990}, 1000, run=''))
    flow.note_progress(progress(fk, {LEN: InputProgress(6990, 6990, 0)}, depth=60, run=''))
    assert not flow.ready()
    # compensation has marked the run but its subscription has not matched our publisher yet
    flow.note_progress(progress(comp, {RAW: InputProgress(7000, 0, 0, 0)}, {LEN: 6990}, 1000,
                                published_run={LEN: 0}))
    flow.note_progress(progress(fk, {LEN: InputProgress(6990, 0, 0)}, depth=60))
    assert flow.ready() and not flow.ready([RAW]) and flow.readers(RAW) == 0
    flow.note_progress(progress(comp, {RAW: InputProgress(7000, 0, 0, 1)}, {LEN: 6990}, 1000,
                                published_run={LEN: 0}))
    assert flow.ready([RAW]) and flow.readers(RAW) == 1
    flow.begin([RAW])
    assert flow.batch(64) == 15  # half of fk's window (half its depth of 60)
    # nothing of ours taken yet: the earlier publisher's 7000 are no progress
    flow.note_sent(RAW, 20)
    assert flow.waiting_for(0) == []
    assert flow.waiting_for(15) == [fk]  # what compensation has yet to take will reach fk too
    flow.note_sent(RAW, 150)
    assert set(flow.waiting_for()) == {comp, fk}
    # compensation takes 140 of ours, 5 lost; it published 135 lengths, fk took 100
    flow.note_progress(progress(comp, {RAW: InputProgress(145, 140, 5)}, {LEN: 6990 + 135}, 1000,
                                published_run={LEN: 135}))
    flow.note_progress(progress(fk, {LEN: InputProgress(6990 + 100, 100, 0)}, depth=60))
    assert flow.waiting_for() == [fk]  # 35 behind, 5 more to come through compensation; window 30
    # a recorder heard only now: it counts for the run
    flow.note_progress(progress(rec, {RAW: InputProgress(150, 150, 0)}))
    flow.note_progress(progress(fk, {LEN: InputProgress(6990 + 135, 133, 2)}, depth=60))
    assert flow.waiting_for() == [] and not flow.drained()  # comp still has 5 to take
    comp_now = progress(comp, {RAW: InputProgress(150, 145, 5)}, {LEN: 6990 + 140}, 1000,
                        published_run={LEN: 140})
    flow.note_progress(comp_now)
    assert not flow.drained()  # fk: 5 more lengths
    # fk takes nothing more: silent (busy) it is waited for; repeating the same report (idle)
    # quiet_s after its last progress, the rest counts as lost at the end of the stream
    fk_now = progress(fk, {LEN: InputProgress(6990 + 135, 133, 2)}, depth=60)
    clock.t = 4.0  # nothing heard from fk since t = 0: busy, waited for (up to timeout_s)
    assert not flow.drained(quiet_s=2.0)
    flow.note_progress(fk_now)  # idle and no further: the rest is lost
    # compensation and the recorder took everything, but each said so once only: a report
    # taken between a stage's last input and its last output would understate what it
    # published, so the end waits for an unchanged one
    assert not flow.drained(quiet_s=2.0)
    flow.note_progress(comp_now)
    assert not flow.drained(quiet_s=2.0)
    flow.note_progress(progress(rec, {RAW: InputProgress(150, 150, 0)}))
    assert flow.drained(quiet_s=2.0)
    rows = {(r['stage'], r['topic']): r for r in flow.summary()}
    c, f, r = rows[(comp, RAW)], rows[(fk, LEN)], rows[(rec, RAW)]
    assert (c['published'], c['received'], c['lost'], c['missing']) == (150, 145, 5, 0)
    assert (f['published'], f['received'], f['lost'], f['missing']) == (140, 133, 2, 5)
    assert not f['stalled'] and not c['stalled']
    assert (r['published'], r['received'], r['lost'], r['missing']) == (150, 150, 0, 0)
    for row in rows.values():  # every message is accounted for
        assert row['received'] + row['lost'] + row['missing'] == row['published']
    text = FlowControl.describe(flow.summary())
    assert f'{fk}: {LEN} 133 of 140 received, 7 lost' in text
    assert f'{comp}: {RAW} 145 of 150 received, 5 lost' in text


def test_a_stage_that_stops_taking_while_behind_is_given_up():
    clock = Clock()
    flow = FlowControl(RUN, window=10, timeout_s=1.0, clock=clock)
    flow.note_progress(progress('/a', {RAW: InputProgress()}))
    flow.begin([RAW])
    flow.note_sent(RAW, 50)
    for t in (0.5, 0.9, 1.2):
        clock.t = t
        flow.note_progress(progress('/a', {RAW: InputProgress()}))  # the same, again
    assert flow.waiting_for() == [] and flow.stages['/a'].stalled  # a heartbeat is no progress
    assert '0 of 50 received, 50 lost (it stopped taking messages)' in FlowControl.describe(flow.summary())


def test_stamp_pairing_waits_for_a_topic_thousands_of_rows_behind_and_gives_up_only_lost_ones():
    """fk_node's lengths and thermal rows: after a busy spell one topic arrives far ahead of
    the other (a replay at full speed: 2,504 lengths before the first thermal row). Every row
    whose partner comes is paired, in stamp order; a row whose partner was lost is given up
    once the other topic has gone past its stamp; a new run gives up what waits."""
    n = 5000
    stamps = np.arange(n, dtype=np.int64) * 1_000_000
    lengths = np.column_stack([stamps * 1e-12, np.arange(n)]).astype(float)
    thermal = -lengths
    lost = {3000, 3001, 4321}                       # thermal rows lost on the way
    keep = np.array([i not in lost for i in range(n)])
    pairing = StampPairing(max_pending=20000)
    got = []
    pairing.add(0, stamps[:2504], lengths[:2504])   # a burst of lengths, no thermal yet
    assert pairing.take() is None and len(pairing) == 2504 and pairing.unpaired == 0
    for a in range(0, n, 8):                        # then the rest, in transfers of 8
        if a >= 2504:
            pairing.add(0, stamps[a:a + 8], lengths[a:a + 8])
        rows = np.arange(a, min(a + 8, n))
        rows = rows[keep[rows]]
        pairing.add(1, stamps[rows], thermal[rows])
        out = pairing.take()
        if out is not None:
            got.append(out)
    s = np.concatenate([g[0] for g in got])
    a_rows, b_rows = np.concatenate([g[1] for g in got]), np.concatenate([g[2] for g in got])
    assert np.array_equal(s, stamps[keep])          # every row that had a partner, in order
    assert np.array_equal(a_rows, lengths[keep]) and np.array_equal(b_rows, -a_rows)
    assert pairing.unpaired == len(lost) and len(pairing) == 0
    # a bound on memory when a topic stops altogether
    small = StampPairing(max_pending=100)
    small.add(0, stamps[:150], lengths[:150])
    assert small.take() is None and len(small) == 100 and small.unpaired == 50
    small.add(1, stamps[140:141], thermal[140:141])  # the thermal row of 140 pairs
    out = small.take()
    assert out is not None and out[0].tolist() == [stamps[140]]
    assert small.unpaired == 140 and len(small) == 9  # and 50..139 given up, 141..149 wait
    small.clear()
    assert len(small) == 0 and small.unpaired == 149


def test_stamp_pairing_follows_stamps_that_go_back_without_a_new_run():
    """A log played again into fk_node by another tool (no run mark): its stamps restart
    below those already seen. Rows of the new pass are still paired when their partners come
    a flush later; nothing is given up."""
    stamps = np.arange(100, dtype=np.int64) * 1_000_000 + 10**12
    rows = np.arange(100, dtype=float)[:, None]
    pairing = StampPairing(max_pending=2000)
    for _ in range(2):                      # the same stamps twice, the partner one flush behind
        got = []
        for a in range(0, 100, 8):
            pairing.add(0, stamps[a:a + 8], rows[a:a + 8])
            if a:
                pairing.add(1, stamps[a - 8:a], -rows[a - 8:a])
            out = pairing.take()
            if out is not None:
                got.append(out[0])
        pairing.add(1, stamps[96:], -rows[96:])
        got.append(pairing.take()[0])
        assert np.array_equal(np.concatenate(got), stamps)
    assert pairing.unpaired == 0 and len(pairing) == 0
