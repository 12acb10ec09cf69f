"""omni_bag_recover: make an unfinished bag (recorder killed, power lost, disk full) complete.

Salvages every complete chunk of the bag's ``.mcap`` (everything ``omni_record`` had flushed),
writes a new ``.mcap`` with summary and end magic and a ``metadata.yaml`` whose counts match, like
``ros2 bag reindex`` but also for a file that ends mid-record. In place by default (the new file is
completed beside the old one before it replaces it), or into a new folder with ``--output``.

    ros2 run haptic_omni_driver omni_bag_recover my_session
    ros2 run haptic_omni_driver omni_bag_recover /media/ro/my_session --output my_session_recovered

Exit codes: 0 recovered (or already complete: nothing changed), 1 nothing recoverable or the result
cannot be written (missing, not a bag, not MCAP, no complete message, read-only), 2 bad usage.
"""

from __future__ import annotations

import argparse
import sys

from .bag_recovery import Recovery, recover_bag
from .errors import DriverError, OutputError

EXIT_OK, EXIT_INPUT, EXIT_USAGE = 0, 1, 2


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog='omni_bag_recover',
        description='Make an unfinished rosbag2 MCAP bag (recorder killed, power lost) complete: '
                    'salvage every complete chunk, write the MCAP summary and metadata.yaml.')
    ap.add_argument('bag', help='bag folder (holding one .mcap, metadata.yaml may be missing)')
    ap.add_argument('-o', '--output', default=None,
                    help='write the recovered bag to this new folder and leave BAG untouched '
                         '(default: recover in place)')
    return ap


def _summary(result: Recovery) -> str:
    counts = ', '.join(f'{t}: {n}' for t, n in result.counts.items()) or 'nothing'
    if result.complete:
        return f'{result.path} is a complete bag ({result.messages} messages: {counts}); unchanged'
    lost = f'; reading stopped at a {result.stop}' if result.stop else ''
    skipped = (f'; {result.skipped} messages skipped (their channel record was lost)'
               if result.skipped else '')
    return (f'recovered {result.messages} messages ({counts}) from {result.source} into '
            f'{result.path}{lost}{skipped}')


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``omni_bag_recover``; returns the exit code (see the module docstring)."""
    args = _parser().parse_args(argv)  # exits 2 on bad usage
    try:
        result = recover_bag(args.bag, args.output)
    except OutputError as exc:
        hint = '' if args.output else ' (use --output to write the recovered bag elsewhere)'
        print(f'omni_bag_recover: error: {exc}{hint}', file=sys.stderr)
        return EXIT_INPUT
    except DriverError as exc:
        print(f'omni_bag_recover: error: {exc}', file=sys.stderr)
        return EXIT_INPUT
    print(f'omni_bag_recover: {_summary(result)}')
    return EXIT_OK


if __name__ == '__main__':
    sys.exit(main())
