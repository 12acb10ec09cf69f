"""Message types of the bags and the rosbags typestore that (de)serializes them.

Shared by :mod:`.bag_writer`, :mod:`.bag_reader` and :mod:`.bag_recovery`: the topic message types
the driver and the recorder use and a ROS 2 Jazzy typestore with the ``tissue_msgs`` types added.
"""

from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING

from .errors import BagError

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

__all__ = ['POSE_TYPE', 'STATE_TYPE', 'WRENCH_TYPE', 'typestore']

POSE_TYPE = 'geometry_msgs/msg/PoseStamped'
WRENCH_TYPE = 'geometry_msgs/msg/WrenchStamped'
STATE_TYPE = 'tissue_msgs/msg/DeviceState'
_CUSTOM_TYPES = {STATE_TYPE: 'DeviceState.msg'}


def _find_msg_file(filename: str) -> Path:
    """The tissue_msgs .msg file: installed share/ copy (ament prefixes) or the source tree."""
    candidates = []
    for prefix in filter(None, os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep)):
        candidates.append(Path(prefix) / 'share' / 'tissue_msgs' / 'msg' / filename)
    here = Path(__file__).resolve()
    for parent in here.parents:
        candidates.append(parent / 'src' / 'tissue_msgs' / 'msg' / filename)
        candidates.append(parent / 'tissue_msgs' / 'msg' / filename)
    for path in candidates:
        if path.is_file():
            return path
    raise BagError(f'cannot find tissue_msgs/msg/{filename} (is tissue_msgs built and sourced?)')


@lru_cache(maxsize=1)
def typestore() -> Typestore:
    """A ROS 2 Jazzy typestore with the tissue_msgs types registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    types = {}
    for msgtype, filename in _CUSTOM_TYPES.items():
        types.update(get_types_from_msg(_find_msg_file(filename).read_text(), msgtype))
    store.register(types)
    return store
