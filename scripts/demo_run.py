#!/usr/bin/env python3
"""The demo: the whole node graph on a recorded device session, with live metrics and a report.

Starts, as separate processes from their installed executables (what ``ros2 run`` starts) on a
private ROS_DOMAIN_ID: ``tissue_viz viz_node``, ``sph_tissue_sim sim_node`` and
``haptic_omni_driver omni_driver`` replaying a bundled bag (or playing its script, or the device).
Shows one live line: progress, the tissue's reaction and step time (``tissue/metrics``), and the
pose->force latency and force rate as viz_node measures them (its ``/diagnostics``: this script
reads no 1 kHz topic, which would take CPU from the solver). At the end of the bag (the script;
Ctrl-C for a device) the nodes are stopped (SIGINT, as Ctrl-C) and the closing lines, from viz_node's
report, say what the device got: replies, latency, and the force's smoothness and passivity.

The same choices as ``ros2 launch sph_tissue_sim bringup.launch.py`` (for installs without the
launch packages): backend, bag, model, tool, timing, and one YAML per node.

Usage (``bash scripts/demo.sh`` sets up the workspace and runs this)::

    python scripts/demo_run.py [--backend replay|scripted|openhaptics] [--bag bags/long]
        [--timing timed|lockstep] [--rate 1.0] [--model liver] [--tool sphere|capsule]
        [--driver-params F.yaml] [--sim-params F.yaml] [--viz-params F.yaml]
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import sys
import time
from pathlib import Path

from tissue_common import feel
from tissue_testing import harness
from tissue_testing import system_graph as graph

ROOT = Path(__file__).resolve().parent.parent
#: [s] how often the demo says what it is waiting for
WAIT_TELL = 5.0


def _fmt_line(mon: graph.Monitor) -> tuple[str, int]:
    """The live line from viz_node's latest diagnostics and sim_node's latest metrics (this script
    reads neither 1 kHz topic: it would take the solver's CPU on a 2-core machine); and the poses
    seen so far."""
    d = mon.viz_values()
    lat = d.get('pose to force latency', {}).get('p50 [ms]', 'n/a')
    rate = d.get('omni/force_feedback rate', {}).get('rate [Hz]', 'n/a')
    poses = d.get('omni/pose rate', {}).get('messages', '0')
    m = mon.last_metrics
    force = '-'
    if m is not None:
        force = f'{math.hypot(m.contact_force.x, m.contact_force.y, m.contact_force.z):5.2f} N'
    step = f'{m.step_wall_time * 1e3:.3f} ms' if m is not None else '-'
    return (f'|F| {force}  latency p50 {lat} ms  rate {rate} Hz  step {step}',
            int(poses) if poses.isdigit() else 0)


def feel_line(q: dict) -> str:
    """The live force as the hand gets it (tissue_common.feel), against the targets."""
    missed = feel.misses(q)
    if math.isfinite(q['dF_p99_mN']):
        steady = (f'|dF| per frame in steady contact p99 {q["dF_p99_mN"]:.2f} mN, max '
                  f'{q["dF_max_mN"]:.1f} mN')
    else:   # a touch too short or too starved to hold steady contact for a frame pair
        steady = 'no frames in steady contact'
    return (f'force sent: {steady}; {q["reversals"]} one-frame reversals above '
            f'{feel.REVERSAL * 1e3:g} mN; E_in min {q["E_in_min_uJ"]:.2f} uJ; '
            + ('targets met' if not missed else 'missed: ' + ', '.join(missed)))


def closing_lines(summary_path: Path) -> list[str]:
    """What the graph gave the device, from viz_node's report (``summary.json``): the replies and
    their latency, and what the hand got (:func:`feel_line`)."""
    import json

    try:
        s = json.loads(summary_path.read_text())
    except (OSError, ValueError) as exc:
        return [f'no report summary ({exc})']

    def num(key: str) -> float:   # the report writes a figure it could not measure as null
        v = s.get(key)
        return float(v) if isinstance(v, (int, float)) else math.nan

    def ms(key: str) -> str:
        v = num(key)
        return f'{v * 1e3:.3f} ms' if math.isfinite(v) else 'n/a'

    lines = [f"{s.get('poses', 0)} poses, {s.get('forces', 0)} forces, {s.get('replies_missed', 0)} "
             f"poses without a reply ({num('replies_missed_pct'):.2f} %); pose->force latency median "
             f"{ms('latency_p50_s')}, p99 {ms('latency_p99_s')}"]
    if 'feel_reversals' in s:
        reversals = num('feel_reversals')
        lines.append(feel_line({'dF_p99_mN': num('feel_dF_p99_mN'), 'dF_max_mN': num('feel_dF_max_mN'),
                                'reversals': int(reversals) if math.isfinite(reversals) else 0,
                                'E_in_min_uJ': num('feel_E_in_min_uJ')}))
    return lines


def _wait_telling(proc, pattern: str, timeout: float, t_start: float):
    """``proc.wait_for_output(pattern)``, printing every few seconds how long it has waited and
    the node's last line (a first start compiles for tens of seconds)."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            return proc.wait_for_output(pattern, timeout=min(WAIT_TELL, max(0.0, deadline - time.monotonic())))
        except AssertionError:
            if not proc.alive() or time.monotonic() >= deadline:
                raise
        lines = proc.output().strip().splitlines()
        last = lines[-1].strip().split(']: ', 1)[-1] if lines else '(nothing yet)'   # without the log prefix
        print(f'demo: waiting for {proc.name}, {time.monotonic() - t_start:.0f} s: {last[:160]}', flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--backend', choices=('replay', 'scripted', 'openhaptics'), default='replay',
                    help='omni_driver backend: replay a bag (default), play the scripted session '
                         'once, or the device (until Ctrl-C)')
    ap.add_argument('--bag', type=Path, default=ROOT / 'bags' / 'long', help='bag folder to replay')
    ap.add_argument('--timing', '--mode', dest='mode', choices=('timed', 'live', 'lockstep'),
                    default='timed',
                    help='timed (or live, as the bring-up launch calls it): the recorded 1 kHz '
                         'timing, sim in live mode (default); lockstep: each pose waits for its '
                         'force, sim in lockstep mode (deterministic; replay only)')
    ap.add_argument('--model', default=None, help='sim_node model (liver, block, beam, mesh)')
    ap.add_argument('--tool', default=None, help='sim_node tool_shape (sphere, capsule)')
    for node in ('driver', 'sim', 'viz'):
        ap.add_argument(f'--{node}-params', type=Path, default=None,
                        help=f'a ROS 2 params YAML for the {node} node (the options above override it)')
    ap.add_argument('--rate', type=float, default=1.0, help='timed replay speed factor')
    ap.add_argument('--report-dir', type=Path, default=None,
                    help='report folder (default reports/demo_<date_time>)')
    ap.add_argument('--golden', action='store_true',
                    help='run the sim with the parameters the bag goldens were recorded with '
                         '(bags/golden_sim_params.yaml) instead of its defaults')
    ap.add_argument('--domain', type=int, default=None, help='ROS_DOMAIN_ID (default: a free one)')
    args = ap.parse_args(argv)
    if args.mode == 'live':
        args.mode = 'timed'

    def _terminate(signum, frame):
        raise KeyboardInterrupt  # SIGTERM (e.g. from `timeout`): stop the nodes as Ctrl-C does

    signal.signal(signal.SIGTERM, _terminate)

    from haptic_omni_driver.bag_reader import bag_topics

    if args.mode == 'lockstep' and args.backend != 'replay':
        print('demo: error: --timing lockstep needs --backend replay (a live source cannot wait '
              'for each force)', file=sys.stderr)
        return 2
    for path in (args.driver_params, args.sim_params, args.viz_params):
        if path is not None and not path.is_file():
            print(f'demo: error: no params file {path}', file=sys.stderr)
            return 2
    bag = args.bag.resolve()
    n_total = 0
    if args.backend == 'replay':
        try:
            topics = bag_topics(bag)
        except Exception as exc:  # noqa: BLE001
            print(f'demo: error: {exc}', file=sys.stderr)
            return 1
        n_total = next((t.count for t in topics.values() if t.name.lstrip('/') == 'omni/pose'), 0)
    report_dir = (args.report_dir or ROOT / 'reports' / time.strftime('demo_%Y%m%d_%H%M%S')).resolve()
    env = harness.ros_env(args.domain)
    tty = sys.stdout.isatty() and os.environ.get('CI', '').lower() not in ('1', 'true', 'yes')
    source = (f'bag {bag} ({n_total} poses), replay {args.mode}' if args.backend == 'replay'
              else f'backend {args.backend}')
    print(f'demo: {source}, ROS_DOMAIN_ID {env["ROS_DOMAIN_ID"]}', flush=True)

    sim_mode = 'lockstep' if args.mode == 'lockstep' else 'live'
    title = f'{bag.name} ({args.mode})' if args.backend == 'replay' else args.backend
    viz = graph.viz(report_dir, env=env, params={'report_title': f'Demo: {title}',
                                                 'summary_period': 5.0},
                    params_file=args.viz_params)
    sim_params = {k: v for k, v in (('model', args.model), ('tool_shape', args.tool)) if v}
    sim = graph.sim(sim_mode, env=env, golden=args.golden, params=sim_params,
                    params_file=args.sim_params)
    # pose subscribers to wait for: sim and viz (this script's monitor reads no pose)
    if args.backend == 'replay':
        drv = graph.driver_replay(bag, args.mode, env=env, rate=args.rate, subscribers=2,
                                  params_file=args.driver_params)
    else:
        drv = graph.driver_device(args.backend, env=env, subscribers=2,
                                  params_file=args.driver_params)
    procs = [drv, sim, viz]
    code = 0
    t_start = time.monotonic()
    try:
        viz.start()
        sim.start()
        print('demo: starting viz_node and sim_node (the first start compiles the SPH kernels)',
              flush=True)
        _wait_telling(viz, graph.VIZ_READY, 60, t_start)
        ready = _wait_telling(sim, graph.SIM_READY + r'(model [^\n]*)', 240, t_start)
        print(f'demo: sim_node {ready.group(1)}', flush=True)
        print(f'demo: nodes ready after {time.monotonic() - t_start:.1f} s; replaying', flush=True)
        with graph.Monitor(env, loop=False) as mon:
            drv.start()
            drv.wait_for_output(graph.DRIVER_READY, timeout=60)
            bar = None
            if tty:
                import shutil

                from tqdm import tqdm

                # a pty without a size (0 x 0) makes tqdm hide the bar: give it one
                size = shutil.get_terminal_size((120, 24))
                bar = tqdm(total=n_total or None, unit='pose', ncols=max(size.columns, 100),
                           nrows=max(size.lines, 10), smoothing=0.1, file=sys.stdout)
            last_print, done = 0.0, 0
            while drv.alive():
                time.sleep(0.2)
                line, seen = _fmt_line(mon)
                done = min(seen, n_total) if n_total else seen
                if bar is not None:
                    bar.update(done - bar.n)
                    bar.set_postfix_str(line, refresh=True)
                elif time.monotonic() - last_print >= 5.0:
                    last_print = time.monotonic()
                    pct = f'{100.0 * done / n_total:5.1f} % ' if n_total else ''
                    print(f'demo: {pct}{done}/{n_total or "?"} poses  {line}', flush=True)
            if bar is not None:
                bar.update((n_total or done) - bar.n)
                bar.close()
            if drv.returncode != 0:
                print(f'demo: error: omni_driver exited with {drv.returncode}:\n'
                      f'{drv.output()[-3000:]}', file=sys.stderr)
                code = 1
    except AssertionError as exc:
        print(f'demo: error: {exc}', file=sys.stderr)
        code = 1
    except KeyboardInterrupt:
        print('demo: interrupted', file=sys.stderr)
        code = 130
    finally:
        graph.stop_all(procs, timeout=60)
    import re

    totals = re.search(r'totals: ([^\n]*)', sim.output())
    if totals:
        print(f'demo: sim_node {totals.group(1)}', flush=True)
    finished = re.search(r'(?:replay|script) finished: ([^\n]*)', drv.output())
    if finished:
        print(f'demo: omni_driver {finished.group(0)}', flush=True)
    m = re.search(r'report written: (\S+)', viz.output())
    if m:
        index = Path(m.group(1))
        folder = index.parent
        pngs = sorted(p.name for p in folder.glob('*.png'))
        for line in closing_lines(folder / 'summary.json'):
            print(f'demo: {line}', flush=True)
        print(f'demo: report folder: {folder}', flush=True)
        print(f'demo: report: {index}' + (f' (plots: {", ".join(pngs)})' if pngs else ''),
              flush=True)
    else:
        print(f'demo: error: viz_node wrote no report; its output:\n{viz.output()[-3000:]}',
              file=sys.stderr)
        code = code or 1
    print(f'demo: done in {time.monotonic() - t_start:.1f} s', flush=True)
    return code


if __name__ == '__main__':
    sys.exit(main())
