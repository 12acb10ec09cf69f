"""OpenHaptics backend: a PHANTOM Omni / Geomagic Touch through the HD C API (libHD) via ctypes.

libHD is loaded only when this backend is selected (the package installs and imports without
OpenHaptics). The servo loop is OpenHaptics' own 1 kHz scheduler: an asynchronous callback at the
highest priority reads the stylus transform and buttons inside hdBeginFrame/hdEndFrame, asks the
node's safety chain for the force to render and sets it with hdSetDoublev(HD_CURRENT_FORCE). Force
output (HD_FORCE_OUTPUT) is disabled at start and enabled only once the safety chain has accepted
a first valid command. Device errors are checked with hdGetError after every frame.

Constant values are those of OpenHaptics 3.x hdDefines.h / hdScheduler.h.
"""

from __future__ import annotations

import ctypes
import threading
import time

import numpy as np
from tissue_common.rotation import matrix_quaternion

from ..errors import DeviceError
from .base import Backend, BackendSink, Sample

# hdDefines.h (OpenHaptics 3.x)
HD_SUCCESS = 0x0000
HD_COMM_ERROR = 0x0302
HD_COMM_CONFIG_ERROR = 0x0303
HD_DEVICE_FAULT = 0x0300
HD_TIMER_ERROR = 0x0304
HD_CURRENT_BUTTONS = 0x2000
HD_CURRENT_POSITION = 0x2050
HD_CURRENT_TRANSFORM = 0x2052
HD_CURRENT_JOINT_ANGLES = 0x2100
HD_CURRENT_GIMBAL_ANGLES = 0x2150
HD_DEVICE_MODEL_TYPE = 0x2501
HD_DEVICE_SERIAL_NUMBER = 0x2504
HD_CALIBRATION_STYLE = 0x2555
HD_NOMINAL_MAX_FORCE = 0x2603
HD_NOMINAL_MAX_CONTINUOUS_FORCE = 0x2604
HD_CURRENT_FORCE = 0x2700
HD_FORCE_OUTPUT = 0x4000
HD_CALIBRATION_OK = 0x5000
HD_CALIBRATION_NEEDS_UPDATE = 0x5001
HD_CALIBRATION_NEEDS_MANUAL_INPUT = 0x5002
HD_DEVICE_BUTTON_1 = 1 << 0
HD_DEVICE_BUTTON_2 = 1 << 1
HD_INVALID_HANDLE = 0xFFFFFFFF
HD_MAX_SCHEDULER_PRIORITY = 0xFFFF
HD_DEFAULT_SCHEDULER_PRIORITY = 0x7FFF
# hdScheduler.h
HD_CALLBACK_DONE = 0
HD_CALLBACK_CONTINUE = 1
#: errors after which the device cannot go on (anything else is logged and counted)
FATAL_ERRORS = {HD_COMM_ERROR, HD_COMM_CONFIG_ERROR, HD_DEVICE_FAULT, HD_TIMER_ERROR}

MM = 1e-3  # libHD positions are millimetres


class HDErrorInfo(ctypes.Structure):
    """hdDefines.h HDErrorInfo."""

    _fields_ = [('errorCode', ctypes.c_uint), ('internalErrorCode', ctypes.c_int),
                ('hHD', ctypes.c_uint)]


HDSchedulerCallback = ctypes.CFUNCTYPE(ctypes.c_uint, ctypes.c_void_p)


def load_libhd(library: str = 'libHD.so') -> ctypes.CDLL:
    """Load libHD and declare the signatures used here; :class:`DeviceError` if impossible."""
    try:
        lib = ctypes.CDLL(library)
    except OSError as exc:
        raise DeviceError(
            f'cannot load the OpenHaptics library {library!r}: {exc}. Install OpenHaptics (Linux '
            f'"OpenHaptics for Linux Developer Edition" + the Touch device driver) and set the '
            f'library parameter to the full path of libHD.so (or add its folder to '
            f'LD_LIBRARY_PATH)') from exc
    sig = {
        'hdInitDevice': (ctypes.c_uint, [ctypes.c_char_p]),
        'hdDisableDevice': (None, [ctypes.c_uint]),
        'hdGetCurrentDevice': (ctypes.c_uint, []),
        'hdGetError': (HDErrorInfo, []),
        'hdGetErrorString': (ctypes.c_char_p, [ctypes.c_uint]),
        'hdBeginFrame': (None, [ctypes.c_uint]),
        'hdEndFrame': (None, [ctypes.c_uint]),
        'hdGetDoublev': (None, [ctypes.c_uint, ctypes.POINTER(ctypes.c_double)]),
        'hdGetIntegerv': (None, [ctypes.c_uint, ctypes.POINTER(ctypes.c_int)]),
        'hdGetString': (ctypes.c_char_p, [ctypes.c_uint]),
        'hdSetDoublev': (None, [ctypes.c_uint, ctypes.POINTER(ctypes.c_double)]),
        'hdEnable': (None, [ctypes.c_uint]),
        'hdDisable': (None, [ctypes.c_uint]),
        'hdCheckCalibration': (ctypes.c_uint, []),
        'hdUpdateCalibration': (None, [ctypes.c_uint]),
        'hdStartScheduler': (None, []),
        'hdStopScheduler': (None, []),
        'hdScheduleAsynchronous': (ctypes.c_ulong, [HDSchedulerCallback, ctypes.c_void_p,
                                                    ctypes.c_ushort]),
        'hdScheduleSynchronous': (None, [HDSchedulerCallback, ctypes.c_void_p, ctypes.c_ushort]),
        'hdUnschedule': (None, [ctypes.c_ulong]),
    }
    missing = []
    for name, (restype, argtypes) in sig.items():
        try:
            fn = getattr(lib, name)
        except AttributeError:
            missing.append(name)
            continue
        fn.restype, fn.argtypes = restype, argtypes
    if missing:
        raise DeviceError(f'{library} lacks OpenHaptics HD symbols: {", ".join(missing)}')
    return lib


def transform_to_pose(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position [m] and quaternion (x, y, z, w) from a column-major 4x4 HD transform in mm."""
    m = np.asarray(m, float).reshape(4, 4).T  # column-major (OpenGL) -> row-major
    rot = m[:3, :3]
    return m[:3, 3] * MM, matrix_quaternion(rot)


class OpenHapticsBackend(Backend):
    """The real device. Opened (library, device, calibration) in the constructor so that failures
    surface before the node spins; :meth:`start` schedules the servo callback."""

    name = 'openhaptics'
    has_device = True
    #: HD_CURRENT_JOINT_ANGLES (base, upper arm, forearm) then HD_CURRENT_GIMBAL_ANGLES, as the
    #: ROS 1 phantom_omni driver named them
    joint_names = ('waist', 'shoulder', 'elbow', 'wrist1', 'wrist2', 'wrist3')

    def __init__(self, library: str = 'libHD.so', device_name: str = '',
                 require_calibration: bool = False, clock_ns=time.time_ns) -> None:
        super().__init__()
        self.lib = load_libhd(library)
        self.clock_ns = clock_ns
        self._handle_sched = None
        self._callback = HDSchedulerCallback(self._servo)     # keep a reference: C holds it
        self._calib_cb = HDSchedulerCallback(self._check_calibration)
        self._sink: BackendSink | None = None
        self._force_on = False
        self._fatal: str | None = None
        self.errors = 0
        self.frames = 0
        self.calibration_status = HD_CALIBRATION_OK
        self._transform = (ctypes.c_double * 16)()
        self._joints = (ctypes.c_double * 3)()
        self._gimbal = (ctypes.c_double * 3)()
        self._buttons = ctypes.c_int(0)
        self._force = (ctypes.c_double * 3)()
        self._done = threading.Event()

        self.hhd = self.lib.hdInitDevice(device_name.encode() if device_name else None)
        err = self._error()
        if self.hhd == HD_INVALID_HANDLE or err is not None:
            raise DeviceError(f'hdInitDevice({device_name or "HD_DEFAULT_DEVICE"}) failed: '
                              f'{err or "invalid handle"}. Is the Omni plugged in and configured '
                              f'(Touch_Setup / PHANToM Configuration)?')
        serial = self.lib.hdGetString(HD_DEVICE_SERIAL_NUMBER) or b''
        self._error()  # a missing serial is not fatal
        self.source = serial.decode(errors='replace') or (device_name or 'default device')
        self.lib.hdDisable(HD_FORCE_OUTPUT)  # enabled only after the first valid command
        self.max_force = self._get_double(HD_NOMINAL_MAX_FORCE, 3.3)
        self.max_continuous_force = self._get_double(HD_NOMINAL_MAX_CONTINUOUS_FORCE, 0.88)
        self.require_calibration = require_calibration

    # -- helpers -------------------------------------------------------------------------------
    def _error(self) -> str | None:
        """Drain hdGetError; return a description of the first error (None if none)."""
        first = None
        for _ in range(32):
            info = self.lib.hdGetError()
            if info.errorCode == HD_SUCCESS:
                break
            text = (self.lib.hdGetErrorString(info.errorCode) or b'').decode(errors='replace')
            desc = f'HD error 0x{info.errorCode:04x} ({text}, internal {info.internalErrorCode})'
            if first is None:
                first = desc
                self._last_code = info.errorCode
        return first

    def _get_double(self, pname: int, default: float) -> float:
        val = ctypes.c_double(default)
        self.lib.hdGetDoublev(pname, ctypes.byref(val))
        if self._error() is not None:
            return default
        return float(val.value)

    def _check_calibration(self, _data) -> int:
        self.calibration_status = self.lib.hdCheckCalibration()
        if self.calibration_status == HD_CALIBRATION_NEEDS_UPDATE:
            style = ctypes.c_int(0)
            self.lib.hdGetIntegerv(HD_CALIBRATION_STYLE, ctypes.byref(style))
            self.lib.hdUpdateCalibration(style.value)
            self.calibration_status = self.lib.hdCheckCalibration()
        return HD_CALLBACK_DONE

    # -- servo loop (runs in the OpenHaptics scheduler thread) ---------------------------------
    def _servo(self, _data) -> int:
        try:
            lib, hhd = self.lib, self.hhd
            lib.hdBeginFrame(hhd)
            lib.hdGetDoublev(HD_CURRENT_TRANSFORM, self._transform)
            lib.hdGetDoublev(HD_CURRENT_JOINT_ANGLES, self._joints)
            lib.hdGetDoublev(HD_CURRENT_GIMBAL_ANGLES, self._gimbal)
            lib.hdGetIntegerv(HD_CURRENT_BUTTONS, ctypes.byref(self._buttons))
            force = self._sink.servo() if self._sink is not None else np.zeros(3)
            if not self._force_on and np.any(force != 0.0):
                lib.hdEnable(HD_FORCE_OUTPUT)
                self._force_on = True
            self._force[0], self._force[1], self._force[2] = (float(f) for f in force)
            lib.hdSetDoublev(HD_CURRENT_FORCE, self._force)
            lib.hdEndFrame(hhd)
            self.frames += 1
            err = self._error()
            if err is not None:
                self.errors += 1
                if getattr(self, '_last_code', None) in FATAL_ERRORS:
                    self._fatal = err
                    self._done.set()
                    return HD_CALLBACK_DONE
                if self._sink is not None and self.errors <= 10:
                    self._sink.log('warn', f'device: {err}')
            pos, quat = transform_to_pose(np.ctypeslib.as_array(self._transform))
            b = self._buttons.value
            if self._sink is not None:
                self._sink.on_sample(Sample(self.clock_ns(), pos, quat,
                                            (bool(b & HD_DEVICE_BUTTON_1),
                                             bool(b & HD_DEVICE_BUTTON_2)),
                                            joints=np.r_[self._joints[:], self._gimbal[:]]))
        except Exception as exc:  # noqa: BLE001 - never let an exception cross into C
            self._fatal = f'servo callback failed: {exc}'
            self._done.set()
            return HD_CALLBACK_DONE
        return HD_CALLBACK_DONE if self.stopping else HD_CALLBACK_CONTINUE

    # -- lifecycle -----------------------------------------------------------------------------
    def start(self, sink: BackendSink) -> None:
        """Schedule the servo callback, start the scheduler, check the calibration."""
        self._sink = sink
        self._handle_sched = self.lib.hdScheduleAsynchronous(self._callback, None,
                                                             HD_MAX_SCHEDULER_PRIORITY)
        self.lib.hdStartScheduler()
        err = self._error()
        if err is not None:
            raise DeviceError(f'hdStartScheduler failed: {err}')
        self.lib.hdScheduleSynchronous(self._calib_cb, None, HD_DEFAULT_SCHEDULER_PRIORITY)
        self.calibrated = self.calibration_status == HD_CALIBRATION_OK
        if not self.calibrated:
            what = ('needs manual input: put the stylus in the inkwell'
                    if self.calibration_status == HD_CALIBRATION_NEEDS_MANUAL_INPUT
                    else 'could not be updated')
            if self.require_calibration:
                raise DeviceError(f'device calibration {what} (require_calibration is true)')
            sink.log('warn', f'device calibration {what}; positions may be offset')
        # A watcher thread turns a fatal device error into a clean node exit.
        self._thread = threading.Thread(target=self._watch, args=(sink,), daemon=True,
                                        name='openhaptics_watch')
        self._thread.start()

    def _watch(self, sink: BackendSink) -> None:
        self._done.wait()
        if self._fatal is not None and not self.stopping:
            sink.on_finished(f'device failed: {self._fatal}', 1)

    def run(self, sink: BackendSink) -> None:  # pragma: no cover - start() is overridden
        raise NotImplementedError

    def stop(self, timeout: float = 2.0) -> None:
        """Zero the force, stop the scheduler and release the device."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._done.set()
        lib = self.lib
        lib.hdStopScheduler()
        if self._handle_sched:
            lib.hdUnschedule(self._handle_sched)
        lib.hdDisable(HD_FORCE_OUTPUT)
        if self.hhd != HD_INVALID_HANDLE:
            lib.hdDisableDevice(self.hhd)
        self._error()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)
