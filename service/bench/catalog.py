"""The benchmarks by name, each with the first line of its docstring, for ``vtolpose bench --help`` without
loading them (``runner.BENCHMARKS`` holds the functions; tests/test_cli.py holds the two to each other)."""

from __future__ import annotations

SUMMARIES: dict[str, str] = {
    'filter-steps': 'Cost of one IMU propagation and one GPS update, both state variants.',
    'replay-speed': 'IMU+GPS replay speed as a multiple of real time (targets: book ≥ 300×, landfill ≥ 100×): the median of',
    'camera-update': 'One camera update (predict, associate, stacked EKF update) vs landmarks in the map.',
    'features': 'Feature extraction per 656 x 494 frame on one core, each detector, on rendered book and landfill frames.',
    'replay-camera': "Test 3 (imu,camera,gps, biases) on a rendered flight: the camera's work per frame on one core,",
    'camera-resolutions': 'Test 3 (imu,camera,gps, biases) on the book flight seen at 10 Hz through a 640 × 480 and a 1280 × 720',
    'camera': "The camera's figures together: extraction on one core, then Test 3's work per frame, speed and accuracy,",
    'odometry-encoding': "µs per ODOMETRY publish to one endpoint, pymavlink's framing and the hand-built one, unsigned and signed.",
    'runtime-latency': 'IMU sample in → ODOMETRY and Zenoh pose out, p50/p99, with SIFT at 7.5 Hz in camera threads, then processes (targets: p99 ≤ 1 ms, handling p50 ≤ 0.2 ms).',
    'latency-floor': "The pose's handling with its encodings, then its prediction too, stood in for (camera process, SIFT at 7.5 Hz): the floor under the 0.2-ms target.",
    'pose-encoding': 'json.dumps(pose_message) against PoseJson, and PoseJson with the covariance written ahead: warm, and paced at 125 Hz.',
    'runtime-hour': 'One hour of IMU+GPS (landfill) through the runtime at full speed: memory and buffers stay flat.',
    'soak-camera': 'One hour of IMU+camera+GPS (landfill, ORB) through the runtime: memory, landmarks, history stay bounded.',
    'fault-targets': 'GPS back after a 30 s loss, NEES through a 30 s camera loss, a 20 m GPS jump: Test 3, SIFT, vs fault-free runs.',
    'fault-table': 'Each fault kind: largest error, quality, recovery, resets, counts (the figures behind the table in docs/faults.md).',
    'sensor-lies': 'The three lies of the fault table (and the GPS lie from mid-flight), each against the clean flight.',
    'euroc': 'Every EuRoC flight under ../shared/data: import, replay both models, score (the table of docs/results.md).',
    'euroc-reference': "Each EuRoC flight: vtolpose's IMU+GPS replay speed (both variants) and the reference's, same inputs, same run; then both sides' position scored alike.",
    'euroc-causes': "Each EuRoC flight: the default model's ratio scored three ways, then with the GPS timing and the IMU's",
    'zenoh-queries': 'Pose lateness in the daemon and losses at a subscriber while a client floods the queryables.',
    'memory-paced': 'RSS and Python allocations per minute of a paced replay with both outputs, after the history fills.',
    'smoothing-sim': 'Simulated Test 1 and Test 3 with --smooth from 15 s (target: smoothed ≤ 0.7 × filtered).',
    'smoothing-landmarks': 'Book Test 3: the robot-block smoother against the exact full-state one (landmarks kept).',
    'smoothing-hour': 'One hour of IMU+GPS (landfill): peak memory of replay and of replay --smooth, each in its own process.',
    'smoothing-latency': 'Pose latency (IMU in → MAVLink and Zenoh out) with the live fixed-lag smoother on, then off.',
    'batch': "`vtolpose batch`: 16 short flights on 1 and 2 workers (speed-up target ≥ 1.8×), the engine's overhead per flight against a plain loop",
    'results': "The tables of docs/results.md again: Tests 1-3 and the starts in the air (the doc's figures beside).",
    'camera-matrix': 'Tests 1–3 per cell of :data:`CELLS`; prints progress per cell, then the table (long: rendered flights).',
    'camera-clock': 'Base and aggressive cells, Tests 2 and 3: the camera time offset right and 10 ms wrong, its estimation off and on.',
    'camera-mounting': 'Base and aggressive cells, Tests 2 and 3: the camera mounting right and 1° wrong (and 10 ms wrong too), its estimation off and on.',
    'cold-start': "First replay with an empty kernel cache against the second (target ≤ 1.5 ×), compile time, daemon's first pose.",
}

# Long runs (a simulated hour, rendered flights replayed many times): only when named or with --all.
LONG_BENCHMARKS = (
    'runtime-hour', 'soak-camera', 'fault-targets', 'fault-table', 'sensor-lies', 'euroc', 'euroc-reference',
    'euroc-causes', 'zenoh-queries', 'memory-paced', 'smoothing-sim', 'smoothing-landmarks', 'smoothing-hour',
    'smoothing-latency', 'batch', 'results', 'camera-matrix', 'cold-start', 'camera-clock', 'camera-mounting',
)

# Several of the above together (camera: features, replay-camera, then camera-resolutions): only when named.
GROUPS = ('camera',)
