"""Helpers shared by the haptic_omni_driver tests: bag construction and the fake libHD build."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

from haptic_omni_driver.bag_types import POSE_TYPE, typestore
from haptic_omni_driver.bag_writer import write_bag

FIXTURES = Path(__file__).resolve().parent / 'fixtures'


def pose_msg(stamp_ns: int, xyz, frame: str = 'omni_base'):
    """A rosbags geometry_msgs/PoseStamped."""
    ts = typestore().types
    Time, Header = ts['builtin_interfaces/msg/Time'], ts['std_msgs/msg/Header']
    Pose, Point, Quat = (ts['geometry_msgs/msg/Pose'], ts['geometry_msgs/msg/Point'],
                         ts['geometry_msgs/msg/Quaternion'])
    sec, nsec = divmod(stamp_ns, 1_000_000_000)
    return ts['geometry_msgs/msg/PoseStamped'](Header(Time(sec, nsec), frame),
                                               Pose(Point(*map(float, xyz)), Quat(0.0, 0.0, 0.0, 1.0)))


def wrench_msg(stamp_ns: int, force, frame: str = 'omni_base'):
    """A rosbags geometry_msgs/WrenchStamped."""
    ts = typestore().types
    Time, Header, Vec = (ts['builtin_interfaces/msg/Time'], ts['std_msgs/msg/Header'],
                         ts['geometry_msgs/msg/Vector3'])
    sec, nsec = divmod(stamp_ns, 1_000_000_000)
    return ts['geometry_msgs/msg/WrenchStamped'](Header(Time(sec, nsec), frame),
                                                 ts['geometry_msgs/msg/Wrench'](Vec(*force),
                                                                                Vec(0.0, 0.0, 0.0)))


def make_pose_bag(path: Path, n: int = 50, period_ns: int = 1_000_000,
                  t0_ns: int = 1_700_000_000_123_000_000, topic: str = '/omni/pose') -> list:
    """Bag of ``n`` poses at ``period_ns`` (x = k mm); returns the rosbags messages written."""
    msgs = [pose_msg(t0_ns + k * period_ns, (k * 1e-3, 0.01, -0.02)) for k in range(n)]
    write_bag(path, [(topic, POSE_TYPE, t0_ns + k * period_ns, m) for k, m in enumerate(msgs)])
    return msgs


def build_fake_libhd(out_dir: Path) -> Path:
    """Compile test/fixtures/fake_hd.c into ``out_dir``/libHD.so with the system C compiler."""
    cc = shutil.which('cc') or shutil.which('gcc')
    assert cc, 'a C compiler (cc) is needed to build the fake libHD'
    out = Path(out_dir) / 'libHD.so'
    subprocess.run([cc, '-shared', '-fPIC', '-O2', '-o', str(out), str(FIXTURES / 'fake_hd.c'),
                    '-lpthread', '-lm'], check=True, capture_output=True)
    return out
