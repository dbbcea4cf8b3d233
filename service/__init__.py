"""The service: the asyncio daemon and the ``vtolpose`` command line.

``runtime`` (the loop that feeds sources through the fusion core to the outputs, live and
replay alike, its wiring from configuration, status and health), ``outputs`` (MAVLink to the
flight controller, Zenoh for the mapper and its client, the trajectory file, flight
recording), ``replay`` (offline replays, their report, fault injection, overlays, progress),
``calibration`` (calibration results as YAML and plots), ``bench`` (the benchmarks),
``mapping`` (the reference LIDAR mapper) and ``commands`` (one module per subcommand).
"""
