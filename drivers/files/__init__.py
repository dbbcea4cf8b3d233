"""Files on disk: the dataset layout replay reads, tolerant CSV, TUM trajectories, ``dataset.yaml``,
image indexes, whole-stream series, LIDAR returns, and the EuRoC importer.
"""
