"""Parameter declarations of omni_driver and omni_record in one place (descriptors, ranges).

Each entry: name -> (default, description, range or choices or None, read_only). Ranges become
FloatingPointRange / IntegerRange on the descriptor (rclpy enforces them on every set); string
choices are checked by the node's set-parameters callback and at start-up. A string array whose
default is empty is named in STRING_ARRAYS (rclpy cannot tell its type from the default).
"""

from __future__ import annotations

from typing import Any

from .safety import (CONTINUOUS_FORCE_LIMIT, DEFAULT_COMMAND_LAG, DEFAULT_FORCE_RATE, FORCE_RATE_RANGE,
                     HARD_FORCE_LIMIT, WATCHDOG_RANGE)

# name: (default, description, range/choices, read_only)
DRIVER_PARAMS: dict[str, tuple[Any, str, Any, bool]] = {
    # -- common ---------------------------------------------------------------------------------
    'backend': ('scripted', 'device backend: openhaptics | replay | scripted',
                ('openhaptics', 'replay', 'scripted'), True),
    'frame_id': ('omni_base', 'device base frame of omni/pose and of accepted force commands',
                 None, True),
    'reliable': (False, 'reliable QoS on omni/pose and omni/force_feedback (default best effort; '
                        'lockstep replay always uses reliable)', None, True),
    'qos_depth': (1, 'history depth of omni/pose and omni/force_feedback (lockstep: 1000)',
                  (1, 10000), True),
    'state_rate': (100.0, '[Hz] omni/state publish rate (also published on every change)',
                   (1.0, 1000.0), True),
    'servo_rate': (1000.0, '[Hz] virtual servo loop (safety chain) rate for replay/scripted',
                   (100.0, 2000.0), True),
    'diagnostics_rate': (1.0, '[Hz] /diagnostics publish rate (0 = off)', (0.0, 10.0), True),
    'force_limit': (CONTINUOUS_FORCE_LIMIT, f'[N] force norm clamp (Omni continuous 0.88 N, never '
                                            f'above {HARD_FORCE_LIMIT} N peak)',
                    (0.0, HARD_FORCE_LIMIT), False),
    'ramp_time': (0.5, '[s] linear force ramp-up after enabling (and after a watchdog trip)',
                  (0.0, 10.0), False),
    'watchdog_timeout': (0.02, '[s] force zeroed when no valid command arrived for this long',
                         WATCHDOG_RANGE, False),
    'max_command_lag': (DEFAULT_COMMAND_LAG, '[s] reject force replies whose stamp is not within this of the '
                             'newest pose (older: stale; newer, or before the first pose: they answer '
                             'no pose); 0 = off', (0.0, 10.0), False),
    'max_force_rate': (DEFAULT_FORCE_RATE, '[N/s] force-rate (impulse) limit: the output force '
                                           'changes by at most this times the time since the '
                                           'previous output (zeroing is immediate); 0 = off',
                       FORCE_RATE_RANGE, False),
    'accept_empty_frame': (True, "accept force commands with an empty frame_id as device frame",
                           None, False),
    'loop': (False, 'replay/scripted: start again at the end', None, True),
    'exit_on_end': (False, 'replay/scripted (loop false): exit with code 0 at the end instead of '
                           'idling (replay) or resting at the last point (scripted)', None, True),
    'wait_for_subscribers': (0, 'replay/scripted: wait for this many omni/pose subscribers before '
                                'starting',
                             (0, 100), True),
    # -- CRTK -----------------------------------------------------------------------------------
    'crtk': (True, 'also offer the CRTK interface: measured_cp, measured_cv, measured_js '
                   '(openhaptics), servo_cf, operating_state, state_command, jaw/measured_js, '
                   'jaw/servo_jp', None, True),
    'crtk_rate': (500.0, '[Hz] CRTK: measured_cp / measured_cv / measured_js rate (at most the '
                         'device\'s)', (1.0, 2000.0), True),
    'velocity_cutoff': (30.0, '[Hz] CRTK: cut-off of the tracking filter behind measured_cv (the '
                              'simulator\'s renderer uses the same filter)', (1.0, 200.0), True),
    'stylus_frame': ('omni_stylus', 'CRTK: child frame of frame_id that /tf moves with the stylus tip '
                                    '(where tf2 is installed; one per instrument)', None, True),
    'jaw_button': (1, 'CRTK: the stylus button that closes the jaw (jaw/measured_js 0 while it is '
                      'down): 1 | 2', (1, 2), True),
    'jaw_open_angle': (1.0, '[rad] CRTK: jaw/measured_js while the jaw button is up; jaw/servo_jp '
                            'accepts 0 (closed) … this', (0.2, 3.14), True),
    'start_state': ('ENABLED', 'CRTK operating state at start: ENABLED (renders force as soon as '
                               'commands come) | DISABLED (waits for an enable on state_command)',
                    ('ENABLED', 'DISABLED'), True),
    # -- replay ---------------------------------------------------------------------------------
    'bag': ('', 'replay: rosbag2 bag folder (metadata.yaml + .mcap)', None, True),
    'pose_topic_in_bag': ('/omni/pose', 'replay: PoseStamped topic name inside the bag', None, True),
    'state_topic_in_bag': ('/omni/state', 'replay: DeviceState topic in the bag for buttons '
                                          '(optional)', None, True),
    'replay_mode': ('timed', 'replay: timed (recorded timing / rate) | lockstep (wait for each '
                             'force reply)', ('timed', 'lockstep'), True),
    'rate': (1.0, 'replay: timing factor (2.0 = twice as fast) in timed mode', (0.01, 100.0), True),
    'lockstep_timeout': (1.0, '[s] replay lockstep: wait this long for a force reply',
                         (0.001, 60.0), True),
    'lockstep_timeout_action': ('continue', 'replay lockstep on timeout: continue | resend | abort '
                                            '(exit code 3)', ('continue', 'resend', 'abort'), True),
    'lockstep_max_resends': (3, 'replay lockstep: resends per pose with action resend', (0, 100),
                             True),
    # -- scripted -------------------------------------------------------------------------------
    'publish_rate': (1000.0, '[Hz] scripted: pose rate', (1.0, 10000.0), True),
    'home': ([0.0, 0.06, 0.0], '[m] scripted: start/end point (device frame)', None, True),
    'target': ([0.0, 0.0, 0.0], '[m] scripted: surface point to press (device frame)', None, True),
    'press_axis': ([0.0, -1.0, 0.0], 'scripted: pressing direction (device frame)', None, True),
    'pull_axis': ([1.0, 0.0, 0.0], 'scripted: lateral pull/sweep direction', None, True),
    'approach_height': (0.01, '[m] scripted: height above the surface before pressing',
                        (0.0, 0.2), True),
    'press_depth': (0.008, '[m] scripted: indentation depth', (0.0, 0.2), True),
    'pull_distance': (0.01, '[m] scripted: lateral drag while pressed', (0.0, 0.2), True),
    'sweep_depth': (0.003, '[m] scripted: indentation during the sweep', (0.0, 0.2), True),
    'sweep_length': (0.04, '[m] scripted: sweep stroke length', (0.0, 0.2), True),
    'approach_time': (1.0, '[s] scripted: approach duration', (0.01, 600.0), True),
    'press_time': (0.8, '[s] scripted: press duration', (0.01, 600.0), True),
    'hold_time': (1.0, '[s] scripted: hold duration', (0.01, 600.0), True),
    'pull_time': (0.8, '[s] scripted: pull duration', (0.01, 600.0), True),
    'release_time': (0.6, '[s] scripted: release (and sweep descent/ascent) duration',
                     (0.01, 600.0), True),
    'sweep_time': (2.0, '[s] scripted: sweep stroke duration', (0.01, 600.0), True),
    'return_time': (1.0, '[s] scripted: return-home duration', (0.01, 600.0), True),
    'tremor_amplitude': (1.5e-4, '[m] scripted: physiological tremor peak per axis (8-12 Hz); 0 = '
                                 'off', (0.0, 0.002), True),
    'quantisation': (0.0, '[m] scripted: encoder resolution (Omni ~5.5e-5); 0 = continuous',
                     (0.0, 0.001), True),
    'seed': (0, 'scripted: random seed (tremor phases)', (0, 2 ** 31 - 1), True),
    'script': ([], 'scripted: a script of its own, one step per entry, from home: "move|press|lift '
                   'x y z T" (to that device-frame point [m] in T [s]), "hold|close|open T" (stay; '
                   'close/open: button 1, the jaw, down/up from then on); [] = the built-in script',
               None, True),
    # -- openhaptics ----------------------------------------------------------------------------
    'library': ('libHD.so', 'openhaptics: libHD file name or full path', None, True),
    'device_name': ('', 'openhaptics: device name from Touch_Setup ("" = HD_DEFAULT_DEVICE)',
                    None, True),
    'require_calibration': (False, 'openhaptics: exit if the device is not calibrated', None,
                            True),
}

#: DRIVER_PARAMS entries declared as string arrays: from an empty default rclpy would infer a byte
#: array and refuse any string
STRING_ARRAYS = ('script',)

RECORDER_PARAMS: dict[str, tuple[Any, str, Any, bool]] = {
    'output': ('', 'bag folder to create ("" = omni_YYYYmmdd_HHMMSS in the working directory)',
               None, True),
    'topics': (['omni/pose', 'omni/force_feedback', 'omni/state'],
               'topics to record (relative names resolve in the node namespace)', None, True),
    'reliable': (False, 'reliable subscriptions for pose/force (needed to record a reliable '
                        'lockstep stream without loss; best effort matches any publisher)', None,
                 True),
    'qos_depth': (1000, 'subscription history depth', (1, 100000), True),
    'duration': (0.0, '[s] stop after this long (0 = until Ctrl-C)', (0.0, 1e6), True),
    'max_messages': (0, 'stop after this many messages (0 = unlimited)', (0, 2 ** 31 - 1), True),
    'wait_for_topics': (True, 'start the duration clock at the first message', None, True),
    'progress_period': (5.0, '[s] log the message counts this often while they change (0 = off)',
                        (0.0, 3600.0), True),
    'metadata_version': (9, 'rosbag2 metadata version (8 = Humble/Iron readers, 9 = Jazzy)', (8, 9),
                         True),
    'flush_period': (0.5, '[s] write the open chunk to the .mcap and fsync it this often: a crash '
                          '(kill, power loss) loses at most about this much (omni_bag_recover '
                          'restores the rest)', (0.05, 60.0), True),
}
