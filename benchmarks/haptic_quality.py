#!/usr/bin/env python3
"""What the hand feels: smoothness and passivity of the rendered force on the bundled sessions.

Replays each bundled bag's poses in order, in the bags' own (lockstep) set-up (``bags/
golden_sim_params.yaml``: the 2000-particle block, tlsph, local mode), through the core alone (no
ROS), two ways:

* ``direct``: one solver step per pose at the device's position; the force is the solver's
  reaction (what ``sim_node`` sends today);
* ``renderer``: :class:`sph_tissue_sim.haptics.renderer.HapticRenderer` answers each pose (velocity
  estimator, virtual coupling, passivity controller) and the solver steps at the proxy every
  ``--every`` poses, refreshing the contact model (every pose by default: the lockstep schedule);
* ``live D`` (``--delays``): the renderer on the live schedule made repeatable: the solver takes
  the newest proxy whenever it is free and its reaction arrives D poses later, as from a solver
  thread whose steps take D ms (what the live graph does, without its timing noise);
* ``rtf R`` (``--rtfs``): the same with a solver at real-time factor R: a job of ``dt`` pose time
  (at most ``max_dt``) arrives ``dt / R`` later.

Per bag and way (measures defined once in :mod:`tissue_common.feel`), in steady contact (more than
20 frames after contact onset): per-frame |dF| p99 and max, the one-frame reversals above 10 mN
(anywhere), the median force change on frames where the device moved by exactly one encoder tick as a share
of the force (``tick %``; ``still``: only the ticks that follow a frame without motion, the
quantisation alone, where inside a motion the change is also the stiffness times the speed;
``smooth``: the tick share of the force's centred 11-frame mean, what a force without any
quantisation artefact would show along the same motion: the floor of ``tick %``), the
ripple (|F| minus its 21-frame centred mean, rms), and E_in (the energy the hand
put in with each force held until the next pose) minimum and final. Also the quasi-static force at
2, 4 and 6 mm on the block, renderer against direct, and direct at the depth where the renderer's
proxy rests (the coupling in series with the tissue). Writes ``haptic_quality.csv`` and
``haptic_quality.png`` (the press session's force, both ways) to ``--out``.

``--live`` adds the live half: ``sim_node`` started as ``ros2 run`` would, fed poses at 1 kHz along a
pressing path (``sim_latency.py``), on the 3670-, 50k- and 100k-particle livers, multirate and
direct, idle and beside one busy process (``python3 -c 'while True: pass'``): pose-to-force latency
p50/p99, the share of poses answered, and the solver's step rate; under each load it first times
``echo_node.py`` (the same transport answering at once, no simulation) with the same probe: the
floor of the round trip on this machine. Writes ``haptic_quality_live.csv``. ``--live-repeats R``
runs the live list R rounds (interleaved) and summarises each configuration's p99 over them
(median, lowest, highest; ``haptic_quality_live_summary.csv``): one run's p99 is its slowest 1 %,
which on a shared VM moves by a factor of two or more between runs of the same code.

Usage: ``python benchmarks/haptic_quality.py [--bags press,pull,...] [--every K] [--live] [--out DIR]``
``[--live-only] [--live-duration S] [--live-repeats R] [--live-modes multirate,direct]``
``[--coupling-stiffness K_c]`` (the coupling trades the quasi-static force against smoothness and
passivity: benchmarks/README.md)
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from pathlib import Path

import numpy as np
import yaml

from haptic_omni_driver.bag_reader import read_bag
from sph_tissue_sim import params as sim_params
from sph_tissue_sim.haptics.multirate import MultiRate
from sph_tissue_sim.haptics.renderer import HapticRenderer, RendererConfig
from sph_tissue_sim.runner import Pose, Runner, make_mapping, make_solver
from tissue_common.feel import TICK, feel
from tissue_common.force import clamp_norm
from tissue_common.stamps import stamp_to_ns
from tissue_testing import system_graph as graph

ROOT = Path(__file__).resolve().parents[1]
BAGS = ('press', 'pull', 'sweep', 'poke', 'long', 'grasp', 'bimanual', 'cut', 'needle')
#: frames after a blade broke bonds that are its crack step (the force meant to drop), left out of the
#: steady |dF| of a cutting session
STEP_FRAMES = 3
#: and after a needle punctured: the renderer lowers the drop (0.67 to 0.33 N on bags/needle) over
#: about 10 frames, its passivity bounding each frame's release of stored energy
PUNCTURE_FRAMES = 10
COLUMNS = ('bag', 'way', 'frames', 'steady_frames', 'dF_p99_mN', 'dF_max_mN', 'reversals', 'tick_change_pct',
           'still_tick_change_pct', 'smooth_tick_change_pct', 'ticks', 'ripple_mN', 'E_in_min_uJ', 'E_in_final_uJ', 'peak_N')


def golden_params() -> dict:
    """sim_node's parameters as the bundled bags were recorded with."""
    p = {name: spec[0] for name, spec in sim_params.SIM_PARAMS.items()}
    text = (ROOT / 'bags' / 'golden_sim_params.yaml').read_text()
    p.update(yaml.safe_load(text)['/**']['ros__parameters'])
    p['timing_mode'] = 'lockstep'   # as make_bags records them: repeatable bit for bit
    return p


def bag_poses(name: str, instrument: str = '') -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(stamps [ns] (M,), device positions [m] (M, 3), jaw closed at each pose (M,) bool) of one
    instrument of a bundled bag, in order. The jaw is closed where the session's ``grasp_input``
    button (the golden parameters with ``system_graph.BAG_SIM_PARAMS``) was down in the newest
    state stamped before the pose, as ``sim_node`` applies it in lockstep."""
    stamps, pos, changes = [], [], []
    button = {**golden_params(), **graph.BAG_SIM_PARAMS.get(name, {})}['grasp_input']
    ns = f'/{instrument}' if instrument else ''
    for topic, _, _, msg in read_bag(ROOT / 'bags' / name, [f'{ns}/omni/pose', f'{ns}/omni/state']):
        if topic.endswith('/omni/state'):
            if button:
                changes.append((stamp_to_ns(msg.header.stamp), bool(getattr(msg, button))))
            continue
        stamps.append(stamp_to_ns(msg.header.stamp))
        q = msg.pose.position
        pos.append((q.x, q.y, q.z))
    stamps = np.array(stamps)
    closed = np.zeros(len(stamps), dtype=bool)
    # the states a bag holds: its changes (stamped with their poses) and the driver's periodic ones
    # (its wall clock, far from the poses' stamps): only those within the session count
    for stamp, down in sorted(c for c in changes if stamps[0] <= c[0] <= stamps[-1]):
        closed[stamps > stamp] = down
    return stamps, np.array(pos), closed


def replay(p: dict, stamps: np.ndarray, device: np.ndarray, way: str, every: int = 1,
           config: RendererConfig | None = None, delay: int = 0,
           rtf: float = 0.0, closed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Tissue-frame (positions, forces) per pose, ``way`` 'direct' or 'renderer'.

    The renderer's schedule: by default the lockstep one of ``sim_node`` (the solver steps at the
    proxy after every ``every``-th pose and its reaction serves the next pose). The live one, made
    repeatable: the solver takes a job (the newest proxy and the pose time since its last job, at
    most ``max_dt``) whenever it is free, and its reaction
    reaches the renderer ``delay`` poses later (``delay`` > 0), or, with ``rtf`` > 0, as from a
    solver at that real-time factor: a job of ``dt`` pose time takes ``dt / rtf``. ``closed``: the
    jaw per pose (:func:`bag_poses`), applied before the solver's next step as ``sim_node`` does."""
    solver = make_solver(sim_params.build_model(p), sim_params.build_material(p),
                         sim_params.build_config(p), p['nominal_dt'])
    mapping = make_mapping(p, solver)
    live = bool(delay or rtf)
    handoff = MultiRate(HapticRenderer(config or RendererConfig(force_limit=p['force_limit'])),
                        0 if live else every, p['max_dt'])
    xs = np.array([mapping.to_tissue(d) for d in device])
    dts = np.r_[p['nominal_dt'], np.diff(stamps) * 1e-9]
    forces = np.empty_like(xs)
    pending, due = None, 0
    gripping = False

    def jaw(k: int) -> None:
        nonlocal gripping
        if closed is not None and closed[k] != gripping:
            gripping = bool(closed[k])
            solver.grasp() if gripping else solver.release()

    for k, (x, dt) in enumerate(zip(xs, dts)):
        jaw(k)
        if way == 'direct':
            forces[k] = clamp_norm(solver.step(x, dt).force_raw, p['force_limit'])[0]
            continue
        forces[k] = handoff.answer(x, dt).force
        if not live:
            if handoff.due():
                job = handoff.take()
                handoff.refresh(job, solver.step(job.point, job.dt))
            continue
        if pending is not None and k >= due:
            handoff.refresh(*pending)
            pending = None
        if pending is None:
            job = handoff.take()
            if job is not None:
                late = delay or max(1, math.ceil(job.dt / (p['nominal_dt'] * rtf) - 1e-9))
                pending, due = (job, solver.step(job.point, job.dt)), k + late
    return xs, forces


def bag_orientations(name: str, instrument: str = '') -> np.ndarray:
    """(M, 4) the stylus orientation (x, y, z, w) of each pose of one instrument of a bundled bag."""
    ns = f'/{instrument}' if instrument else ''
    return np.array([(m.pose.orientation.x, m.pose.orientation.y, m.pose.orientation.z, m.pose.orientation.w)
                     for *_, m in read_bag(ROOT / 'bags' / name, [f'{ns}/omni/pose'])])


def replay_instruments(p: dict, name: str) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """A bag through ``sim_node``'s own loop (its :class:`Runner`, lockstep, in rounds of one pose of
    each instrument, with the bag's parameters, orientations and jaw changes): per instrument,
    (device positions, the forces sent, both in the device frame, and its steps: the bonds its blade
    broke, or 1 where its needle punctured) per pose."""
    # stepping in the caller's thread: the same forces as sim_node's stepping thread in lockstep
    q = {**p, **graph.BAG_SIM_PARAMS.get(name, {}), 'step_thread': False}
    names = graph.bag_instruments(name)
    model = sim_params.build_model(q)
    solver = make_solver(model, sim_params.build_material(q), sim_params.build_config(q), q['nominal_dt'],
                         instruments=len(names), tools=sim_params.instrument_tools(q))
    sent: list[dict] = [{} for _ in names]
    steps: list[dict] = [{} for _ in names]

    def metrics(stamp, res, solver, status, k: int = 0) -> None:
        cutter, needle = solver.cutters.get(k), solver.needles.get(k)
        steps[k][stamp] = (cutter.last_cut if cutter is not None
                           else int(needle.punctured) if needle is not None else 0)

    runner = Runner(q, model, solver, lambda stamp, frame, force, k=0: sent[k].__setitem__(stamp, np.array(force)),
                    metrics, lambda _: None, lambda *_: None)
    streams = [bag_poses(name, instrument) for instrument in names]
    turns = [bag_orientations(name, instrument) for instrument in names]
    for j in range(len(streams[0][0])):
        for k, (stamps, device, closed) in enumerate(streams):
            if j and closed[j] != closed[j - 1]:       # the change came with the previous pose
                runner.on_grasp(k, bool(closed[j]), int(stamps[j - 1]))
            st = int(stamps[j])
            runner.on_pose(Pose(st, st, q['device_frame'], tuple(device[j]), tuple(turns[k][j])), k)
    runner.shutdown()
    return {instrument: (device, np.array([sent[k][int(s)] for s in stamps]),
                         np.array([steps[k].get(int(s), 0) for s in stamps]))
            for k, (instrument, (stamps, device, _)) in enumerate(zip(names, streams))}


def step_frames(steps: np.ndarray, frames: int = STEP_FRAMES) -> np.ndarray:
    """(M,) bool: the poses at and up to ``frames`` after one at which a blade broke bonds or a
    needle punctured."""
    out = np.zeros(len(steps), dtype=bool)
    for k in np.flatnonzero(steps):
        out[k:k + frames + 1] = True
    return out


def quality(xs: np.ndarray, forces: np.ndarray, skip: np.ndarray | None = None) -> dict:
    """The smoothness and passivity measures of one replay (:func:`tissue_common.feel.feel`; ``skip``:
    frames left out of the steady ones)."""
    return feel(xs, forces, skip=skip)


def stiff_params(p: dict, factor: float = 10.0) -> dict:
    """The same set-up on a tissue ``factor`` times stiffer (E; same Poisson ratio, viscosities
    and density)."""
    m = sim_params.build_material(p)
    return {**p, 'material': 'custom', 'E': m.E * factor, 'nu': m.nu, 'eta_shear': m.eta_shear,
            'eta_bulk': m.eta_bulk, 'rho': m.rho}


def quasi_static(p: dict, depths=(0.002, 0.004, 0.006), hold: int = 1500,
                 config: RendererConfig | None = None) -> list[tuple]:
    """Force after a slow press to each depth and a hold: direct, through the renderer, and direct
    at the depth the renderer's proxy holds (``F / K_c`` short of the device: the coupling in series
    with the tissue)."""
    def press(depth: float, way: str) -> float:
        ramp = np.r_[np.linspace(0.0, depth, 2000), np.full(hold, depth)]
        device = np.zeros((ramp.size, 3))
        device[:, 1] = -ramp                      # device y (up) is tissue z in the default mapping
        stamps = np.arange(ramp.size) * 1_000_000
        return float(np.linalg.norm(replay(p, stamps, device, way, config=config)[1][-1]))

    coupling = (config or RendererConfig()).coupling_stiffness
    out = []
    for depth in depths:
        rendered = press(depth, 'renderer')
        out.append((depth, press(depth, 'direct'), rendered, press(depth - rendered / coupling, 'direct')))
    return out


LIVE_SIZES = (3670, 50000, 100000)
LIVE_COLUMNS = ('round', 'particles', 'haptic_mode', 'load', 'poses_sent', 'replies', 'answered_pct',
                'rtt_median_ms', 'rtt_p99_ms', 'rtt_max_ms', 'solver_rate_hz', 'max_force_n',
                'dF_p99_mN', 'dF_max_mN', 'reversals', 'E_in_min_uJ')


def live(sizes=LIVE_SIZES, modes=('multirate', 'direct'), duration: float = 10.0,
         repeats: int = 1) -> list[dict]:
    """The live graph's answers at 1 kHz: each size x mode x (idle, one busy process), and under
    each load first the floor: ``echo_node.py`` (same transport, no simulation, particles 0).

    With ``repeats`` > 1 the whole list runs that many rounds, one configuration after the other in
    each round, so that a slow spell of the shared machine hits every configuration alike (a run's
    p99 is its slowest 1 %, which moves from run to run on a shared VM)."""
    import subprocess

    sys.path.insert(0, str(ROOT / 'benchmarks'))
    import sim_latency

    runs = [(load, 0, 'echo') for load in ('idle', 'busy')]
    runs += [(load, n, mode) for n in sizes for mode in modes for load in ('idle', 'busy')]
    rows = []
    for rnd in range(1, repeats + 1):
        for load, n, mode in runs:
            busy = (subprocess.Popen([sys.executable, '-c', 'while True: pass'])
                    if load == 'busy' else None)
            try:
                argv = ['--peer'] if mode == 'echo' else ['--n-particles', str(n), '--haptic-mode', mode]
                s = sim_latency.run(sim_latency.parser().parse_args(
                    [*argv, '--duration', str(duration), '--csv', '']))
            finally:
                if busy is not None:
                    busy.kill()
                    busy.wait()
            row = {k: s.get(k) for k in LIVE_COLUMNS if k in s}
            row.update(round=rnd, particles=max(s['particles'], 0), haptic_mode=mode, load=load,
                       answered_pct=100.0 - s['no_reply_pct'])
            rows.append(row)
            print(f'{rnd:>5} {row["particles"]:>7} {mode:9} {load:5} {row["answered_pct"]:8.2f} '
                  f'{row["rtt_median_ms"]:7.3f} {row["rtt_p99_ms"]:7.3f} {row["rtt_max_ms"]:7.2f} '
                  f'{row["solver_rate_hz"]:8.1f} {row["max_force_n"]:6.3f} {row["dF_p99_mN"]:6.2f} '
                  f'{row["dF_max_mN"]:6.1f} {row["reversals"]:4.0f} {row["E_in_min_uJ"]:8.2f}',
                  flush=True)
    return rows


def live_summary(rows: list[dict]) -> list[dict]:
    """Per configuration over its rounds: the median, lowest and highest p99 and the lowest share
    of poses answered."""
    out = []
    for key in dict.fromkeys((r['particles'], r['haptic_mode'], r['load']) for r in rows):
        runs = [r for r in rows if (r['particles'], r['haptic_mode'], r['load']) == key]
        p99 = np.array([r['rtt_p99_ms'] for r in runs])
        out.append({'particles': key[0], 'haptic_mode': key[1], 'load': key[2], 'runs': len(runs),
                    'p99_median_ms': float(np.median(p99)), 'p99_min_ms': float(p99.min()),
                    'p99_max_ms': float(p99.max()),
                    'answered_min_pct': min(r['answered_pct'] for r in runs)})
    return out


def plot(path: Path, press: dict) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(9, 4))
    for way, colour in (('direct', '#d62728'), ('renderer', '#1f77b4')):
        xs, forces = press[way]
        t = np.arange(forces.shape[0]) * 1e-3
        ax.plot(t, np.linalg.norm(forces, axis=1), lw=0.7, color=colour, label=way)
    ax.set_xlabel('time [s]')
    ax.set_ylabel('|F| [N]')
    ax.set_title('press session (lockstep): force sent to the device')
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--bags', default=','.join(BAGS))
    ap.add_argument('--every', type=int, default=1, help='solver steps every K poses (renderer)')
    ap.add_argument('--delays', default='8,16', help='also the renderer on the live schedule, the '
                    'solver\'s reaction arriving D poses after its job, for each D (empty: none)')
    ap.add_argument('--rtfs', default='0.5,0.2', help='also the live schedule of a solver at each of '
                    'these real-time factors (empty: none)')
    ap.add_argument('--live', action='store_true', help='also the live half (sim_node at 1 kHz, '
                    '3670/50k/100k livers, idle and busy; about 15 minutes)')
    ap.add_argument('--live-only', action='store_true', help='only the live half')
    ap.add_argument('--live-duration', type=float, default=10.0, help='[s] of 1 kHz poses per live run')
    ap.add_argument('--live-repeats', type=int, default=1, help='rounds of the live runs (a summary '
                    'of each configuration\'s p99 over the rounds follows)')
    ap.add_argument('--live-modes', default='multirate,direct', help='haptic modes of the live half')
    ap.add_argument('--coupling-stiffness', type=float, default=RendererConfig.coupling_stiffness,
                    help='[N/m] the renderer\'s K_c (default: the renderer\'s)')
    ap.add_argument('--out', type=Path, default=ROOT / 'benchmarks' / 'results')
    args = ap.parse_args(argv)
    if args.live or args.live_only:
        args.out.mkdir(parents=True, exist_ok=True)
        print(f'live, 1 kHz poses for {args.live_duration:g} s (first second left out):')
        print(f'{"round":>5} {"N":>7} {"mode":9} {"load":5} {"answered":>8} {"p50":>7} {"p99":>7} '
              f'{"max":>7} {"solver":>8} {"|F|max":>6} {"dFp99":>6} {"dFmax":>6} {"rev":>4} '
              f'{"E_in min":>8}   (%, ms, ms, ms, Hz, N, mN, mN, one-frame reversals > 10 mN, uJ; '
              f'the forces sent along the pressing path)')
        rows = live(modes=tuple(args.live_modes.split(',')), duration=args.live_duration,
                    repeats=max(1, args.live_repeats))
        with open(args.out / 'haptic_quality_live.csv', 'w', newline='') as fh:
            w = csv.DictWriter(fh, fieldnames=LIVE_COLUMNS)
            w.writeheader()
            w.writerows(rows)
        if args.live_repeats > 1:
            print(f'p99 over {args.live_repeats} rounds (ms: median [lowest, highest]; answered: '
                  f'lowest %):')
            summary = live_summary(rows)
            with open(args.out / 'haptic_quality_live_summary.csv', 'w', newline='') as fh:
                w = csv.DictWriter(fh, fieldnames=list(summary[0]))
                w.writeheader()
                w.writerows(summary)
            for r in summary:
                print(f'{r["particles"]:>7} {r["haptic_mode"]:9} {r["load"]:5} {r["p99_median_ms"]:7.3f} '
                      f'[{r["p99_min_ms"]:.3f}, {r["p99_max_ms"]:.3f}] {r["answered_min_pct"]:8.2f}')
        if args.live_only:
            return 0
    p = golden_params()
    config = RendererConfig(force_limit=p['force_limit'], coupling_stiffness=args.coupling_stiffness)
    args.out.mkdir(parents=True, exist_ok=True)
    rows, press = [], {}
    delays = [int(d) for d in args.delays.split(',') if d]
    rtfs = [float(r) for r in args.rtfs.split(',') if r]
    print(f'{"bag":6} {"way":9} {"dF p99":>7} {"dF max":>7} {"rev":>4} {"tick %":>6} {"still":>6} '
          f'{"smooth":>6} {"ripple":>6} {"E_in min":>9} {"E_in end":>9} {"peak":>6}   (mN, mN, '
          f'one-frame reversals > 10 mN, %, %, %, mN, uJ, uJ, N)')

    def row(bag: str, way: str, q: dict) -> None:
        rows.append({'bag': bag, 'way': way, **q})
        print(f'{bag:6} {way:9} {q["dF_p99_mN"]:7.1f} {q["dF_max_mN"]:7.1f} {q["reversals"]:4d} '
              f'{q["tick_change_pct"]:6.2f} {q["still_tick_change_pct"]:6.2f} '
              f'{q["smooth_tick_change_pct"]:6.2f} {q["ripple_mN"]:6.2f} '
              f'{q["E_in_min_uJ"]:9.2f} {q["E_in_final_uJ"]:9.1f} {q["peak_N"]:6.3f}', flush=True)

    for name in args.bags.split(','):
        if len(graph.bag_instruments(name)) > 1 or 'tool_shape' in graph.BAG_SIM_PARAMS.get(name, {}):
            # sim_node's loop itself (its answers are the bag's golden forces): each device's feel,
            # and a blade's or a needle's outside its steps
            for instrument, (device, forces, steps) in replay_instruments(p, name).items():
                gold = np.array([(m.wrench.force.x, m.wrench.force.y, m.wrench.force.z) for *_, m in
                                 read_bag(ROOT / 'bags' / name, [f'{"/" + instrument if instrument else ""}'
                                                                 f'/omni/force_feedback'])])
                label = f'{name} {instrument}'.strip()
                row(label, 'renderer', quality(device, forces))
                if steps.any():
                    frames = (PUNCTURE_FRAMES if graph.BAG_SIM_PARAMS.get(name, {}).get('tool_shape') == 'needle'
                              else STEP_FRAMES)
                    row(label, 'no steps', quality(device, forces, step_frames(steps, frames)))
                    print(f'  {label}: bonds broken or a puncture at {np.count_nonzero(steps)} poses '
                          f'({int(steps.sum())} in all); "no steps" leaves those and the {frames} after '
                          f'each out')
                print(f'  {label}: the forces sent differ from the golden ones by at most '
                      f'{np.abs(forces - gold).max():.1e} N')
            continue
        stamps, device, closed = bag_poses(name)
        for way in ('direct', 'renderer'):
            xs, forces = replay(p, stamps, device, way, args.every, config, closed=closed)
            if name == 'press':
                press[way] = (xs, forces)
            row(name, way, quality(xs, forces))
        for d in delays:
            row(name, f'live {d}', quality(*replay(p, stamps, device, 'renderer', config=config, delay=d,
                                                   closed=closed)))
        for r in rtfs:
            row(name, f'rtf {r:g}', quality(*replay(p, stamps, device, 'renderer', config=config, rtf=r,
                                                   closed=closed)))
    stamps, device, _ = bag_poses('poke')
    for way in ('direct', 'renderer'):
        row('poke E x10', way, quality(*replay(stiff_params(p), stamps, device, way, config=config)))
    print('quasi-static force after a slow press and 1.5 s hold (block, top centre); last: direct at '
          'the depth of the proxy (F / K_c short of the device):')
    for depth, direct, rendered, at_proxy in quasi_static(p, config=config):
        print(f'  {depth * 1e3:.0f} mm: direct {direct:.4f} N, renderer {rendered:.4f} N '
              f'({(rendered / direct - 1) * 100:+.1f} %), direct at the proxy {at_proxy:.4f} N '
              f'({(at_proxy / direct - 1) * 100:+.1f} %)')
    with open(args.out / 'haptic_quality.csv', 'w', newline='') as fh:
        w = csv.DictWriter(fh, fieldnames=COLUMNS)
        w.writeheader()
        w.writerows(rows)
    if {'direct', 'renderer'} <= set(press):
        plot(args.out / 'haptic_quality.png', press)
    print(f'wrote {args.out / "haptic_quality.csv"}' + (', .png' if press else ''))
    return 0


if __name__ == '__main__':
    sys.exit(main())
