"""What leaves the service: MAVLink ODOMETRY, Zenoh poses and queries (and the mapper's client
for them), the TUM trajectory file, and crash-safe flight recordings.
"""
