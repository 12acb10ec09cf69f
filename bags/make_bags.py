#!/usr/bin/env python3
"""Regenerate the bundled bags: scripted device sessions closed through the simulation, recorded.

For each session (see ``bags/sessions.py``):

1. the session's stylus script (the scripted backend's minimum-jerk generator, tremor and encoder
   quantisation) is written to an input bag, poses at ``rate`` with header stamp = log time;
2. the node graph runs as real processes on a private ROS_DOMAIN_ID: ``omni_driver`` replays the
   input bag in lockstep (each pose waits for the force reply), ``sim_node`` runs in lockstep with
   the golden parameters (``bags/golden_sim_params.yaml``) and ``omni_record`` records
   ``omni/pose``, ``omni/force_feedback`` and ``omni/state`` (reliable, no loss); a session of
   several instruments runs one replaying driver per instrument, each in its namespace, and the
   recorder records every instrument's three topics;
3. the recording is finalised into ``bags/<name>/``: the recorded CDR bytes are kept as they are;
   log times are put on the device clock (a pose at its header stamp, a force at the stamp of the
   pose it answers + 1 ns, a state 2 ns after the pose it followed: in lockstep the wall-clock
   receive times only say how fast this machine was) so that timed replay plays the session at its
   real rate; MCAP chunks are zstd-compressed (rosbags and ``ros2 bag`` read them).

The pose and force streams are bit-identical on every regeneration (lockstep, fixed parameters);
``omni/state`` is the driver's 100 Hz wall-clock status, so its count and ``command_age`` vary.

Usage (after ``source scripts/env.sh``)::

    python bags/make_bags.py                 # all sessions into bags/
    python bags/make_bags.py press poke      # some of them
    python bags/make_bags.py --check         # regenerate into a temp dir, compare with bags/
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))   # sessions.py, beside this script

from tissue_testing import harness  # noqa: E402
from tissue_testing import system_graph as graph  # noqa: E402
from haptic_omni_driver.bag_reader import read_bag  # noqa: E402
from haptic_omni_driver.bag_types import POSE_TYPE, WRENCH_TYPE, typestore  # noqa: E402
from haptic_omni_driver.bag_writer import qos_profile, write_bag  # noqa: E402
from sessions import SESSIONS, Geometry, session_messages, session_scripts, topic  # noqa: E402

#: name -> (pose rate [Hz], seed, t0 [ns]); the long session is recorded at 1 kHz too
PLAN = {
    'press': (1000.0, 1, 1_700_000_000_000_000_000),
    'pull': (1000.0, 2, 1_700_000_100_000_000_000),
    'sweep': (1000.0, 3, 1_700_000_200_000_000_000),
    'poke': (1000.0, 4, 1_700_000_300_000_000_000),
    'long': (1000.0, 5, 1_700_000_400_000_000_000),
    'grasp': (1000.0, 6, 1_700_000_500_000_000_000),
    'bimanual': (1000.0, 7, 1_700_000_600_000_000_000),
    'cut': (1000.0, 8, 1_700_000_700_000_000_000),
    'needle': (1000.0, 9, 1_700_000_800_000_000_000),
}
POSE, FORCE, STATE = 'omni/pose', 'omni/force_feedback', 'omni/state'


class IncompleteRecording(RuntimeError):
    """The recording misses poses or force replies."""


def log(text: str) -> None:
    print(f'make_bags: {text}', flush=True)


def stamp_of(raw: bytes, msgtype: str) -> int:
    """Header stamp [ns] of a CDR-encoded stamped message."""
    msg = typestore().deserialize_cdr(raw, msgtype)
    return msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def instruments(name: str) -> tuple[str, ...]:
    """The instruments of a session: its scripts' names, which sim_node must serve."""
    names = tuple(session_scripts(name))
    if names != graph.bag_instruments(name):
        raise SystemExit(f'make_bags: {name}: the scripts are for {names}, sim_node would serve '
                         f'{graph.bag_instruments(name)} (system_graph.BAG_SIM_PARAMS)')
    return names


def topics(name: str) -> list[str]:
    """Every recorded topic of a session: pose, force and state of each instrument."""
    return [topic(i, t) for i in instruments(name) for t in (POSE, FORCE, STATE)]


def record(name: str, input_bag: Path, raw_out: Path, timeout: float) -> None:
    """Run a driver per instrument (replay, lockstep) + sim (lockstep, golden params) + omni_record
    on a private domain."""
    env = harness.ros_env()
    sim = graph.sim('lockstep', env=env, params=graph.BAG_SIM_PARAMS.get(name))
    rec = graph.recorder(raw_out, env=env, params={'topics': topics(name)})
    drivers = [graph.driver_replay(input_bag, 'lockstep', env=env, subscribers=2, instrument=i,
                                   params={'lockstep_timeout_action': 'abort', 'lockstep_timeout': 60.0})
               for i in instruments(name)]
    procs = [sim, rec, *drivers]
    try:
        sim.start()
        sim.wait_for_output(graph.SIM_READY, timeout=180)
        rec.start()
        rec.wait_for_output(graph.RECORD_READY, timeout=60)
        for i in instruments(name):
            rec.wait_for_output(graph.record_matched(topic(i, FORCE)), timeout=60)
        t0 = time.monotonic()
        for drv in drivers:
            drv.start()
        for drv in drivers:
            code = drv.wait(timeout)
            if code != 0:
                # e.g. a lockstep reply that never came on a loaded machine: the run is lost, not the session
                raise IncompleteRecording(f'{drv.name} exited with {code}:\n{drv.output()[-3000:]}')
        log(f'{name}: lockstep replay took {time.monotonic() - t0:.1f} s')
        time.sleep(0.5)  # the last force is in flight to the recorder as well
        rec.stop(30)
        if 'bag closed' not in rec.output():
            raise SystemExit(f'make_bags: omni_record did not close the bag:\n{rec.output()[-3000:]}')
    finally:
        for p in procs:
            p.stop()


def finalise(raw_bag: Path, out: Path, expected_poses: int, names: tuple[str, ...] = ('',)) -> dict:
    """Re-time the recording of the instruments ``names`` onto the device clock and write ``out``
    (zstd MCAP); ``expected_poses`` per instrument; returns counts."""
    msgs = list(read_bag(raw_bag, raw=True))
    out_msgs = []
    counts = {'poses': 0, 'forces': 0, 'states': 0}
    qos = {}
    for k, instrument in enumerate(names):
        pose_topic, force_topic, state_topic = (topic(instrument, t) for t in (POSE, FORCE, STATE))
        poses = [m for m in msgs if m[0] == pose_topic]
        forces = [m for m in msgs if m[0] == force_topic]
        if len(poses) != expected_poses:
            raise IncompleteRecording(f'recorded {len(poses)} poses on {pose_topic}, the script has '
                                      f'{expected_poses}')
        pose_stamps = [stamp_of(m[3], POSE_TYPE) for m in poses]
        force_stamps = [stamp_of(m[3], WRENCH_TYPE) for m in forces]
        if sorted(force_stamps) != pose_stamps:
            missing = len(set(pose_stamps) - set(force_stamps))
            raise IncompleteRecording(f'{len(forces)} forces for {len(poses)} poses on {pose_topic} '
                                      f'({missing} poses without a reply, or duplicates): not a '
                                      f'complete lockstep recording')
        last_pose = pose_stamps[0]
        for name, msgtype, _, raw in msgs:
            if name == pose_topic:
                last_pose = stamp_of(raw, msgtype)
                out_msgs.append((last_pose, 0, k, name, msgtype, raw))
            elif name == force_topic:
                out_msgs.append((stamp_of(raw, msgtype) + 1, 1, k, name, msgtype, raw))
            elif name == state_topic:
                out_msgs.append((last_pose + 2, 2, k, name, msgtype, raw))
                counts['states'] += 1
        counts['poses'] += len(poses)
        counts['forces'] += len(forces)
        qos.update({pose_topic: [qos_profile(True, 1000)], force_topic: [qos_profile(True, 1000)],
                    state_topic: [qos_profile(True, 10)]})
    # at one log time: poses, then forces, then states, each in the instruments' order
    out_msgs.sort(key=lambda m: m[:3])
    tmp_dir = Path(tempfile.mkdtemp(prefix='make_bags_'))
    tmp = tmp_dir / out.name  # rosbags names the .mcap file after the folder
    write_bag(tmp, [(t, mt, log_ns, raw) for log_ns, _, _, t, mt, raw in out_msgs], qos=qos)
    try:
        compress_mcap(tmp, out)
    finally:
        shutil.rmtree(tmp_dir)
    return counts


def compress_mcap(src: Path, dst: Path) -> None:
    """Copy the bag folder ``src`` to ``dst`` with its MCAP chunks zstd-compressed (records kept)."""
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    dst.mkdir(parents=True)
    shutil.copy2(src / 'metadata.yaml', dst / 'metadata.yaml')
    for mcap_file in src.glob('*.mcap'):
        with open(mcap_file, 'rb') as fin, open(dst / mcap_file.name, 'wb') as fout:
            reader = make_reader(fin)
            header = reader.get_header()
            writer = Writer(fout, compression=CompressionType.ZSTD, chunk_size=4 * 1024 * 1024)
            writer.start(header.profile, header.library)
            schema_ids, channel_ids = {}, {}
            for schema, channel, message in reader.iter_messages(log_time_order=False):
                if schema is not None and schema.id not in schema_ids:
                    schema_ids[schema.id] = writer.register_schema(schema.name, schema.encoding,
                                                                   schema.data)
                if channel.id not in channel_ids:
                    channel_ids[channel.id] = writer.register_channel(
                        channel.topic, channel.message_encoding,
                        schema_ids.get(channel.schema_id, 0), channel.metadata)
                writer.add_message(channel_ids[channel.id], message.log_time, message.data,
                                   message.publish_time, message.sequence)
            for meta in reader.iter_metadata():
                writer.add_metadata(meta.name, meta.metadata)
            writer.finish()


def stream_digest(bag: Path, topic: str) -> tuple[int, str]:
    """(count, sha256 of the concatenated CDR bytes) of one topic, in log-time order."""
    h = hashlib.sha256()
    n = 0
    for _, _, _, raw in read_bag(bag, [topic], raw=True):
        h.update(raw)
        n += 1
    return n, h.hexdigest()


def make(name: str, out_dir: Path, geometry: Geometry) -> dict:
    """Script -> lockstep recording -> ``out_dir/name`` (retried if the recording is incomplete or
    the driver gave up on a reply)."""
    rate, seed, t0 = PLAN[name]
    out = out_dir / name
    with tempfile.TemporaryDirectory(prefix=f'make_bags_{name}_') as tmp:
        input_bag = Path(tmp) / f'{name}_script'
        messages = session_messages(name, rate, geometry, seed, t0)
        write_bag(input_bag, messages)
        names = instruments(name)
        n = sum(1 for m in messages if m[0] == topic(names[0], POSE))
        log(f'{name}: script of {n} poses ({n / rate:.1f} s at {rate:g} Hz); recording')
        for attempt in range(1, 4):
            raw = Path(tmp) / f'{name}_raw{attempt}'
            if out.exists():
                shutil.rmtree(out)
            try:
                record(name, input_bag, raw, timeout=max(120.0, 0.02 * n))
                counts = finalise(raw, out, n, names)
                break
            except IncompleteRecording as exc:
                # e.g. a lockstep reply that never came on a loaded machine
                log(f'{name}: attempt {attempt}: {exc}')
        else:
            raise SystemExit(f'make_bags: {name}: no complete recording in 3 attempts')
    size = sum(f.stat().st_size for f in out.iterdir())
    log(f'{name}: {counts} -> {out} ({size / 1e6:.2f} MB)')
    return counts


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('names', nargs='*', default=list(PLAN),
                    help='sessions (default all): ' + '; '.join(f'{n}: {SESSIONS[n][1]}'
                                                                for n in PLAN))
    ap.add_argument('--out', type=Path, default=HERE, help='output folder (default: bags/)')
    ap.add_argument('--check', action='store_true',
                    help='regenerate into a temp dir and compare pose/force streams with bags/')
    args = ap.parse_args(argv)
    unknown = [n for n in args.names if n not in PLAN]
    if unknown:
        ap.error(f'unknown session(s) {unknown}; choose from {list(PLAN)}')
    geometry = Geometry()
    if not args.check:
        for name in args.names:
            make(name, args.out, geometry)
        if args.out.resolve() == HERE.resolve():
            # the system tests hold the goldens bit for bit on this kind of CPU, to 1e-9 N elsewhere
            graph.GOLDEN_HOST.write_text(json.dumps(graph.host_kind(), indent=1) + '\n')
        return 0
    bad = 0
    with tempfile.TemporaryDirectory(prefix='make_bags_check_') as tmp:
        for name in args.names:
            make(name, Path(tmp), geometry)
            for stream in (topic(i, t) for i in instruments(name) for t in (POSE, FORCE)):
                new, old = stream_digest(Path(tmp) / name, stream), stream_digest(HERE / name, stream)
                same = new == old
                bad += not same
                log(f'check {name} {stream}: {"identical" if same else "DIFFERENT"} '
                    f'({new[0]} vs {old[0]} messages)')
    return 1 if bad else 0


if __name__ == '__main__':
    sys.exit(main())
