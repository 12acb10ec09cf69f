"""Whether a process's DDS transport can stall it when a peer dies (no rclpy).

Fast DDS (the default RMW of ROS 2 Jazzy) sends to processes on the same host through shared memory
by default, and always with ``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` (the RMW then adds it
itself, whatever ``FASTDDS_BUILTIN_TRANSPORTS`` says). When a peer is killed, a ``publish()``
towards it can block for whole seconds (measured: stalls of 1 to 4 s starting at the kill, in 8 of
about 100 kills with a core kept busy), and rclpy holds the GIL while it blocks, so every
thread of the publishing process stops: in the driver, the servo loop with its watchdog, i.e. the
device keeps its last force for that long. With UDP only (``FASTDDS_BUILTIN_TRANSPORTS=UDPv4``,
another discovery range) no such stall was seen in 28 kills, and the round-trip latency is the same
(``benchmarks/sim_latency.py --peer``), so ``scripts/env.sh`` selects it.
"""

from __future__ import annotations

from collections.abc import Mapping

#: the transport ``scripts/env.sh`` selects (``FASTDDS_BUILTIN_TRANSPORTS``)
SAFE_TRANSPORTS = 'UDPv4'

#: Fast DDS builtin transport sets that include shared memory
_WITH_SHM = {'DEFAULT', 'DEFAULTV6', 'SHM', 'LARGE_DATA', 'LARGE_DATAV6'}
_FASTDDS_RMWS = {'rmw_fastrtps_cpp', 'rmw_fastrtps_dynamic_cpp'}
_PROFILE_VARS = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')


def shared_memory_warning(environ: Mapping[str, str]) -> str | None:
    """A warning when this environment gives the process Fast DDS's shared-memory transport.

    None for another RMW, for builtin transports without shared memory, and when an XML profile
    file is set without ``FASTDDS_BUILTIN_TRANSPORTS`` (the profile then chooses the transports).
    """
    rmw = environ.get('RMW_IMPLEMENTATION') or 'rmw_fastrtps_cpp'
    if rmw not in _FASTDDS_RMWS:
        return None
    builtin = environ.get('FASTDDS_BUILTIN_TRANSPORTS', '')
    if environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE', '').upper() == 'LOCALHOST':
        return ('Fast DDS shared-memory transport in use (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST '
                'adds it): when a peer process dies, publishing can block this process, its safety '
                'watchdog included, for seconds; use another discovery range with '
                f'FASTDDS_BUILTIN_TRANSPORTS={SAFE_TRANSPORTS}')
    if not builtin and any(environ.get(v) for v in _PROFILE_VARS):
        return None
    kind = builtin.split('?', 1)[0].strip().upper() or 'DEFAULT'
    if kind not in _WITH_SHM:
        return None
    return (f'Fast DDS shared-memory transport in use (FASTDDS_BUILTIN_TRANSPORTS='
            f'{builtin or "unset"}): when a peer process dies, publishing can block this process, '
            f'its safety watchdog included, for seconds; set FASTDDS_BUILTIN_TRANSPORTS='
            f'{SAFE_TRANSPORTS} (scripts/env.sh does)')
