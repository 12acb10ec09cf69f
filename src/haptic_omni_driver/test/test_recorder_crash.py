"""omni_record as a real process: killed mid-stream, unwritable output, refused starts."""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest
import yaml

from tissue_testing import harness
from haptic_omni_driver.bag_reader import read_bag
from omni_test_utils import make_pose_bag

pytestmark = pytest.mark.ros

PKG = 'haptic_omni_driver'
PROGRESS = re.compile(r'\[INFO\] \[(\d+\.\d+)\] \[omni_record\]: recorded \d+ messages \(.*?'
                      r'/omni/pose: (\d+)')


def recorder(params: dict, **kw) -> harness.NodeProcess:
    return harness.NodeProcess(PKG, 'omni_record', params=params, **kw)


def replay(bag: Path, **params) -> harness.NodeProcess:
    return harness.NodeProcess(PKG, 'omni_driver', params={
        'backend': 'replay', 'bag': str(bag), 'reliable': True, 'qos_depth': 1000,
        'exit_on_end': True, **params})


def progress(output: str) -> list[tuple[float, int]]:
    """(wall time of the log line, /omni/pose messages written) of each progress line."""
    return [(float(t), int(n)) for t, n in PROGRESS.findall(output)]


def wait_for_progress(rec: harness.NodeProcess, predicate, timeout: float) -> list:
    deadline = time.monotonic() + timeout
    while True:
        lines = progress(rec.output())
        if predicate(lines):
            return lines
        assert rec.alive(), f'omni_record exited:\n{rec.output()}'
        assert time.monotonic() < deadline, f'progress not seen in {timeout} s:\n{rec.output()}'
        time.sleep(0.05)


def _contiguous_run(got: list[bytes], ref: list[bytes]) -> bool:
    """``got`` is ``ref[s:s + len(got)]`` for some s (in order, no gap, no duplicate)."""
    if not got or got[0] not in ref:
        return False
    start = ref.index(got[0])
    return got == ref[start:start + len(got)]


def test_killed_recorder_loses_at_most_the_last_second_after_recovery(ros_domain, tmp_path):
    make_pose_bag(tmp_path / 'input', n=8000, period_ns=1_000_000)  # 8 s at 1 kHz
    published = [d for *_, d in read_bag(tmp_path / 'input', ['/omni/pose'], raw=True)]
    out = tmp_path / 'session'
    rec = recorder({'output': str(out), 'reliable': True, 'progress_period': 0.1})
    with rec:
        rec.wait_for_output(r'recording', 60)
        with replay(tmp_path / 'input', wait_for_subscribers=1):
            # 1500 poses on the recorder's side, then the recorder still at work 1.2 s later
            first = wait_for_progress(rec, lambda ls: any(n >= 1500 for _, n in ls), 60)
            t_first = next(t for t, n in first if n >= 1500)
            wait_for_progress(rec, lambda ls: ls[-1][0] >= t_first + 1.2, 60)
            rec.send_signal(signal.SIGKILL)
            t_kill = time.time()
            assert rec.wait(10) == -signal.SIGKILL
        written_1s_before = max(n for t, n in progress(rec.output()) if t <= t_kill - 1.0)
    assert written_1s_before >= 1500
    assert sorted(p.name for p in out.iterdir()) == ['session.mcap']  # no metadata.yaml yet

    # the replay backend refuses it with a pointer to the recover command
    with replay(out) as drv:
        assert drv.wait(60) == 1
        assert 'omni_bag_recover' in drv.output() and 'Traceback' not in drv.output()

    exe = harness.executable(PKG, 'omni_bag_recover')
    proc = subprocess.run([str(exe), str(out)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert 'recovered' in proc.stdout

    # (a) every pose written at least 1 s before the kill is back, in order, byte for byte (the
    # stream may start a little late: a reliable reader that DDS discovery matched after the
    # replay began does not get the poses sent before)
    recovered = [d for *_, d in read_bag(out, ['/omni/pose'], raw=True)]
    assert len(recovered) >= written_1s_before
    assert _contiguous_run(recovered, published)
    # (b) rosbags reads the bag and metadata.yaml counts what is in it
    from rosbags.highlevel import AnyReader

    with AnyReader([out]) as reader:
        read: dict[str, int] = {}
        for conn, _, _ in reader.messages():
            read[conn.topic] = read.get(conn.topic, 0) + 1
    meta = yaml.safe_load((out / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert {t['topic_metadata']['name']: t['message_count']
            for t in meta['topics_with_message_count']} == read
    assert meta['message_count'] == sum(read.values())
    assert read['/omni/pose'] == len(recovered) and read.get('/omni/state', 0) > 0
    # (c) the replay backend plays it
    with replay(out, rate=4.0) as drv:
        assert drv.wait(120) == 0
        assert f'replay finished: {len(recovered)} poses' in drv.output()


def _private_mounts_available() -> bool:
    if not shutil.which('unshare'):
        return False
    probe = subprocess.run(['unshare', '-m', 'sh', '-c', 'mount -t tmpfs -o ro none /mnt'],
                           capture_output=True, timeout=30)
    return probe.returncode == 0


def _recorder_cmd(cmd_prefix: list[str], params: dict, tmp_path: Path) -> subprocess.Popen:
    """Start omni_record (inside ``cmd_prefix``, e.g. a private mount namespace); output piped."""
    params_file = harness.write_params_file('/**', params, tmp_path)
    cmd = [*cmd_prefix, str(harness.executable(PKG, 'omni_record')), '--ros-args', '--params-file',
           str(params_file)]
    return subprocess.Popen(cmd, env=harness.ros_env(int(os.environ['ROS_DOMAIN_ID'])),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            start_new_session=True, preexec_fn=harness._die_with_parent)


def _finish(proc: subprocess.Popen, timeout: float = 120) -> str:
    """Wait for ``proc`` to exit by itself (killed if it does not); returns its output."""
    try:
        out, _ = proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)
    return out


def _start_refused(cmd_prefix: list[str], params: dict, tmp_path: Path) -> tuple[int, str]:
    """(exit code, output) of an omni_record start that is expected to be refused."""
    proc = _recorder_cmd(cmd_prefix, params, tmp_path)
    out = _finish(proc)
    return proc.returncode, out


@pytest.mark.parametrize('case', ['under_a_file', 'read_only_file_system', 'no_permission'])
def test_unwritable_output_is_one_error_line_and_exit_code_1(ros_domain, tmp_path, case):
    prefix: list[str] = []
    if case == 'under_a_file':
        (tmp_path / 'notes.txt').write_text('x')
        output, expected = tmp_path / 'notes.txt' / 'session', 'notes.txt is a file, not a folder'
    elif case == 'read_only_file_system':
        if not _private_mounts_available():
            pytest.skip('no private mount namespace (unshare -m) to mount a read-only file system')
        (tmp_path / 'ro').mkdir()
        output, expected = tmp_path / 'ro' / 'session', 'Read-only file system'
        script = f'mount -t tmpfs -o ro none {tmp_path / "ro"} && exec "$0" "$@"'
        prefix = ['unshare', '-m', 'sh', '-c', script]
    else:
        if os.geteuid() == 0:
            pytest.skip('root ignores directory permissions')
        (tmp_path / 'locked').mkdir(mode=0o555)
        output, expected = tmp_path / 'locked' / 'session', 'Permission denied'
    code, out = _start_refused(prefix, {'output': str(output)}, tmp_path)
    assert code == 1, out
    assert re.search(rf'\[FATAL\].*error: cannot create bag folder .*{expected}', out)
    assert 'Traceback' not in out
    assert not output.exists()


def test_refused_start_creates_nothing_and_is_refused_the_same_way_again(ros_domain, tmp_path):
    out = tmp_path / 'session'
    for _ in range(2):
        code, text = _start_refused([], {'output': str(out), 'topics': ['tissue/metrics']},
                                    tmp_path)
        assert code == 2, text
        assert "error: cannot record 'tissue/metrics'" in text
        assert 'already exists' not in text and 'Traceback' not in text
        assert not out.exists()


def test_existing_output_is_refused_with_exit_code_1_and_left_alone(ros_domain, tmp_path):
    out = tmp_path / 'session'
    out.mkdir()
    (out / 'keep.txt').write_text('mine')
    code, text = _start_refused([], {'output': str(out)}, tmp_path)
    assert code == 1, text
    assert 'already exists' in text and 'Traceback' not in text
    assert sorted(p.name for p in out.iterdir()) == ['keep.txt']


def test_full_disk_while_recording_is_an_error_line_and_exit_code_1(ros_domain, tmp_path):
    if not _private_mounts_available():
        pytest.skip('no private mount namespace (unshare -m) to mount a small file system')
    make_pose_bag(tmp_path / 'input', n=3000, period_ns=1_000_000)
    (tmp_path / 'small').mkdir()
    script = f'mount -t tmpfs -o size=128k none {tmp_path / "small"} && exec "$0" "$@"'
    rec = _recorder_cmd(['unshare', '-m', 'sh', '-c', script],
                        {'output': str(tmp_path / 'small' / 'session'), 'reliable': True}, tmp_path)
    with replay(tmp_path / 'input', wait_for_subscribers=1):
        out = _finish(rec)  # 3 s of poses fill 128 KiB long before the end
    assert rec.returncode == 1, out
    assert re.search(r'\[FATAL\].*error: cannot write .*session\.mcap: No space left on device',
                     out)
    assert 'omni_bag_recover' in out and 'Traceback' not in out
