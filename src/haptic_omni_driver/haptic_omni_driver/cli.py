"""Start-up of the package's executables: a command line rcl refuses is one clear fatal line.

``rclpy.init`` raises ``RCLError`` (a traceback) for a ROS argument it cannot parse, e.g.
``--ros-args -p model:=`` (an override without a value). :func:`init_rclpy` turns that into one
``[FATAL]`` line naming the argument, so ``main`` can exit with the invalid-parameters code.
"""

from __future__ import annotations

import re

#: exit code of invalid parameters or command-line arguments (documented in the README)
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
