"""Ctrl-C and SIGTERM handling for nodes spun by rclpy's EventsExecutor."""

from __future__ import annotations

import signal
import threading

from rclpy.signals import uninstall_signal_handlers


def stop_on_signals() -> threading.Event:
    """Replace rclpy's SIGINT/SIGTERM handlers by ones that only set the returned event.

    rclpy's own handlers shut the context down from another thread, so a callback running at that
    moment fails (a publish raises ``RCLError``), and a ``KeyboardInterrupt`` raised inside a
    callback reaches ``spin_once`` as a ``RuntimeError`` from the executor's C++; either made a
    node exit 1 on Ctrl-C. With a flag the spin loop ends between callbacks and the node shuts
    down in order. Call it once the node is built (Ctrl-C still interrupts a slow start-up).
    """
    stop = threading.Event()
    uninstall_signal_handlers()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop
