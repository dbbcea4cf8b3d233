"""The reference LIDAR mapper: the dataset's returns placed with poses from a trajectory or the service.

``poses`` gives a pose to every return at its own time, from a trajectory file, the dataset's
truth or a running vtolpose over Zenoh (the public ``vtolpose.client.PoseClient``, one
``trajectory()`` query per scan, as the README tells a mapper to); ``mapper`` runs the scans
through a height grid (``vtolpose.estimator.mapping``); ``report`` and ``plots`` turn a map into
figures, a table and PNGs. ``vtolpose map`` and ``vtolpose demo --lidar`` are built on it.
"""
