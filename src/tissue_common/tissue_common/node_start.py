"""A node's start-up and shutdown, the same for every executable of the simulator.

- :func:`init_rclpy`: ``rclpy.init`` raises ``RCLError`` (a traceback) for a ROS argument it cannot
  parse, e.g. ``--ros-args -p model:=`` (an override without a value); here that is one ``[FATAL]``
  line naming the argument, and ``main`` exits with :data:`EXIT_PARAMS`.
- :func:`build_node`: a node whose construction refuses its parameters or inputs logs one
  ``[FATAL]`` line and ``main`` exits with that refusal's code.
- :func:`stop_on_signals`: Ctrl-C and SIGTERM set a flag instead of running rclpy's handlers.
- :func:`spin_until_stopped`: the spin loop every node runs until that flag (or its own end).
"""

from __future__ import annotations

import re
import signal
import threading

#: exit code of invalid parameters or command-line arguments (documented in the READMEs)
EXIT_PARAMS = 2

#: what rcl calls the argument it could not parse -> the form it expects
_EXPECTED = {
    'parameter override rule': '-p name:=value, with a value',
    'remap rule': '-r from:=to',
    'log level': '--log-level [logger:=]severity',
    'params file': '--params-file <readable YAML file>',
}


def init_rclpy(args, executable: str) -> bool:
    """``rclpy.init(args=args)``; False, after one fatal log line, if rcl refuses the arguments."""
    import rclpy
    import rclpy.logging
    from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

    try:
        rclpy.init(args=args)
    except _rclpy.RCLError as exc:
        rclpy.logging.get_logger(executable).fatal(f'error: {describe_rcl_error(str(exc))}')
        return False
    return True


def describe_rcl_error(text: str) -> str:
    """One sentence for an rcl initialisation error, naming the argument it could not parse."""
    match = re.search(r"Couldn't parse (.+?): '(.*?)'\.", text)
    if match:
        kind, arg = match.groups()
        hint = _EXPECTED.get(kind)
        return (f'invalid command-line argument {arg!r}: cannot parse it as a {kind}'
                + (f' (expected {hint})' if hint else ''))
    # anything else: rcl's own words, without the C source locations
    text = re.sub(r'^failed to initialize rcl: ', '', text)
    return 'invalid command-line arguments: ' + re.sub(r'(, at /\S+:\d+)+$', '', text)


def stop_on_signals() -> threading.Event:
    """Replace rclpy's SIGINT/SIGTERM handlers by ones that only set the returned event.

    rclpy's own handlers shut the context down from another thread, so a callback running at that
    moment fails (a publish raises ``RCLError``), and a ``KeyboardInterrupt`` raised inside a
    callback reaches ``spin_once`` as a ``RuntimeError`` from the EventsExecutor's C++; either made
    a node exit 1 on Ctrl-C. With a flag the spin loop ends between callbacks and the node shuts
    down in order. Call it once the node is built (Ctrl-C still interrupts a slow start-up).
    """
    from rclpy.signals import uninstall_signal_handlers

    stop = threading.Event()
    uninstall_signal_handlers()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def build_node(factory, executable: str, refusals: dict):
    """``factory()``, or ``(None, code)`` after one ``[FATAL]`` line when it raises an exception
    listed in ``refusals`` (exception class -> (what failed, exit code)); returns ``(node, None)``."""
    import rclpy.logging

    try:
        return factory(), None
    except tuple(refusals) as exc:
        for cls, (what, code) in refusals.items():
            if isinstance(exc, cls):
                rclpy.logging.get_logger(executable).fatal(f'{what}: {exc}')
                return None, code
        raise


def spin_until_stopped(node, stop: threading.Event, done: threading.Event | None = None,
                       on_spinning=None) -> None:
    """Spin ``node`` on an ``EventsExecutor`` until ``stop`` (:func:`stop_on_signals`) or ``done``
    is set or rclpy shuts down; ``on_spinning()`` runs once the node is on the executor.

    ``spin_once`` in a loop, not ``spin()``: ``EventsExecutor.spin()`` of these rclpy wheels does
    not return on Ctrl-C (it busy-waits in C++); the default ``SingleThreadedExecutor`` cannot keep
    up with 1 kHz poses.
    """
    import rclpy
    from rclpy.experimental import EventsExecutor

    executor = EventsExecutor()
    executor.add_node(node)
    if on_spinning is not None:
        on_spinning()
    while rclpy.ok() and not stop.is_set() and not (done is not None and done.is_set()):
        executor.spin_once(timeout_sec=0.1)
