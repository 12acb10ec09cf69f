"""Crash tolerance of the bag writer and omni_bag_recover, without ROS processes.

A killed writer is simulated by copying the .mcap while the writer is still open (what a SIGKILL
leaves: the bytes handed to the kernel), or by truncating a finished file at many offsets.
"""

from __future__ import annotations

import errno
import shutil
import subprocess
import time
from pathlib import Path

import pytest
import yaml

from tissue_testing import harness
from haptic_omni_driver import recover
from haptic_omni_driver.backends.replay import load_replay
from haptic_omni_driver.bag_reader import read_bag
from haptic_omni_driver.bag_recovery import recover_bag, salvage_records
from haptic_omni_driver.bag_types import POSE_TYPE, STATE_TYPE, WRENCH_TYPE, typestore
from haptic_omni_driver.bag_writer import BagWriter, qos_profile
from haptic_omni_driver.errors import BagError, OutputError
from omni_test_utils import pose_msg, wrench_msg

T0 = 1_700_000_000_000_000_000


def pose_raw(k: int) -> bytes:
    """CDR bytes of pose k (stamp T0 + k ms, x = k mm)."""
    return bytes(typestore().serialize_cdr(pose_msg(T0 + k * 1_000_000, (k * 1e-3, 0, 0)),
                                           POSE_TYPE))


def write_pose(writer: BagWriter, k: int) -> None:
    writer.write('/omni/pose', POSE_TYPE, T0 + k * 1_000_000, pose_raw(k))


def snapshot(writer: BagWriter, dest: Path) -> Path:
    """Copy of the bag folder as a kill of the writing process would leave it now."""
    shutil.copytree(writer.path, dest)
    return dest


def pose_stamps(bag: Path) -> list[int]:
    return [stamp for _, _, stamp, _ in read_bag(bag, ['/omni/pose'], raw=True)]


def metadata(bag: Path) -> dict:
    return yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']


def assert_reads_with_rosbags_and_counts_match(bag: Path) -> dict[str, int]:
    """AnyReader reads every message; metadata.yaml counts equal what is in the .mcap."""
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as reader:
        read: dict[str, int] = {}
        for conn, _, _ in reader.messages():
            read[conn.topic] = read.get(conn.topic, 0) + 1
    meta = metadata(bag)
    listed = {t['topic_metadata']['name']: t['message_count']
              for t in meta['topics_with_message_count']}
    assert listed == read
    assert meta['message_count'] == sum(read.values()) == meta['files'][0]['message_count']
    return read


# -- what a kill leaves ---------------------------------------------------------------------------
def test_flushed_messages_survive_a_writer_that_never_closes(tmp_path):
    writer = BagWriter(tmp_path / 'live')
    for k in range(300):
        write_pose(writer, k)
    writer.flush()
    for k in range(300, 450):  # in the open chunk: not on disk yet
        write_pose(writer, k)
    killed = snapshot(writer, tmp_path / 'killed')
    writer.close()
    assert not (killed / 'metadata.yaml').exists()
    result = recover_bag(killed)
    assert result.counts == {'/omni/pose': 300} and not result.complete
    assert pose_stamps(killed) == [T0 + k * 1_000_000 for k in range(300)]
    assert_reads_with_rosbags_and_counts_match(killed)


def test_flush_period_puts_messages_on_disk_without_any_call(tmp_path):
    writer = BagWriter(tmp_path / 'live', flush_period=0.05)
    try:
        for k in range(200):
            write_pose(writer, k)
        deadline = time.monotonic() + 30
        while True:
            salvaged = sum(1 for r in salvage_records(writer.mcap_path)
                           if type(r).__name__ == 'Message')
            if salvaged == 200 or time.monotonic() > deadline:
                break
            time.sleep(0.02)
        assert salvaged == 200
    finally:
        writer.close()


def test_recovery_after_a_cut_anywhere_keeps_every_complete_chunk(tmp_path):
    """Cut the file at many offsets: every chunk written before the cut comes back, nothing else."""
    from mcap.reader import make_reader

    writer = BagWriter(tmp_path / 'full')
    for k in range(1000):
        write_pose(writer, k)
        if k % 100 == 99:
            writer.flush()  # one chunk of 100 poses
    writer.close()
    with open(writer.mcap_path, 'rb') as stream:
        chunk_ends = [c.chunk_start_offset + c.chunk_length
                      for c in make_reader(stream).get_summary().chunk_indexes]
    assert len(chunk_ends) == 10
    data = writer.mcap_path.read_bytes()
    for i, cut in enumerate([*range(chunk_ends[0] - 50, len(data), len(data) // 37),
                             *chunk_ends, chunk_ends[3] - 1]):
        bag = tmp_path / f'cut{i}'
        bag.mkdir()
        (bag / 'cut.mcap').write_bytes(data[:cut])
        expected = 100 * sum(end <= cut for end in chunk_ends)
        if expected == 0:
            with pytest.raises(BagError, match='no complete message'):
                recover_bag(bag)
            continue
        result = recover_bag(bag)
        assert result.counts == {'/omni/pose': expected}, f'cut at {cut} of {len(data)}'
        assert pose_stamps(bag) == [T0 + k * 1_000_000 for k in range(expected)]
        assert assert_reads_with_rosbags_and_counts_match(bag) == {'/omni/pose': expected}


def test_recovery_keeps_topics_types_qos_hashes_and_metadata_version(tmp_path):
    qos = [qos_profile(reliable=False, depth=7)]
    writer = BagWriter(tmp_path / 'live', version=8)
    writer.add_topic('/omni/pose', POSE_TYPE, qos)
    write_pose(writer, 0)
    writer.write('/omni/force_feedback', WRENCH_TYPE, T0 + 1, wrench_msg(T0, (0.1, 0, 0)))
    from tissue_msgs.msg import DeviceState

    writer.write('/omni/state', STATE_TYPE, T0 + 2, DeviceState(backend='replay'))
    writer.flush()
    killed = snapshot(writer, tmp_path / 'killed')
    writer.close()
    recover_bag(killed)
    got, ref = metadata(killed), metadata(writer.path)
    assert got['version'] == 8
    assert got['topics_with_message_count'] == ref['topics_with_message_count']
    assert got['starting_time'] == ref['starting_time'] and got['duration'] == ref['duration']
    assert list(read_bag(killed, raw=True)) == list(read_bag(writer.path, raw=True))


def test_unfinished_bag_of_the_previous_rosbags_writer_is_recovered(tmp_path):
    """Bags of the recorder before the chunk flushing: 1 MiB chunks, killed mid-chunk."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    rb = Writer(tmp_path / 'old', version=9, storage_plugin=StoragePlugin.MCAP)
    rb.open()
    conn = rb.add_connection('/omni/pose', POSE_TYPE, typestore=typestore())
    raw = pose_raw(0)
    n = 20_000  # > 2 chunks of 1 MiB
    for k in range(n):
        rb.write(conn, T0 + k, raw)
    rb.storage.bio.flush()
    killed = snapshot(rb, tmp_path / 'killed')
    rb.close()
    assert not (killed / 'metadata.yaml').exists()
    result = recover_bag(killed)
    whole_chunks = chunk_message_counts(tmp_path / 'old' / 'old.mcap')[:-1]  # the last was open
    assert len(whole_chunks) >= 2
    assert result.counts == {'/omni/pose': sum(whole_chunks)}
    assert pose_stamps(killed) == [T0 + k for k in range(sum(whole_chunks))]
    assert metadata(killed)['topics_with_message_count'][0]['topic_metadata'][
        'type_description_hash'] == typestore().hash_rihs01(POSE_TYPE)
    assert_reads_with_rosbags_and_counts_match(killed)


def chunk_message_counts(mcap_path: Path) -> list[int]:
    """Messages per chunk record of a complete MCAP file, in file order."""
    from mcap.records import Chunk, Message
    from mcap.stream_reader import StreamReader, breakup_chunk

    with open(mcap_path, 'rb') as stream:
        return [sum(isinstance(r, Message) for r in breakup_chunk(rec))
                for rec in StreamReader(stream, emit_chunks=True).records if isinstance(rec, Chunk)]


def test_complete_bag_is_left_unchanged(tmp_path):
    with BagWriter(tmp_path / 'b') as writer:
        for k in range(5):
            write_pose(writer, k)
    before = {p.name: p.read_bytes() for p in (tmp_path / 'b').iterdir()}
    result = recover_bag(tmp_path / 'b')
    assert result.complete and result.counts == {'/omni/pose': 5}
    assert {p.name: p.read_bytes() for p in (tmp_path / 'b').iterdir()} == before


def test_recovery_into_an_output_folder_leaves_the_input_untouched(tmp_path):
    writer = BagWriter(tmp_path / 'live')
    for k in range(10):
        write_pose(writer, k)
    writer.flush()
    killed = snapshot(writer, tmp_path / 'killed')
    writer.close()
    before = (killed / 'live.mcap').read_bytes()
    result = recover_bag(killed, tmp_path / 'out')
    assert result.path == tmp_path / 'out' and result.counts == {'/omni/pose': 10}
    assert (killed / 'live.mcap').read_bytes() == before and not (killed / 'metadata.yaml').exists()
    assert assert_reads_with_rosbags_and_counts_match(tmp_path / 'out') == {'/omni/pose': 10}
    with pytest.raises(OutputError, match='already exists'):
        recover_bag(killed, tmp_path / 'out')


# -- clear errors ---------------------------------------------------------------------------------
def _unfinished(tmp_path: Path, n: int = 50) -> Path:
    writer = BagWriter(tmp_path / 'live')
    for k in range(n):
        write_pose(writer, k)
    writer.flush()
    bag = snapshot(writer, tmp_path / 'unfinished')
    writer.close()
    return bag


def test_replay_of_an_unfinished_bag_names_the_recover_command(tmp_path):
    bag = _unfinished(tmp_path)
    with pytest.raises(BagError, match=r'unfinished bag.*omni_bag_recover'):
        load_replay(bag)
    shutil.copy(tmp_path / 'live' / 'metadata.yaml', bag / 'metadata.yaml')  # ...but no summary
    with pytest.raises(BagError, match=r'corrupt or unreadable.*omni_bag_recover'):
        load_replay(bag)
    recover_bag(bag)
    assert len(load_replay(bag)) == 50


@pytest.mark.parametrize('case', ['empty', 'not_mcap', 'header_only', 'no_mcap', 'missing', 'file'])
def test_unrecoverable_input_is_a_clear_error(tmp_path, case):
    bag = tmp_path / 'bag'
    bag.mkdir()
    if case == 'empty':
        (bag / 'bag.mcap').write_bytes(b'')
    elif case == 'not_mcap':
        (bag / 'bag.mcap').write_bytes(b'SQLite format 3\x00' + bytes(200))
    elif case == 'header_only':
        BagWriter(tmp_path / 'h').abort()
        shutil.copy(tmp_path / 'h' / 'h.mcap', bag / 'bag.mcap')
    elif case == 'missing':
        bag = tmp_path / 'nope'
    elif case == 'file':
        bag = bag / 'x.mcap'
        bag.write_bytes(b'x')
    expected = {'empty': 'is empty', 'not_mcap': 'not an MCAP file', 'header_only':
                'no complete message', 'no_mcap': 'no .mcap file', 'missing': 'bag not found',
                'file': 'got a file'}[case]
    with pytest.raises(BagError, match=expected):
        recover_bag(bag)


def test_damaged_or_truncated_bags_never_raise_anything_but_bag_error(tmp_path):
    """Replay loading and recovery of a bag cut or flipped anywhere: BagError or success only."""
    writer = BagWriter(tmp_path / 'src')
    for k in range(400):
        write_pose(writer, k)
        if k % 50 == 49:
            writer.flush()
    writer.close()
    data = writer.mcap_path.read_bytes()
    meta = (writer.path / 'metadata.yaml').read_bytes()
    for i in range(60):
        pos = (i * 7919) % len(data)
        damaged = data[:pos] if i % 2 else data[:pos] + bytes([data[pos] ^ 0x5A]) + data[pos + 1:]
        bag = tmp_path / f'd{i}'
        bag.mkdir()
        (bag / f'd{i}.mcap').write_bytes(damaged)
        (bag / 'metadata.yaml').write_bytes(meta.replace(b'src.mcap', f'd{i}.mcap'.encode()))
        for action in (load_replay, recover_bag, load_replay):
            try:
                action(bag)
            except BagError:
                pass


def test_recover_command_reports_and_exits_with_the_documented_codes(tmp_path, capsys):
    bag = _unfinished(tmp_path, n=30)
    assert recover.main([str(bag)]) == 0
    assert 'recovered 30 messages (/omni/pose: 30)' in capsys.readouterr().out
    assert recover.main([str(bag)]) == 0
    assert 'is a complete bag' in capsys.readouterr().out
    (tmp_path / 'empty').mkdir()
    (tmp_path / 'empty' / 'empty.mcap').write_bytes(b'')
    assert recover.main([str(tmp_path / 'empty')]) == 1
    assert 'omni_bag_recover: error:' in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        recover.main([])
    assert exc.value.code == 2


def test_installed_recover_command_gives_an_error_line_not_a_traceback(tmp_path):
    bag = tmp_path / 'bag'
    bag.mkdir()
    (bag / 'bag.mcap').write_bytes(b'\x89MCAP0\r\n' + b'\x00garbage' * 20)
    exe = harness.executable('haptic_omni_driver', 'omni_bag_recover')
    proc = subprocess.run([str(exe), str(bag)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1
    assert 'omni_bag_recover: error:' in proc.stderr and 'Traceback' not in proc.stderr


def test_a_failed_background_flush_makes_the_next_write_fail_cleanly(tmp_path, monkeypatch):
    import os

    writer = BagWriter(tmp_path / 'b', flush_period=0.02)
    monkeypatch.setattr(os, 'fsync', lambda fd: (_ for _ in ()).throw(
        OSError(errno.ENOSPC, 'No space left on device')))
    write_pose(writer, 0)
    deadline = time.monotonic() + 30
    with pytest.raises(OutputError, match='cannot sync .*No space left on device'):
        while time.monotonic() < deadline:
            write_pose(writer, 1)
            time.sleep(0.01)
    monkeypatch.undo()
    writer.abort()
