#!/usr/bin/env python3
"""Closed-loop latency of sim_node: omni/pose at 1 kHz in, omni/force_feedback out.

Starts ``sim_node`` (the installed executable, as ``ros2 run`` would) on an isolated DDS domain,
publishes geometry_msgs/PoseStamped at ``--rate`` Hz along a pressing path (down 1 cm into the
tissue and back, with a lateral sweep) for ``--duration`` seconds, and matches every
geometry_msgs/WrenchStamped reply to its pose by header stamp. Reports the round trip (pose publish
-> wrench receive, both measured in this process) median / p90 / p99 / max, the achieved pose and
reply rates, the share of poses without a reply (live mode drops to the newest pose by design),
and the node's own step wall time from tissue/metrics. Prints a table and writes CSV files.

With ``--instruments left,right`` the node serves several instruments on one tissue: each gets its
own 1 kHz pose stream in its namespace, the second half a period after the first (two devices'
clocks are not in step), along the same path 30 mm apart (``instrument_offsets``), and each is
reported on its own.

    source scripts/env.sh
    python benchmarks/sim_latency.py --duration 10 --model liver --n-particles 3670
    python benchmarks/sim_latency.py --model block --n-particles 256 --mode global --csv /tmp/x.csv
    python benchmarks/sim_latency.py --instruments left,right --duration 10

This is a benchmark, not a test: it asserts nothing and reports what it measured.
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import re
import sys
import threading
import time
from pathlib import Path

import numpy as np
import yaml

from tissue_common.feel import feel
from tissue_common.instruments import topic_within
from tissue_testing import harness

ROOT = Path(__file__).resolve().parent.parent


def quaternion(text: str) -> tuple[float, float, float, float]:
    """``x,y,z,w`` as a unit quaternion (argparse type)."""
    q = np.array([float(v) for v in text.split(',')])
    if q.shape != (4,) or not np.isfinite(q).all() or np.linalg.norm(q) < 1e-6:
        raise argparse.ArgumentTypeError(f'a quaternion is four finite numbers x,y,z,w, got {text!r}')
    return tuple(float(v) for v in q / np.linalg.norm(q))


def pressing_path(t: float, depth: float, period: float) -> tuple[float, float, float]:
    """Device-frame tip position [m] at time t: 4 mm above the surface point down to ``depth`` below
    it and back every ``period`` s (cosine), sweeping +-5 mm along x twice as slowly."""
    s = 0.5 - 0.5 * math.cos(2.0 * math.pi * t / period)
    y = 0.004 - (0.004 + depth) * s
    x = 0.005 * math.sin(math.pi * t / period)
    return x, y, 0.0


def percentile(a, q: float) -> float:
    return float(np.percentile(a, q)) if len(a) else math.nan


#: what the hand got, in each summary (tissue_common.feel)
FEEL_KEYS = ('dF_p99_mN', 'dF_max_mN', 'reversals', 'E_in_min_uJ')
#: [m] between neighbouring instruments' devices on the tissue (along the tissue frame's y: the
#: default liver's top is level there)
INSTRUMENT_SPACING = 0.03


def instrument_names(text: str) -> list[str]:
    """``--instruments``: '' is one instrument at the root namespace."""
    return [n.strip() for n in text.split(',')] if text else ['']


def loop_stats(args, send_ns: np.ndarray, recv_ns: np.ndarray, force: np.ndarray) -> dict:
    """One instrument's pose stream: answered share, round trip and what the hand got."""
    n_total = len(send_ns)
    skip = int(args.skip * args.rate)
    sel = slice(skip, n_total)
    got = recv_ns[sel] > 0
    rtt_ms = (recv_ns[sel][got] - send_ns[sel][got]) * 1e-6
    span = (send_ns[n_total - 1] - send_ns[skip]) * 1e-9
    fnorm = np.linalg.norm(force[sel][got], axis=1)
    out = {
        'poses_sent': int(n_total - skip),
        'send_rate_hz': (n_total - skip - 1) / span if span > 0 else math.nan,
        'replies': int(got.sum()),
        'reply_rate_hz': got.sum() / span if span > 0 else math.nan,
        'no_reply_pct': 100.0 * (1.0 - got.mean()) if len(got) else math.nan,
        'rtt_median_ms': percentile(rtt_ms, 50), 'rtt_p90_ms': percentile(rtt_ms, 90),
        'rtt_p99_ms': percentile(rtt_ms, 99), 'rtt_max_ms': float(rtt_ms.max()) if len(rtt_ms) else math.nan,
        'max_force_n': float(fnorm.max()) if len(fnorm) else math.nan,
        'forces_finite': bool(np.all(np.isfinite(force[sel][got]))),
    }
    # what the hand got (tissue_common.feel): every reply, each with the pose it answered (from the
    # first pose: E_in counts what went in before the skipped second too)
    k_got = np.flatnonzero(recv_ns > 0)
    if k_got.size >= 3:
        path_xyz = np.array([pressing_path(k / args.rate, args.depth, args.press_period) for k in k_got])
        felt = feel(path_xyz, force[k_got], k_got / args.rate, 1.0 / args.rate)
        out.update({key: felt[key] for key in FEEL_KEYS})
    else:
        out.update({key: math.nan for key in FEEL_KEYS})
    return out


def run(args) -> dict:
    # the probe's publisher thread and executor share the GIL: hand it over quickly
    sys.setswitchinterval(args.switch_interval)
    import rclpy
    from geometry_msgs.msg import PoseStamped, WrenchStamped
    from rclpy.experimental import EventsExecutor
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from tissue_msgs.msg import SimMetrics

    domain = harness.new_domain_id()
    os.environ['ROS_DOMAIN_ID'] = str(domain)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    params = {'model': args.model, 'n_particles': args.n_particles, 'mode': args.mode,
              'scheme': args.scheme, 'timing_mode': args.timing,
              'particles_rate': args.particles_rate, 'haptic_mode': args.haptic_mode}
    for item in args.set:
        name, _, value = item.partition('=')
        params[name] = yaml.safe_load(value)
    if args.step_thread != 'default':
        params['step_thread'] = args.step_thread == 'on'
    if args.model == 'block':
        params['block_size'] = [0.08, 0.08, 0.04]
    names = instrument_names(args.instruments)
    n_inst = len(names)
    if n_inst > 1:
        params['instruments'] = names
        params['instrument_offsets'] = [v for i in range(n_inst)
                                        for v in (0.0, INSTRUMENT_SPACING * (i - 0.5 * (n_inst - 1)), 0.0)]
    lockstep = args.timing == 'lockstep'
    io_qos = QoSProfile(depth=1000 if lockstep else 1, history=HistoryPolicy.KEEP_LAST,
                        reliability=ReliabilityPolicy.RELIABLE if lockstep
                        else ReliabilityPolicy.BEST_EFFORT)
    n_total = int(round(args.duration * args.rate))
    send_ns = np.zeros((n_inst, n_total), dtype=np.int64)
    recv_ns = np.zeros((n_inst, n_total), dtype=np.int64)
    force = np.full((n_inst, n_total, 3), np.nan)
    step_wall: list[float] = []
    stamp0 = time.time_ns()
    period_ns = int(round(1e9 / args.rate))

    peer, env = None, None
    if args.peer:
        peer = [sys.executable, str(ROOT / 'benchmarks' / 'echo_node.py')]
    elif args.node_src:
        # another checkout's sim_node (before / after a change, timed in one run)
        peer = [sys.executable, '-m', 'sph_tissue_sim.sim_node']
        env = harness.ros_env(int(os.environ['ROS_DOMAIN_ID']) if 'ROS_DOMAIN_ID' in os.environ
                              else None)
        src = Path(args.node_src).resolve() / 'src'
        env['PYTHONPATH'] = os.pathsep.join([str(src / 'sph_tissue_sim'), str(src / 'tissue_common'),
                                             env.get('PYTHONPATH', '')])
    # the probe is up before the node starts: discovery runs while it loads
    rclpy.init()
    node = rclpy.create_node('sim_latency_probe')
    executor = EventsExecutor()
    executor.add_node(node)
    pubs = [node.create_publisher(PoseStamped, topic_within(name, 'omni/pose'), io_qos) for name in names]
    # the i-th instrument's poses are stamped i / n_inst of a period after the first's
    offset_ns = [i * period_ns // n_inst for i in range(n_inst)]

    def on_wrench(msg: WrenchStamped, i: int) -> None:
        now = time.monotonic_ns()
        st = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        k = (st - stamp0 - offset_ns[i]) // period_ns
        if 0 <= k < n_total and recv_ns[i, k] == 0:
            recv_ns[i, k] = now
            f = msg.wrench.force
            force[i, k] = (f.x, f.y, f.z)

    def on_metrics(msg: SimMetrics) -> None:
        step_wall.append(msg.step_wall_time)

    subs = [node.create_subscription(WrenchStamped, topic_within(name, 'omni/force_feedback'),
                                     lambda msg, i=i: on_wrench(msg, i),
                                     QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST,
                                                reliability=io_qos.reliability))
            for i, name in enumerate(names)]
    msub = None
    if args.metrics:  # another 1 kHz stream into this process: it delays the wrench callbacks
        # one step serves every instrument: the first one's metrics carry its wall time
        msub = node.create_subscription(SimMetrics, topic_within(names[0], 'tissue/metrics'), on_metrics,
                                        QoSProfile(depth=1000, history=HistoryPolicy.KEEP_LAST,
                                                   reliability=ReliabilityPolicy.RELIABLE))
    launched_ns = time.monotonic_ns()
    with harness.NodeProcess('sph_tissue_sim', 'sim_node', params=params, command=peer,
                             env=env) as sim:
        m = None if args.peer else sim.wait_for_output(r'numba warm-up .*: ([0-9.]+) s', 600)
        sim.wait_for_output(r'ready:', 60)
        ready_s = (time.monotonic_ns() - launched_ns) * 1e-9
        ready_line = [ln for ln in sim.output().splitlines() if 'ready:' in ln][-1]
        deadline = time.monotonic() + 30
        while (any(pub.get_subscription_count() < 1 for pub in pubs)
               or any(sub.get_publisher_count() < 1 for sub in subs)
               or (msub is not None and msub.get_publisher_count() < 1)):
            executor.spin_once(timeout_sec=0.01)
            if time.monotonic() > deadline:
                raise RuntimeError('sim_node did not match the probe within 30 s')

        done = threading.Event()

        def publisher() -> None:
            msg = PoseStamped()
            msg.header.frame_id = 'omni_base'
            o = msg.pose.orientation
            o.x, o.y, o.z, o.w = args.orientation
            t_start = time.monotonic_ns() + 50_000_000
            for k in range(n_total):
                x, y, z = pressing_path(k / args.rate, args.depth, args.press_period)
                msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = x, y, z
                for i, pub in enumerate(pubs):
                    target = t_start + k * period_ns + offset_ns[i]
                    rest = target - time.monotonic_ns()
                    if rest > 0:  # sleep, never spin: a spinning thread would hold the GIL
                        time.sleep(rest * 1e-9)
                    stamp = stamp0 + k * period_ns + offset_ns[i]
                    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 1_000_000_000)
                    send_ns[i, k] = time.monotonic_ns()
                    pub.publish(msg)
            done.set()

        thread = threading.Thread(target=publisher, daemon=True)
        thread.start()
        while not done.is_set():
            executor.spin_once(timeout_sec=0.01)
        end = time.monotonic() + 0.5  # late replies
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.01)
        executor.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
        code = sim.stop()
        totals = [ln for ln in sim.output().splitlines() if 'totals' in ln]
        steps_line = [ln for ln in sim.output().splitlines() if 'step wall time' in ln]
        if code != 0:
            raise RuntimeError(f'sim_node exited with {code}:\n{sim.output()}')

    skip = int(args.skip * args.rate)
    sw = np.array(step_wall[int(len(step_wall) * skip / max(n_total, 1)):]) * 1e3
    node_steps = [float(v) for v in re.findall(r'([0-9.]+) ms', steps_line[-1])] if steps_line else []
    if not len(sw) and len(node_steps) >= 2:
        sw = np.array(node_steps[:2])          # the node's own median, p99 over the whole run
    summary = {
        'model': args.model, 'n_particles_requested': args.n_particles,
        'particles': _particles(ready_line), 'scheme': args.scheme, 'mode': args.mode,
        'timing': args.timing, 'haptic_mode': args.haptic_mode, 'rate_hz': args.rate, 'duration_s': args.duration,
        'compile_s': float(m.group(1)) if m else math.nan,
        'launch_to_ready_s': ready_s,
        'launch_to_first_reply_s': ((recv_ns[recv_ns > 0].min() - launched_ns) * 1e-9 if np.any(recv_ns > 0)
                                    else math.nan),
        'instruments': ','.join(names),
        'step_median_ms': percentile(sw, 50) if args.metrics else (sw[0] if len(sw) else math.nan),
        'step_p99_ms': percentile(sw, 99) if args.metrics else (sw[1] if len(sw) > 1 else math.nan),
        'sim_totals': totals[-1].split('totals: ')[-1] if totals else '',
    }
    # each instrument's loop; the summary's own loop columns are the first instrument's
    per = [loop_stats(args, send_ns[i], recv_ns[i], force[i]) for i in range(n_inst)]
    summary.update(per[0])
    if n_inst > 1:   # and each one's, for the summary CSV
        summary.update({f'{name}_{key}': value for name, stats in zip(names, per) for key, value in stats.items()})
    steps = re.search(r'([0-9]+) steps', summary['sim_totals'])
    summary['solver_rate_hz'] = int(steps.group(1)) / args.duration if steps else math.nan
    if args.csv:
        path = Path(args.csv)
        path.parent.mkdir(parents=True, exist_ok=True)
        with path.open('w', newline='') as fh:
            w = csv.writer(fh)
            w.writerow(['instrument', 'k', 'stamp_ns', 'send_ns', 'recv_ns', 'rtt_ms', 'fx', 'fy', 'fz'])
            for i, name in enumerate(names):
                for k in range(n_total):
                    rtt = (recv_ns[i, k] - send_ns[i, k]) * 1e-6 if recv_ns[i, k] else ''
                    w.writerow([name, k, stamp0 + k * period_ns + offset_ns[i], send_ns[i, k],
                                recv_ns[i, k] or '', rtt, *force[i, k].tolist()])
        # one summary file per number of instruments: their rows have other columns
        spath = path.with_name(path.stem + ('_summary.csv' if n_inst == 1 else f'_{n_inst}_instruments_summary.csv'))
        new = not spath.exists()
        with spath.open('a', newline='') as fh:
            w = csv.DictWriter(fh, fieldnames=list(summary))
            if new:
                w.writeheader()
            w.writerow(summary)
        summary['csv'] = str(path)
        summary['summary_csv'] = str(spath)
    summary['per_instrument'] = dict(zip(names, per))
    return summary


def _particles(ready_line: str) -> int:
    import re

    m = re.search(r'\((\d+) particles', ready_line)
    return int(m.group(1)) if m else -1


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--duration', type=float, default=10.0, help='seconds of poses')
    ap.add_argument('--rate', type=float, default=1000.0, help='pose rate [Hz]')
    ap.add_argument('--skip', type=float, default=1.0, help='seconds at the start left out of stats')
    ap.add_argument('--model', default='liver', help='liver | block | beam')
    ap.add_argument('--n-particles', type=int, default=3670)
    ap.add_argument('--mode', default='local', help='local | global')
    ap.add_argument('--instruments', default='', help='comma-separated instrument names (namespaces), '
                    'e.g. left,right: one 1 kHz pose stream each; default one at the root')
    ap.add_argument('--scheme', default='tlsph', help='tlsph | mass_spring | paper')
    ap.add_argument('--timing', default='live', help='live | lockstep')
    ap.add_argument('--haptic-mode', default='multirate', help='multirate (the renderer answers, the '
                    'solver refreshes it) | direct (one solver step per pose)')
    ap.add_argument('--depth', type=float, default=0.006, help='[m] deepest press below the surface')
    ap.add_argument('--orientation', type=quaternion, default=(0.0, 0.0, 0.0, 1.0),
                    help='x,y,z,w: the stylus orientation in omni_base (default identity: a shaft along '
                         'the stylus +z lies flat in the default map); --orientation=-0.7071,0,0,0.7071 holds it '
                         'upright, point down into the tissue, as the cut and needle bags do')
    ap.add_argument('--press-period', type=float, default=2.0, help='[s] one press and release')
    ap.add_argument('--particles-rate', type=float, default=30.0, help='[Hz] cloud rate of the node')
    ap.add_argument('--step-thread', default='default', help='on | off | default: the node steps '
                    'in a worker thread (on) or in the subscription callback (off)')
    ap.add_argument('--switch-interval', type=float, default=1e-4,
                    help='[s] this process\'s GIL switch interval (Python default 0.005)')
    ap.add_argument('--set', action='append', default=[], metavar='NAME=VALUE',
                    help='any other sim_node parameter (YAML value; repeatable)')
    ap.add_argument('--peer', action='store_true',
                    help='time benchmarks/echo_node.py instead of sim_node: the same transport and '
                         'executor answering at once with no simulation (the floor of the round trip)')
    ap.add_argument('--node-src', default='',
                    help='run sim_node from this checkout\'s sources instead of the installed one '
                         '(a before/after comparison; its numba cache is its own)')
    ap.add_argument('--metrics', action='store_true',
                    help='also subscribe tissue/metrics for the step time (default: the node\'s own '
                         'step-time line at shutdown)')
    ap.add_argument('--csv', default=str(ROOT / 'benchmarks' / 'results' / 'sim_latency.csv'),
                    help='per-pose CSV ("" = none); a *_summary.csv next to it gets one row per run')
    return ap


def loop_rows(s: dict, rate: float, label: str = '') -> list[tuple[str, str]]:
    """The table rows of one instrument's loop (``label``: its name, when there are several)."""
    at = f'{label}: ' if label else ''
    return [
        (f'{at}poses sent / replies', f"{s['poses_sent']} / {s['replies']}"),
        (f'{at}pose rate sent', f"{s['send_rate_hz']:.1f} Hz (target {rate:g})"),
        (f'{at}reply rate', f"{s['reply_rate_hz']:.1f} Hz"),
        (f'{at}poses without reply', f"{s['no_reply_pct']:.2f} %"),
        (f'{at}round trip median', f"{s['rtt_median_ms']:.3f} ms"),
        (f'{at}round trip p90', f"{s['rtt_p90_ms']:.3f} ms"),
        (f'{at}round trip p99', f"{s['rtt_p99_ms']:.3f} ms"),
        (f'{at}round trip max', f"{s['rtt_max_ms']:.3f} ms"),
        (f'{at}max |force|', f"{s['max_force_n']:.3f} N (all finite: {s['forces_finite']})"),
        (f'{at}force sent, steady contact', f"|dF| per frame p99 {s['dF_p99_mN']:.2f} mN, max "
                                            f"{s['dF_max_mN']:.1f} mN; {s['reversals']:.0f} one-frame "
                                            f"reversals > 10 mN; E_in min {s['E_in_min_uJ']:.2f} uJ"),
    ]


def main(argv=None) -> int:
    ap = parser()
    args = ap.parse_args(argv)
    if len(instrument_names(args.instruments)) > 1 and args.peer:
        ap.error('several --instruments need sim_node, not --peer')
    s = run(args)
    per = s['per_instrument']
    rows = [
        ('configuration', 'echo_node (no simulation: the floor)' if args.peer else
                          f"{s['model']} ({s['particles']} particles), {s['scheme']}, {s['mode']}, "
                          f"{s['timing']}, haptic {s['haptic_mode']}, cloud {args.particles_rate:g} Hz, step thread "
                          f"{args.step_thread}" + (f", instruments {s['instruments']}" if len(per) > 1 else '')),
        ('numba warm-up + first step', f"{s['compile_s']:.2f} s"),
        ('launch -> ready / first reply', f"{s['launch_to_ready_s']:.2f} / {s['launch_to_first_reply_s']:.2f} s"),
        *(row for name, stats in per.items() for row in loop_rows(stats, args.rate, name)),
        ('step wall time median / p99', f"{s['step_median_ms']:.3f} / {s['step_p99_ms']:.3f} ms"),
        ('node totals', s['sim_totals']),
    ]
    width = max(len(r[0]) for r in rows)
    print(f"sim_node pose -> wrench latency, {args.duration:g} s at {args.rate:g} Hz "
          f"(first {args.skip:g} s left out)")
    for name, value in rows:
        print(f'  {name:<{width}}  {value}')
    if 'csv' in s:
        print(f"  per-pose CSV: {s['csv']}\n  summary CSV:  {s['summary_csv']}")
    return 0


if __name__ == '__main__':
    sys.exit(main())
