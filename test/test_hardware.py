"""Hardware layer: the terminal protocol, the simulated terminal behind the real pyusb API, the driver.

Everything goes through ``usb.core.find(..., backend=SimUsbBackend(...))`` and pyusb's own
``Device`` objects, so the driver code under test is the code that runs on a real terminal.
Known truth comes from :class:`SyntheticSource`, whose counts are a function of the sample index.
"""

from __future__ import annotations

import ast
import errno
import threading
import time
import zlib
from pathlib import Path

import numpy as np
import pytest
import usb.control
import usb.core
import usb.util
from hypothesis import given, settings
from hypothesis import strategies as st

from mmd_ros.hardware import (
    PRODUCT_ID, VENDOR_ID, AmbiguousTerminalError, CommandError, FrameStream, SampleBatch,
    SimTerminal, SimUsbBackend, SyntheticSource, TerminalBusyError, TerminalClosedError,
    TerminalDisconnectedError, TerminalDriver, TerminalNotFoundError, TerminalTimeoutError,
    Transport, decode_frames, encode_frames,
)
from mmd_ros.hardware.protocol import (
    EP_COMMAND_OUT, EP_REPLY_IN, EP_SAMPLES_IN, FLAG_COUNTER_RESET, FLAG_FIFO_OVERFLOW, FRAME_DTYPE,
    FRAME_SIZE, Opcode, Status, decode_info, decode_reply, encode_command, wrap_counts,
)

ROOT = Path(__file__).resolve().parents[1]
TWO31 = 1 << 31


def fast_terminal(**kw) -> SimTerminal:
    """A terminal that produces as fast as the host reads (no wall-clock pacing)."""
    kw.setdefault('paced', False)
    kw.setdefault('power_on_reset', False)
    return SimTerminal(**kw)


def read_n(drv: TerminalDriver, n: int, timeout: float = 2.0) -> list[SampleBatch]:
    out, got = [], 0
    while got < n:
        b = drv.read_batch(timeout)
        out.append(b)
        got += b.n
    return out


def cat(batches: list[SampleBatch], field: str) -> np.ndarray:
    return np.concatenate([getattr(b, field) for b in batches])


# ------------------------------------------------------------------ protocol
frame_fields = st.integers(1, 40).flatmap(lambda n: st.tuples(
    st.lists(st.integers(0, 2**32 - 1), min_size=n, max_size=n),
    st.lists(st.integers(0, 2**64 - 1), min_size=n, max_size=n),
    st.lists(st.lists(st.integers(-2**62, 2**62), min_size=8, max_size=8), min_size=n, max_size=n),
    st.lists(st.integers(0, 0xFFFF), min_size=n, max_size=n),
    st.lists(st.integers(0, 3), min_size=n, max_size=n),
))


@settings(max_examples=150, deadline=None)
@given(frame_fields)
def test_encode_decode_round_trip(fields):
    seq, t_ns, counts, status, flags = fields
    t_arr = np.array(t_ns, dtype=np.uint64)
    data = encode_frames(seq, t_arr, counts, channel_status=status, flags=flags)
    assert len(data) == FRAME_SIZE * len(seq)
    fr = decode_frames(data)
    assert fr.valid.all() and fr.trailing_bytes == 0
    np.testing.assert_array_equal(fr.seq, np.array(seq, np.uint32))
    np.testing.assert_array_equal(fr.time_ns.view(np.uint64), t_arr)
    np.testing.assert_array_equal(fr.counts, wrap_counts(counts))
    # counters wrap at 2^31: the difference to the truth is a multiple of 2^32
    assert np.all((np.array(counts, dtype=object) - fr.counts.astype(object)) % 2**32 == 0)
    np.testing.assert_array_equal(fr.channel_status, status)
    np.testing.assert_array_equal(fr.flags, flags)
    # the CRC is zlib's CRC-32 of bytes 0-59, little-endian in bytes 60-63
    for i in range(len(seq)):
        frame = data[i * 64:(i + 1) * 64]
        assert zlib.crc32(frame[:60]) == int.from_bytes(frame[60:], 'little')


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 63), st.integers(1, 255), st.integers(1, 8))
def test_any_damaged_byte_invalidates_only_its_frame(pos, mask, n):
    data = bytearray(encode_frames(np.arange(n), np.arange(n) * 1000, np.ones((n, 8), np.int64)))
    hit = n // 2
    data[hit * 64 + pos] ^= mask
    fr = decode_frames(bytes(data))
    assert fr.valid.tolist() == [i != hit for i in range(n)]


def test_frame_layout_is_the_documented_one():
    assert FRAME_DTYPE.itemsize == 64
    data = encode_frames([0x01020304], [0x1122334455667788], [[1, -1, 2, -2, TWO31 - 1, -TWO31, 0, 7]],
                         channel_status=0x0102, flags=FLAG_COUNTER_RESET)
    assert data[:4] == b'MD\x01S'
    assert data[4:8] == bytes([4, 3, 2, 1])
    assert data[8:16] == (0x1122334455667788).to_bytes(8, 'little')
    assert data[16:20] == (1).to_bytes(4, 'little') and data[20:24] == b'\xff' * 4
    assert data[48:52] == bytes([2, 1, 1, 0])
    doc = (ROOT / 'msg_docs' / 'usb_protocol.md').read_text()
    assert f'0x{VENDOR_ID:04X}' in doc and f'0x{PRODUCT_ID:04X}' in doc and 'CRC-32' in doc


@settings(max_examples=60, deadline=None)
@given(st.data())
def test_stream_unwraps_any_walk_split_into_any_transfers(data):
    """Counts moving < 2^31 per sample, cut into transfers anywhere, unwrap to the truth."""
    n = data.draw(st.integers(2, 300))
    seed = data.draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    steps = rng.integers(-(2**30), 2**30, size=(n, 8))
    truth = np.cumsum(steps, axis=0) + rng.integers(-2**40, 2**40, size=8)
    raw = encode_frames(np.arange(n) + 2**32 - 5, np.arange(n) * 10**6, truth)  # seq wraps too
    cuts = sorted(set(data.draw(st.lists(st.integers(1, n - 1), max_size=6))))
    stream = FrameStream()
    pieces = [stream.feed(raw[a * 64:b * 64]) for a, b in zip([0] + cuts, cuts + [n])]
    got = cat(pieces, 'counts')
    np.testing.assert_array_equal(got - got[0], truth - truth[0])
    assert got[0].tolist() == wrap_counts(truth[0]).tolist()
    assert stream.stats.gaps == 0 and stream.stats.frames_ok == n


def test_stream_skips_duplicates_and_counts_gaps():
    counts = np.arange(10)[:, None] * np.ones(8, np.int64)
    f = [encode_frames([i], [i], counts[i:i + 1]) for i in range(10)]
    stream = FrameStream()
    b = stream.feed(f[0] + f[1] + f[1] + f[4] + f[3] + f[5])
    assert b.seq.tolist() == [0, 1, 4, 5]
    assert b.missing_before.tolist() == [0, 0, 2, 0]
    assert b.counts[:, 0].tolist() == [0, 1, 4, 5]
    assert stream.stats.sequence_errors == 2 and stream.stats.missing_samples == 2


def test_stream_reset_and_duplicate_rules_across_transfers():
    def frames(seqs, counts=None, flag=0):
        c = np.array(seqs if counts is None else counts, np.int64)[:, None] * np.ones(8, np.int64)
        return encode_frames(seqs, np.arange(len(seqs)), c, flags=flag)

    s = FrameStream()
    assert not s.feed(frames([0, 1, 2, 3])).counter_reset
    b = s.feed(frames([2, 3, 4]))  # duplicates from an earlier transfer
    assert b.seq.tolist() == [4] and s.stats.sequence_errors == 2
    b = s.feed(frames([10, 11], [100, 101], FLAG_COUNTER_RESET))  # flag rises: a reset
    assert b.counter_reset and b.reset_index == 0 and b.counts[:, 0].tolist() == [100, 101]
    assert b.missing_before.tolist() == [0, 0]  # nothing is known to be missing across a reset
    b = s.feed(frames([12, 13], [102, 103], FLAG_COUNTER_RESET))  # sticky flag: same reset
    assert not b.counter_reset and not b.gap and b.counts[:, 0].tolist() == [102, 103]
    b = s.feed(frames([0, 1], [7, 8], FLAG_COUNTER_RESET))  # reset again before the host acked
    assert b.counter_reset and b.counts[:, 0].tolist() == [7, 8]
    assert not s.feed(frames([2, 3], [9, 10])).counter_reset  # acked: flag clear
    b = s.feed(frames([4, 5], [0, 1], FLAG_COUNTER_RESET))  # flag rises with seq advancing
    assert b.counter_reset and s.stats.resets == 3


@pytest.mark.parametrize('seed', range(8))
def test_compiled_decoding_gives_what_numpy_gives(seed):
    """FrameStream's compiled path (continuing transfers, the 1 kHz case) against its numpy
    path, batch for batch and counter for counter, on a stream with every fault: counter and
    sequence wrap, gaps, duplicates, bad CRCs, trailing bytes, resets, status bits, overflows."""
    from mmd_ros.core.compiled import AVAILABLE, NOT_IN_USE
    assert AVAILABLE, NOT_IN_USE
    rng = np.random.default_rng(seed)
    n = 4000
    counts = np.cumsum(rng.integers(-(2**29), 2**29, (n, 8)), axis=0)
    counts += rng.integers(-2**40, 2**40, 8)
    seqs = (np.arange(n) + 2**32 - 900) % 2**32
    flags = np.zeros(n, np.int64)
    flags[1500:1530] = FLAG_COUNTER_RESET                    # a reset, flag held for 30 frames
    flags[rng.integers(0, n, 20)] |= FLAG_FIFO_OVERFLOW
    status = np.where(rng.random(n) < 0.01, rng.integers(1, 2**16, n), 0)
    frames = bytearray(encode_frames(seqs, np.arange(n) * 10**6, counts, status, flags))
    order = np.arange(n)
    order = np.delete(order, rng.integers(0, n, 40))       # gaps
    dup = rng.integers(1, len(order), 10)
    order = np.insert(order, dup, order[dup - 1])           # duplicates
    for bad in rng.integers(0, n, 10):                      # damaged frames
        frames[bad * 64 + int(rng.integers(0, 60))] ^= 0xFF
    payload = b''.join(bytes(frames[i * 64:(i + 1) * 64]) for i in order)
    cuts = np.sort(rng.choice(np.arange(1, len(order)), 600, replace=False)) * 64
    transfers = [payload[a:b] for a, b in zip(np.r_[0, cuts], np.r_[cuts, len(payload)])]
    transfers[300] += b'\x01\x02'                          # trailing bytes
    streams = [FrameStream(compiled=False), FrameStream(compiled=True)]
    took = []  # what the compiled path returned for each transfer (None: the numpy path)
    compiled_path = streams[1]._continue_compiled
    streams[1]._continue_compiled = lambda raw, t: took.append(compiled_path(raw, t)) or took[-1]
    for data in transfers:
        a, b = (s.feed(data, 7) for s in streams)
        for f in ('seq', 'device_time_ns', 'counts', 'channel_status', 'flags', 'missing_before'):
            x, y = getattr(a, f), getattr(b, f)
            assert x.dtype == y.dtype and np.array_equal(x, y), f
        for f in ('counter_reset', 'reset_index', 'crc_errors'):
            assert getattr(a, f) == getattr(b, f), f
        assert a.raw == b.raw
    assert streams[0].stats == streams[1].stats
    st_ = streams[1].stats
    assert st_.resets >= 1 and st_.gaps > 0 and st_.crc_errors > 0 and st_.sequence_errors > 0
    assert st_.overflows > 0 and st_.signal_errors > 0 and st_.framing_errors == 1
    assert 300 < sum(t is not None for t in took) < len(transfers) - 20


# ------------------------------------------------------------------ the simulated device through pyusb
def test_found_by_vendor_product_and_serial():
    backend = SimUsbBackend([fast_terminal(serial='MMD-A-0001', port=1),
                             fast_terminal(serial='MMD-B-0002', port=2)])
    devs = list(usb.core.find(find_all=True, idVendor=VENDOR_ID, idProduct=PRODUCT_ID, backend=backend))
    assert len(devs) == 2
    dev = usb.core.find(idVendor=VENDOR_ID, idProduct=PRODUCT_ID, serial_number='MMD-B-0002',
                        backend=backend)
    assert dev is not None and dev.serial_number == 'MMD-B-0002' and dev.port_number == 2
    assert usb.core.find(idVendor=VENDOR_ID, idProduct=PRODUCT_ID, serial_number='nope',
                         backend=backend) is None
    assert usb.core.find(idVendor=VENDOR_ID, idProduct=PRODUCT_ID + 1, backend=backend) is None
    with pytest.raises(AmbiguousTerminalError, match='serial'):
        TerminalDriver(backend=backend).open()
    with TerminalDriver('MMD-B-0002', backend=backend) as drv:
        assert drv.info.serial == 'MMD-B-0002'
    with pytest.raises(TerminalNotFoundError, match='nope'):
        TerminalDriver('nope', backend=backend).open()


def test_descriptors_are_sane():
    backend = SimUsbBackend(fast_terminal())
    dev = usb.core.find(idVendor=VENDOR_ID, idProduct=PRODUCT_ID, backend=backend)
    assert (dev.bLength, dev.bDescriptorType, dev.bcdUSB, dev.bNumConfigurations) == (18, 1, 0x0200, 1)
    assert (dev.manufacturer, dev.product, dev.serial_number) == ('MMD Lab', 'MMD-ET8', 'MMD-SIM-0001')
    assert dev.speed == usb.util.SPEED_HIGH
    cfgs = list(dev)  # pyusb iterates until IndexError: must end
    assert len(cfgs) == 1
    intfs = list(cfgs[0])
    assert len(intfs) == 1 and intfs[0].bInterfaceClass == 0xFF and intfs[0].bNumEndpoints == 3
    eps = {e.bEndpointAddress: e for e in intfs[0]}
    assert set(eps) == {EP_SAMPLES_IN, EP_COMMAND_OUT, EP_REPLY_IN}
    assert all(usb.util.endpoint_type(e.bmAttributes) == usb.util.ENDPOINT_TYPE_BULK for e in eps.values())
    assert all(e.wMaxPacketSize == 512 for e in eps.values())
    assert usb.util.endpoint_direction(EP_SAMPLES_IN) == usb.util.ENDPOINT_IN
    assert cfgs[0].wTotalLength == 9 + 9 + 3 * 7 and cfgs[0].bmAttributes & 0x40  # self-powered
    raw = usb.control.get_descriptor(dev, 18, usb.util.DESC_TYPE_DEVICE, 0)
    assert len(raw) == 18 and int.from_bytes(bytes(raw[8:10]), 'little') == VENDOR_ID
    raw_cfg = usb.control.get_descriptor(dev, 64, usb.util.DESC_TYPE_CONFIG, 0)
    assert len(raw_cfg) == 39 and raw_cfg[1] == 2
    with pytest.raises(usb.core.USBError):  # an unknown request stalls
        dev.ctrl_transfer(0xC0, 0x42, 0, 0, 4)
    usb.util.dispose_resources(dev)


def test_info_read_raw_and_through_the_driver():
    backend = SimUsbBackend(fast_terminal(serial='MMD-0042'))
    dev = usb.core.find(idVendor=VENDOR_ID, idProduct=PRODUCT_ID, backend=backend)
    dev.set_configuration()
    dev.write(EP_COMMAND_OUT, encode_command(Opcode.GET_INFO, tag=77))
    reply = decode_reply(bytes(dev.read(EP_REPLY_IN, 128, 1000)))
    assert (reply.opcode, reply.tag, reply.status) == (Opcode.GET_INFO, 77, Status.OK)
    info = decode_info(reply.payload)
    assert (info.serial, info.n_channels, info.counter_bits, info.sample_rate_hz) == ('MMD-0042', 8, 32, 1000)
    dev.write(EP_COMMAND_OUT, encode_command(Opcode.GET_INFO, tag=78)[:-1] + b'\0')  # bad CRC
    assert decode_reply(bytes(dev.read(EP_REPLY_IN, 128, 1000))).status == Status.BAD_COMMAND
    usb.util.dispose_resources(dev)
    with TerminalDriver(backend=backend) as drv:
        assert drv.info == info
        assert isinstance(drv, Transport)
        assert 'bus 1' in drv.usb_location


def test_stream_equals_source_across_the_2_31_wrap():
    source = SyntheticSource(drift_counts_per_sample=(400, -400, 300, -300, 7, -7, 0, 1))
    term = fast_terminal(source=source)
    preset = np.array([TWO31 - 1000, -TWO31 + 1000, TWO31 - 5, -TWO31 + 5, 0, 0, TWO31 - 1, -TWO31])
    term.preset_counters(preset)
    n = 6000
    with TerminalDriver(backend=SimUsbBackend(term)) as drv:
        batches = read_n(drv, n)
    got = cat(batches, 'counts')[:n]
    truth = source.counts_at(np.arange(n))
    expected = truth - truth[0] + preset
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(cat(batches, 'seq')[:n], np.arange(n))
    assert expected[:, 0].max() > TWO31 + 2_000_000 and expected[:, 1].min() < -TWO31 - 2_000_000
    np.testing.assert_array_equal(cat(batches, 'device_time_ns')[:n], source.time_at(np.arange(n)))
    assert drv.stats.crc_errors == 0 and drv.stats.gaps == 0 and drv.stats.frames_ok >= n


def test_crc_corruption_is_counted_and_the_frame_dropped():
    term = fast_terminal(record=True)
    with TerminalDriver(backend=SimUsbBackend(term), max_transfer_frames=32) as drv:
        first = drv.read_batch()
        term.corrupt_frames(3, byte_offset=20)  # inside channel 1's count
        bad = drv.read_batch()
        rest = read_n(drv, 100)
        stats = drv.stats
    assert bad.crc_errors == 3 and bad.n == 32 - 3
    assert stats.crc_errors == 3 and stats.gaps == 1 and stats.missing_samples == 3
    assert bad.gap and bad.missing_before[0] == 3
    seq = np.concatenate([first.seq, bad.seq, cat(rest, 'seq')])
    assert not np.isin([32, 33, 34], seq).any()  # the damaged frames never became data
    truth = term.source.counts_at(seq.astype(np.int64))
    np.testing.assert_array_equal(np.concatenate([first.counts, bad.counts, cat(rest, 'counts')]), truth)


def test_dropped_frames_are_a_gap_of_exactly_that_many_samples():
    term = fast_terminal()
    with TerminalDriver(backend=SimUsbBackend(term), max_transfer_frames=50) as drv:
        drv.read_batch()
        term.drop_frames(7)
        b = drv.read_batch()
        stats = drv.stats
    assert b.gap and b.missing == 7 and b.missing_before.tolist() == [7] + [0] * (b.n - 1)
    assert b.seq[0] == 50 + 7
    assert stats.gaps == 1 and stats.missing_samples == 7 and stats.crc_errors == 0
    np.testing.assert_array_equal(b.counts, term.source.counts_at(b.seq.astype(np.int64)))


def test_counter_reset_is_flagged_and_unwrapping_restarts():
    term = fast_terminal()
    src = term.source
    with TerminalDriver(backend=SimUsbBackend(term), max_transfer_frames=40) as drv:
        before = drv.read_batch()
        assert drv.reference_valid and not before.counter_reset
        term.reset_counters()
        b = drv.read_batch()
        assert b.counter_reset and b.reset_index == 0 and b.seq[0] == 0
        assert (b.flags[0] & FLAG_COUNTER_RESET) and b.missing_before[0] == 0
        assert not drv.reference_valid  # calibration invalid until re-referenced
        # counters restarted from 0 at the reset sample (source index 40)
        k = 40 + np.arange(b.n)
        np.testing.assert_array_equal(b.counts, src.counts_at(k) - src.counts_at([40]))
        assert b.device_time_ns[0] == 0
        assert not term.reset_flag  # the driver acknowledged it (CLEAR_RESET_FLAG)
        after = drv.read_batch()
        assert not after.counter_reset and not (after.flags & FLAG_COUNTER_RESET).any()
        np.testing.assert_array_equal(after.counts, src.counts_at(80 + np.arange(40)) - src.counts_at([40]))
        drv.mark_referenced()
        assert drv.reference_valid and drv.stats.resets == 1 and drv.stats.gaps == 0


def test_reset_in_the_middle_of_a_transfer_and_power_on_flag():
    term = SimTerminal(paced=False)  # power-on: frames carry COUNTER_RESET until acknowledged
    with TerminalDriver(backend=SimUsbBackend(term), max_transfer_frames=64) as drv:
        first = drv.read_batch()
        assert first.counter_reset and first.reset_index == 0 and not drv.reference_valid
        drv.mark_referenced()
        stream = FrameStream()  # mid-transfer: old epoch then new epoch in one feed
        old = encode_frames([10, 11], [0, 1], [[5] * 8, [6] * 8])
        new = encode_frames([0, 1], [0, 1], [[0] * 8, [1] * 8], flags=FLAG_COUNTER_RESET)
        b = stream.feed(old + new)
        assert b.counter_reset and b.reset_index == 2 and b.counts[:, 0].tolist() == [5, 6, 0, 1]
        assert stream.stats.resets == 1 and stream.stats.sequence_errors == 0


def test_cable_pulled_mid_stream_reconnects_and_keeps_every_delivered_frame():
    term = SimTerminal(paced=True, power_on_reset=False, record=True)  # real time, 1 kHz
    backend = SimUsbBackend(term)
    batches: list[SampleBatch] = []
    events: list[str] = []
    with TerminalDriver(backend=backend, read_timeout_s=0.5) as drv:
        t_end = time.monotonic() + 0.3
        while time.monotonic() < t_end:
            batches.append(drv.read_batch())
        # pull the cable while read_batch is blocked waiting for the next transfer
        threading.Timer(0.003, term.unplug).start()
        with pytest.raises(TerminalDisconnectedError, match='left the bus'):
            while True:
                batches.append(drv.read_batch())
        events.append('disconnected')
        assert usb.core.find(idVendor=VENDOR_ID, idProduct=PRODUCT_ID, backend=backend) is None
        assert isinstance(drv.last_error, usb.core.USBError) and drv.last_error.errno == errno.ENODEV
        with pytest.raises(TerminalDisconnectedError, match='off the bus'):
            drv.read_batch(timeout=0.1)  # still away: reported, retried with backoff
        threading.Timer(0.1, term.plug).start()
        while True:
            try:
                b = drv.read_batch(timeout=0.5)
            except TerminalDisconnectedError:
                continue
            if b.reconnected:
                events.append('reconnected')
                break
        t_end = time.monotonic() + 0.3
        while time.monotonic() < t_end:
            batches.append(drv.read_batch())
        stats = drv.stats
    assert events == ['disconnected', 'reconnected']
    assert stats.disconnects == 1 and stats.reconnects == 1
    seq = cat(batches, 'seq').astype(np.int64)
    # every frame the terminal put on the wire reached the caller, in order, once
    np.testing.assert_array_equal(seq, term.delivered_seqs)
    assert len(seq) > 400
    # the samples taken while the cable was out are one gap, counted exactly
    jumps = np.flatnonzero(np.diff(seq) != 1)
    assert len(jumps) == 1
    missing = int(seq[jumps[0] + 1] - seq[jumps[0]] - 1)
    assert missing > 50 and stats.missing_samples == missing and stats.gaps == 1
    assert cat(batches, 'missing_before').sum() == missing
    # counts stay unwrapped and true across the disconnect (sample index == sequence number)
    np.testing.assert_array_equal(cat(batches, 'counts'), term.source.counts_at(seq))
    assert stats.crc_errors == 0 and stats.resets == 0


def test_explicit_reconnect_without_auto_mode():
    term = fast_terminal()
    with TerminalDriver(backend=SimUsbBackend(term), auto_reconnect=False) as drv:
        drv.read_batch()
        term.unplug()
        with pytest.raises(TerminalDisconnectedError):
            drv.read_batch()
        with pytest.raises(TerminalDisconnectedError, match='reconnect'):
            drv.read_batch()
        with pytest.raises(TerminalDisconnectedError):
            drv.reconnect(timeout=0.1)
        term.plug()
        info = drv.reconnect(timeout=2.0)
        assert info.serial == term.serial and drv.connected
        b = drv.read_batch()
        assert b.n > 0 and not b.gap  # fast mode: the terminal took no samples meanwhile


def test_raw_pyusb_sees_unplug_and_stall_like_libusb():
    term = fast_terminal()
    backend = SimUsbBackend(term)
    dev = usb.core.find(idVendor=VENDOR_ID, idProduct=PRODUCT_ID, backend=backend)
    dev.set_configuration()
    dev.write(EP_COMMAND_OUT, encode_command(Opcode.START_STREAM, 1))
    assert len(dev.read(EP_SAMPLES_IN, 64 * 4, 100)) == 256
    term.stall()
    t0 = time.monotonic()
    with pytest.raises(usb.core.USBTimeoutError):
        dev.read(EP_SAMPLES_IN, 64 * 4, 100)
    assert 0.09 <= time.monotonic() - t0 < 1.0
    term.resume()
    term.unplug()
    with pytest.raises(usb.core.USBError) as err:
        dev.read(EP_SAMPLES_IN, 64 * 4, 100)
    assert err.value.errno == errno.ENODEV == 19 and err.value.backend_error_code == -4
    assert not isinstance(err.value, usb.core.USBTimeoutError)
    address = dev.address
    usb.util.dispose_resources(dev)
    assert usb.core.find(idVendor=VENDOR_ID, backend=backend) is None
    term.plug()
    again = usb.core.find(idVendor=VENDOR_ID, idProduct=PRODUCT_ID, backend=backend)
    assert again is not None and again.address != address


def test_stall_times_out_then_overflow_is_reported():
    term = SimTerminal(paced=True, power_on_reset=False, fifo_frames=64)
    with TerminalDriver(backend=SimUsbBackend(term)) as drv:
        read_n(drv, 50)
        term.stall()
        t0 = time.monotonic()
        with pytest.raises(TerminalTimeoutError, match='stalled'):
            drv.read_batch(timeout=0.25)
        assert 0.2 <= time.monotonic() - t0 < 1.0
        assert drv.stats.timeouts == 1 and drv.connected
        term.resume()
        got = read_n(drv, 200)
        stats = drv.stats
    flagged = [b for b in got if b.overflow]
    assert flagged and flagged[0].gap  # the FIFO filled during the stall: samples discarded
    assert stats.overflows == 1 and stats.missing_samples == term.frames_lost_to_overflow > 100


def test_commands_refused_with_a_reason():
    term = fast_terminal()
    with TerminalDriver(backend=SimUsbBackend(term)) as drv:
        with pytest.raises(CommandError, match='BUSY.*stop streaming'):
            drv._command(Opcode.SET_SAMPLE_RATE, 500)
        with pytest.raises(CommandError, match='BAD_ARGUMENT'):
            drv._command(Opcode.SET_FRAMES_PER_TRANSFER, 1000)
        info = drv.set_sample_rate(500)
        assert info.sample_rate_hz == 500 and term.sample_rate_hz == 500
        b = drv.read_batch()
        assert np.all(np.diff(b.device_time_ns) == 2_000_000)  # 500 Hz
    with TerminalDriver(backend=SimUsbBackend(fast_terminal()), sample_rate_hz=250,
                        frames_per_transfer=16) as drv:
        assert drv.info.sample_rate_hz == 250 and drv.info.frames_per_transfer == 16


def test_driver_errors_say_what_to_do():
    term = fast_terminal()
    backend = SimUsbBackend(term)
    drv = TerminalDriver(backend=backend)
    with pytest.raises(TerminalClosedError, match='open'):
        drv.read_batch()
    with drv:
        with pytest.raises(TerminalBusyError, match='another process'):
            TerminalDriver(backend=backend).open()
        term.set_signal_lost(3)
        term.set_quadrature_error(5)
        b = drv.read_batch()
        assert b.signal_lost[:, 3].all() and not b.signal_lost[:, 2].any()
        assert b.quadrature_error[:, 5].all() and drv.stats.signal_errors == b.n
    drv.close()  # twice is fine
    term.unplug()
    with pytest.raises(TerminalNotFoundError, match='cable'):
        TerminalDriver(backend=backend).open()


def test_replaying_raw_transfers_gives_the_same_batches():
    term = fast_terminal()
    with TerminalDriver(backend=SimUsbBackend(term), max_transfer_frames=20) as drv:
        live = [drv.read_batch()]
        term.drop_frames(4)
        term.corrupt_frames(1)
        live += read_n(drv, 200)
        live_stats = drv.stats
    replay = FrameStream()
    again = [replay.feed(b.raw, b.host_time_ns) for b in live]
    for a, b in zip(live, again):
        np.testing.assert_array_equal(a.counts, b.counts)
        np.testing.assert_array_equal(a.missing_before, b.missing_before)
    assert (replay.stats.crc_errors, replay.stats.missing_samples) == (live_stats.crc_errors,
                                                                       live_stats.missing_samples) == (1, 5)


def test_no_ros_imports_in_the_hardware_layer():
    for path in (ROOT / 'mmd_ros' / 'hardware').glob('*.py'):
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ''] if isinstance(node, ast.ImportFrom) else [])
            assert not any(n.split('.')[0] in ('rclpy', 'rosidl_runtime_py') or n.endswith('_msgs')
                           for n in names), (path.name, names)
