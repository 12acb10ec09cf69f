"""The OpenHaptics backend's ctypes path against a fake libHD compiled from C (in-process)."""

import ctypes
import math
import threading
import time

import numpy as np
import pytest

from tissue_common.rotation import matrix_quaternion

from haptic_omni_driver.backends.openhaptics import OpenHapticsBackend, transform_to_pose
from haptic_omni_driver.errors import DeviceError
from haptic_omni_driver.safety import ForceSafety, SafetyConfig
from omni_test_utils import build_fake_libhd


@pytest.fixture(scope='module')
def fake_libhd(tmp_path_factory):
    return build_fake_libhd(tmp_path_factory.mktemp('fakehd'))


@pytest.fixture
def fake_env(monkeypatch):
    for key in ('FAKEHD_FAIL_INIT', 'FAKEHD_CALIBRATION', 'FAKEHD_FAIL_AFTER', 'FAKEHD_FORCE_LOG',
                'FAKEHD_AMPLITUDE'):
        monkeypatch.delenv(key, raising=False)
    monkeypatch.setenv('FAKEHD_POSITION', '12.5,-30,45')
    monkeypatch.setenv('FAKEHD_BUTTONS', '2')
    return monkeypatch


class Sink:
    """Stands in for the node: safety chain + sample collection."""

    def __init__(self, **safety):
        # the test's commands answer no pose: no stale-reply window (tested in test_safety_battery)
        self.safety = ForceSafety(SafetyConfig(**{'max_command_lag': 0.0, **safety}))
        self.samples = []
        self.logs = []
        self.finished = None
        self.done = threading.Event()

    def on_sample(self, s):
        self.samples.append(s)

    def servo(self):
        return self.safety.output(time.monotonic())

    def log(self, level, text):
        self.logs.append((level, text))

    def on_finished(self, summary, code):
        self.finished = (summary, code)
        self.done.set()


def wait(pred, timeout=2.0):
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.002)
    return True


def last_force(backend):
    out = (ctypes.c_double * 3)()
    backend.lib.fakehd_last_force(out)
    return np.array(out)


def test_missing_library_is_a_device_error_with_install_hint():
    with pytest.raises(DeviceError, match='cannot load the OpenHaptics library.*Install OpenHaptics'):
        OpenHapticsBackend('/nonexistent/libHD.so')


def test_library_without_hd_symbols_is_rejected():
    with pytest.raises(DeviceError, match='lacks OpenHaptics HD symbols'):
        OpenHapticsBackend('libm.so.6')


def test_init_failure_reports_the_hd_error(fake_libhd, fake_env):
    fake_env.setenv('FAKEHD_FAIL_INIT', '1')
    with pytest.raises(DeviceError, match=r'hdInitDevice.*0x0303'):
        OpenHapticsBackend(str(fake_libhd))


def test_servo_loop_pose_in_metres_and_force_enabled_only_after_first_command(fake_libhd,
                                                                             fake_env):
    backend = OpenHapticsBackend(str(fake_libhd))
    sink = Sink(ramp_time=0.0, watchdog_timeout=0.02)
    try:
        backend.start(sink)
        assert backend.source == 'FAKE-00042' and backend.calibrated
        assert wait(lambda: len(sink.samples) >= 50, 30.0)
        s = sink.samples[-1]
        assert s.position == pytest.approx([0.0125, -0.030, 0.045], abs=1e-12)
        assert s.orientation == pytest.approx([0, 0, 0, 1])
        assert s.buttons == (False, True)
        assert backend.lib.fakehd_force_enabled() == 0  # no command yet: output stays disabled
        # command until the device renders the force: should this thread wait for a core longer
        # than the 20 ms watchdog, the force is zeroed again before it can be seen
        def commanded(pred):
            sink.safety.command([0.3, -0.1, 0.0], 'omni_base', time.monotonic())
            return pred()

        assert wait(lambda: commanded(lambda: backend.lib.fakehd_force_enabled() == 1), 30.0)
        assert wait(lambda: commanded(lambda: last_force(backend) == pytest.approx([0.3, -0.1, 0.0])),
                    30.0)
        # commands stop: the watchdog zeroes the force (its timing is unit-tested with a controlled
        # clock in test_safety.py; here the servo thread may wait for a core)
        assert wait(lambda: np.all(last_force(backend) == 0.0), 30.0)
        # the scheduler keeps calling the servo callback
        n0 = backend.lib.fakehd_frames()
        assert wait(lambda: backend.lib.fakehd_frames() >= n0 + 50, 30.0)
    finally:
        backend.stop()
    assert backend.lib.fakehd_force_enabled() == 0


def test_manual_calibration_required_is_an_error(fake_libhd, fake_env):
    fake_env.setenv('FAKEHD_CALIBRATION', 'manual')
    backend = OpenHapticsBackend(str(fake_libhd), require_calibration=True)
    try:
        with pytest.raises(DeviceError, match='inkwell'):
            backend.start(Sink())
    finally:
        backend.stop()


def test_calibration_update_is_applied_and_manual_input_is_a_warning(fake_libhd, fake_env):
    fake_env.setenv('FAKEHD_CALIBRATION', 'update')
    backend = OpenHapticsBackend(str(fake_libhd))
    try:
        backend.start(Sink())
        assert backend.calibrated  # hdUpdateCalibration fixed it
    finally:
        backend.stop()
    fake_env.setenv('FAKEHD_CALIBRATION', 'manual')
    backend = OpenHapticsBackend(str(fake_libhd))
    sink = Sink()
    try:
        backend.start(sink)
        assert not backend.calibrated
        assert any('inkwell' in text for _, text in sink.logs)
    finally:
        backend.stop()


def test_communication_error_stops_the_backend_with_failure(fake_libhd, fake_env):
    fake_env.setenv('FAKEHD_FAIL_AFTER', '30')
    backend = OpenHapticsBackend(str(fake_libhd))
    sink = Sink()
    try:
        backend.start(sink)
        assert sink.done.wait(30.0)
        assert sink.finished[1] == 1 and '0x0302' in sink.finished[0]
    finally:
        backend.stop()


def test_transform_rotation_and_translation_conversion():
    c, s = math.cos(math.pi / 3), math.sin(math.pi / 3)
    rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])  # 60 deg about z
    m = np.eye(4)
    m[:3, :3] = rz
    m[:3, 3] = [10.0, 20.0, -5.0]  # mm
    pos, q = transform_to_pose(m.T.reshape(-1))  # column-major, as libHD returns it
    assert pos == pytest.approx([0.010, 0.020, -0.005])
    assert q == pytest.approx([0, 0, math.sin(math.pi / 6), math.cos(math.pi / 6)])
    # a 180 deg rotation about x (trace -1: the non-trivial branch)
    q = matrix_quaternion(np.diag([1.0, -1.0, -1.0]))
    assert abs(q[0]) == pytest.approx(1.0)
