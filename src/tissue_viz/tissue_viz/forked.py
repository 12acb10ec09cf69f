"""Independent jobs shared between the calling process and forked children (no rclpy).

A report is drawn while viz_node stops, and ``ros2 launch`` escalates to SIGTERM 5 s after SIGINT:
matplotlib holds the GIL, so only processes draw two plots at once. Children are forked (they
inherit the imported matplotlib and the data, nothing is pickled), which is only safe where no
other thread can hold a lock a job needs: viz_node forks after destroying its node (that stops
the DDS threads), ``tissue_report`` has no other thread. A child that dies only costs time: the
jobs it did not report run again in the caller.
"""

from __future__ import annotations

import ctypes
import gc
import json
import os
import signal
import sys
from typing import Callable

_PR_SET_PDEATHSIG = 1


def run(jobs: list[Callable[[], dict]], processes: int = 1) -> dict:
    """Run every job once and return the union of their results.

    Jobs are handed out in their order to whichever process is free (a pipe holds one byte per
    job); a job returns a JSON-serializable dict. With ``processes`` > 1 the caller forks
    ``processes - 1`` children and works alongside them; without ``os.fork``, or when forking
    fails, the caller runs them all.
    """
    if len(jobs) > 255:
        raise ValueError(f'at most 255 jobs, got {len(jobs)}')
    children = []
    if processes > 1 and len(jobs) > 1 and hasattr(os, 'fork'):
        queue_r, queue_w = os.pipe()
        os.write(queue_w, bytes(range(len(jobs))))
        os.close(queue_w)
        children = _fork(jobs, queue_r, min(processes, len(jobs)) - 1)
        try:
            done = _work(jobs, queue_r)
        finally:
            os.close(queue_r)
            reported = _collect(children)
        done.update(reported)
    else:
        done = {k: jobs[k]() for k in range(len(jobs))}
    out: dict = {}
    for k, job in enumerate(jobs):
        out.update(done[k] if k in done else job())
    return out


def _collect(children: list[tuple[int, int]]) -> dict[int, dict]:
    """Wait for the children; the results they reported."""
    done = {}
    for pid, result_r in children:
        raw = _read_all(result_r)
        os.close(result_r)
        os.waitpid(pid, 0)
        try:
            done.update({int(k): v for k, v in json.loads(raw).items()})
        except ValueError:      # it died before reporting: its jobs run again in the caller
            pass
    return done


def _fork(jobs, queue_r: int, count: int) -> list[tuple[int, int]]:
    """Start ``count`` children working on ``queue_r``; (pid, read end of its result) each."""
    children = []
    for stream in (sys.stdout, sys.stderr):     # or a child's exit would write it again
        try:
            stream.flush()
        except (AttributeError, OSError, ValueError):
            pass
    # Objects the children never free stay out of their garbage collector: fewer pages copied.
    gc.freeze()
    try:
        for _ in range(count):
            result_r, result_w = os.pipe()
            try:
                pid = os.fork()
            except OSError:
                os.close(result_r)
                os.close(result_w)
                break
            if pid == 0:
                _child(jobs, queue_r, result_r, result_w)
            os.close(result_w)
            children.append((pid, result_r))
    finally:
        gc.unfreeze()
    return children


def _child(jobs, queue_r: int, result_r: int, result_w: int) -> None:
    """Work on the queue, write the results, and leave without running the parent's exit code."""
    code = 1
    try:
        os.close(result_r)
        try:    # die with the parent (Linux): a killed node leaves no drawing process behind
            ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
        except (OSError, AttributeError):
            pass
        payload = json.dumps(_work(jobs, queue_r)).encode()
        while payload:
            payload = payload[os.write(result_w, payload):]
        code = 0
    finally:
        os._exit(code)


def _work(jobs, queue_r: int) -> dict[int, dict]:
    done = {}
    while True:
        claimed = os.read(queue_r, 1)
        if not claimed:
            return done
        done[claimed[0]] = jobs[claimed[0]]()


def _read_all(fd: int) -> bytes:
    chunks = []
    while True:
        chunk = os.read(fd, 65536)
        if not chunk:
            return b''.join(chunks)
        chunks.append(chunk)
